"""What produced a committed result: the machine, its kernels, the library versions and the commit.

A micro model's per-pair outcome depends on the CPU (another instruction set or thread count moves
the feature maps by 1e-6, and FPFH and RANSAC can turn that into other matches, docs/reproducibility.md),
so every result JSON that :func:`~freereg_lib.training.evaluate_split.publish` writes carries
:func:`machine_record` under ``provenance``:

    from freereg_lib.training.provenance import machine_record
    machine_record()["cpu"]["model"]
"""
from __future__ import annotations

import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

# The instruction-set flags that choose a kernel path in torch, oneDNN, OpenBLAS, NumPy or Open3D.
ISA_FLAGS = ("sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512vl", "avx512_vnni",
             "avx512_bf16", "amx_tile", "neon", "asimd", "sve")
PACKAGES = ("torch", "numpy", "scipy", "open3d", "opencv-python-headless", "diffusers", "transformers", "matplotlib",
            "Pillow")
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "ATEN_CPU_CAPABILITY",
                    "ONEDNN_MAX_CPU_ISA", "OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")


def cpu_info(cpuinfo: str | None = None) -> dict:
    """``{"model", "isa_flags", "logical_cores"}`` of this machine (``/proc/cpuinfo`` on Linux; the model
    from :mod:`platform` elsewhere, flags then unknown: ``None``)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    flags = (fields.get("flags") or fields.get("Features") or "").split()
    return {"model": fields.get("model name") or platform.processor() or platform.machine(),
            "isa_flags": [f for f in ISA_FLAGS if f in flags] if flags else None,
            "logical_cores": os.cpu_count()}


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _kernels() -> dict:
    """The kernel choices of the loaded numeric libraries (only those already imported, so a light
    command does not pay for torch)."""
    out: dict = {}
    torch = sys.modules.get("torch")
    if torch is not None:
        out["torch_threads"] = torch.get_num_threads()
        out["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
        out["onednn_enabled"] = bool(torch.backends.mkldnn.enabled)
    np = sys.modules.get("numpy")
    if np is not None:
        try:
            blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
            out["numpy_blas"] = f"{blas.get('name')} {blas.get('version')}"
        except Exception:  # older NumPy: no dict mode
            out["numpy_blas"] = None
    return out


def git_commit(cwd: str | Path | None = None) -> dict:
    """``{"commit", "dirty"}`` of the checkout at ``cwd`` (``None`` outside a git checkout)."""
    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None

    head = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if head else None
    return {"commit": head, "dirty": None if status is None else bool(status)}


def machine_record(cwd: str | Path | None = None) -> dict:
    """Everything that decides a result's last bits on this machine: CPU model and instruction-set
    flags, thread counts and kernel settings, package versions, Python, OS, and the git commit."""
    return {"cpu": cpu_info(), "kernels": _kernels(),
            "environment": {k: os.environ[k] for k in THREAD_VARIABLES if k in os.environ},
            "packages": {name: _version(name) for name in PACKAGES},
            "python": platform.python_version(), "os": f"{platform.system()} {platform.release()}",
            "git": git_commit(cwd)}
