"""The pipeline benchmark's instruments: what machine it ran on, and memory meters (Python's
allocations by ``tracemalloc``, the process's resident set from ``/proc``)."""
from __future__ import annotations

import contextlib
import ctypes
import datetime
import gc
import os
import platform
import tracemalloc

import numpy as np

MIB = 1024.0 ** 2


# ---------------------------------------------------------------------------------------
# The device.

def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else what ``platform`` knows)."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def device_info(mode: str, device: str | None) -> dict:
    import cv2
    import open3d
    import torch

    from freereg_lib.commands.cluster import available_cores

    n_cpu = available_cores()
    info = {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "mode": mode,
        "cpu": cpu_model(),
        "cpu_cores": n_cpu,
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "numpy": np.__version__,
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "open3d": open3d.__version__,
        "gpu": None,
    }
    if device is not None and device.startswith("cuda") and torch.cuda.is_available():
        idx = torch.device(device).index or 0
        prop = torch.cuda.get_device_properties(idx)
        info["gpu"] = f"{prop.name} ({prop.total_memory / 1024**3:.1f} GiB, CUDA {torch.version.cuda})"
    return info


def format_device(info: dict) -> str:
    lines = [
        f"device: CPU {info['cpu']} ({info['cpu_cores']} cores available, load average "
        f"{' '.join(str(x) for x in info['load_average'])})",
        f"        torch {info['torch']} ({info['torch_threads']} threads), numpy {info['numpy']} "
        f"(OPENBLAS_NUM_THREADS={info['OPENBLAS_NUM_THREADS']}), OpenCV {info['opencv']} "
        f"({info['opencv_threads']} threads), Open3D {info['open3d']}, Python {info['python']}",
    ]
    if info.get("gpu"):
        lines.append(f"        GPU {info['gpu']}")
    lines.append(f"date:   {info['date']}    mode: {info['mode']}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------
# Memory meters.

def _malloc_trim() -> None:
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _proc_status_kib(key: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


class Meter:
    """Peak memory of one call: tracemalloc, VmHWM and (on CUDA) the torch allocator."""

    def __init__(self, cuda: bool = False):
        self.cuda = cuda
        self.hwm_ok = _reset_hwm()

    @contextlib.contextmanager
    def measure(self, out: dict):
        gc.collect()
        # What survived is long-lived (modules, models, earlier stages' results): frozen, the next
        # collect scans only what is new. A full one took 0.18 s with torch and diffusers loaded.
        gc.freeze()
        _malloc_trim()
        if self.cuda:
            import torch

            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        tracemalloc.reset_peak()
        py0 = tracemalloc.get_traced_memory()[0]
        rss0 = _proc_status_kib("VmRSS") if self.hwm_ok and _reset_hwm() else None
        try:
            yield
        finally:
            if self.cuda:
                import torch

                torch.cuda.synchronize()
                out["gpu_peak_mib"] = torch.cuda.max_memory_allocated() / MIB
            out["py_peak_mib"] = max(tracemalloc.get_traced_memory()[1] - py0, 0) / MIB
            hwm = _proc_status_kib("VmHWM") if rss0 is not None else None
            out["rss_peak_mib"] = max(hwm - rss0, 0) / 1024.0 if hwm is not None else None
