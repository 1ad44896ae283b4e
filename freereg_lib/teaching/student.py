"""The student's process: run each exercise's solution code, call it on the grader's inputs, write the answers.

The grader copies this module, :mod:`.sandbox` and :mod:`.wire` (all three import only the
standard library and NumPy) into the job's folder and starts ``python -I -S`` on them, in a
session of its own, with an import path of the standard library and NumPy only: ``freereg_lib``
is not on it, and neither are the project's other packages. Before any student code runs the
process puts its resource limits on (:func:`.sandbox.limit`) and confines itself with
Landlock (:func:`.sandbox.confine`): it may read the standard library, NumPy and the system's
libraries, and write only its scratch folder, so the library's files (and the answer key, and
the rest of your files) cannot be read, by import or by path.

Then, exercise by exercise, it runs the solution code the grader extracted from the notebook
(in a fresh namespace holding ``numpy as np``), calls the function on the inputs the grader
drew and writes what came back, as data, one ``.npz`` per exercise as it finishes. It decides
nothing: the grading process compares those numbers with the library's answers. Through a pipe
it tells the grader when each exercise starts (each has its own time budget) and each attempt
to read or write outside its folders (:func:`watch`).
"""
from __future__ import annotations

import builtins
import contextlib
import copy
import io
import json
import os
import signal
import sys
import threading
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import sandbox, wire

SYSTEM = ("/usr", "/lib", "/lib64", "/lib32", "/bin")
# Of /etc, /proc, /sys and /dev only what Python and NumPy read: the rest holds root's secrets
# (/etc/shadow, the grader's /proc/<pid>/environ, raw disks), which uid 0 may read by ownership alone.
SYSTEM_FILES = ("/etc/ld.so.cache", "/etc/ld.so.conf", "/etc/ld.so.conf.d", "/etc/localtime", "/proc/cpuinfo",
                "/proc/meminfo", "/proc/stat", "/sys/devices/system/cpu", "/dev/null", "/dev/zero", "/dev/urandom",
                "/dev/random")


@contextlib.contextmanager
def _time_limit(seconds: float | None):
    """A soft per-call limit (the code can catch it: the grader's hard limit is the real one)."""
    if not (seconds and hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()):
        yield
        return

    def expired(signum, frame):
        raise TimeoutError(f"no answer within {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@contextlib.contextmanager
def _quiet():
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
            warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def describe(e: BaseException) -> str:
    text = " ".join((f"{type(e).__name__}: {e}" if str(e) else type(e).__name__).split())
    return text if len(text) <= 200 else text[:197] + "..."


def _plain(value: Any, depth: int = 0) -> Any:
    """What the student's function returned, as data the wire carries (or TypeError)."""
    try:
        wire.encode(value, {})
        return value
    except wire.WireError:
        pass
    if depth < 4 and isinstance(value, (tuple, list)):
        return type(value)(_plain(v, depth + 1) for v in value)
    try:
        out = np.asarray(value)
    except Exception:  # noqa: BLE001
        out = None
    if out is None or out.dtype.kind not in "biuf":
        raise TypeError(f"it returned a {type(value).__name__}, not numbers")
    return out


def answer(f: Callable, args: tuple, timeout: float | None) -> dict:
    """One call of the student's function, as a record: ``{"value": ...}`` or ``{"error", "kind"}``."""
    try:
        with _quiet(), _time_limit(timeout):
            value = f(*copy.deepcopy(args))
        return {"value": _plain(value)}
    except BaseException as e:  # noqa: BLE001 - the student's crash is a result
        if isinstance(e, KeyboardInterrupt):
            raise
        return {"error": describe(e), "kind": type(e).__name__}


def solve(name: str, source: str, cases: list, timeout: float | None) -> dict:
    """Run one exercise's solution code alone, then its function on every call of every case."""
    namespace = {"__name__": "__student__", "__builtins__": builtins, "np": np}
    try:
        code = compile(source, f"<solution of {name}>", "exec")
        with _quiet(), _time_limit(timeout):
            exec(code, namespace)
    except BaseException as e:  # noqa: BLE001 - any failure of the student's cell is a result
        if isinstance(e, KeyboardInterrupt):
            raise
        return {"problem": f"its solution cell failed: {describe(e)}"}
    f = namespace.get(name)
    if not callable(f):
        return {"problem": f"its solution cell does not define {name}"}
    return {"calls": [[answer(f, tuple(args), timeout) for args in case] for case in cases]}


def readable(lib: Path) -> list[Path]:
    """What the confined process may read: its import path (the standard library and ``lib``),
    what ``lib``'s links point to (NumPy), the system's library folders, the few files of /etc, /proc, /sys
    and /dev that Python and NumPy read, and its own /proc entry."""
    places = [Path(p) for p in sys.path if p and Path(p).exists()]
    places += [entry.resolve() for entry in lib.iterdir()] + [Path(p) for p in SYSTEM if Path(p).exists()]
    places += [Path(p) for p in SYSTEM_FILES if Path(p).exists()] + [Path(f"/proc/{os.getpid()}")]
    return places


# Python's audit events (PEP 578) that touch a path: the ones that read, and the ones that change it.
_READS = ("os.listdir", "os.scandir")
_CHANGES = ("os.remove", "os.rename", "os.mkdir", "os.rmdir", "os.symlink", "os.link", "os.chmod", "os.chown",
            "os.truncate", "os.utime", "shutil.rmtree", "shutil.copyfile", "shutil.move")
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
MAX_ATTEMPTS = 20  # lines reported per process


def _inside(path: str, places: list[str]) -> bool:
    return any(path == p or path.startswith(p.rstrip("/") + "/") for p in places)


def report(fd: int | None, line: str) -> None:
    """One line to the grader, at once (what is written into the pipe cannot be taken back)."""
    if fd is not None:
        with contextlib.suppress(OSError):
            os.write(fd, (" ".join(line.split()) + "\n").encode("utf-8", "replace"))


def watch(read: list[Path], write: list[Path], fd: int | None, state: dict) -> None:
    """Report to the grader each attempt of this process to read or change a path outside what it
    may read (``read``) or write (``write``), or another process's ``/proc`` entry, through Python's
    file functions (an audit hook: it cannot be removed). Landlock refuses them; this says they were
    tried, for the teacher. Code that calls the C library directly is not seen, and is refused all the same."""
    reads, writes = [os.path.abspath(p) for p in read], [os.path.abspath(p) for p in write]
    seen: set[str] = set()

    def hook(event: str, args: tuple) -> None:
        with contextlib.suppress(Exception):  # whatever the arguments, the student's call goes on as it would
            note(event, args)

    def note(event: str, args: tuple) -> None:
        if event == "open":
            path, mode, flags = (tuple(args) + (None, None, None))[:3]
            changes = bool((flags or 0) & _WRITE_FLAGS) or (isinstance(mode, str) and any(c in mode for c in "wax+"))
        elif event in _READS or event in _CHANGES:
            path, changes = (args[0] if args else None), event in _CHANGES
        else:
            return
        if path is None or isinstance(path, int) or len(seen) >= MAX_ATTEMPTS:
            return
        try:
            path = os.path.abspath(os.fsdecode(path))
        except (TypeError, ValueError):
            return
        parts = path.split("/")
        other = len(parts) > 2 and parts[1] == "proc" and parts[2].isdigit() and int(parts[2]) != os.getpid()
        if _inside(path, writes) or (not changes and not other and _inside(path, reads)):
            return
        line = f"{state.get('exercise') or 'its solution cells'}: {'write' if changes else 'read'} {path}"
        if line not in seen:
            seen.add(line)
            report(fd, "attempt " + line)

    sys.addaudithook(hook)


def main(job_dir: str | Path) -> int:
    job_dir = Path(job_dir)
    job = json.loads((job_dir / "job.json").read_text())
    answers, work = job_dir / "answers", job_dir / "work"
    if job.get("cgroup"):
        with contextlib.suppress(OSError):
            (Path(job["cgroup"]) / "cgroup.procs").write_text(str(os.getpid()))
    sandbox.limit(job["memory_mb"], job["cpu_s"], job["file_mb"])
    if os.geteuid() == 0 and not sandbox.drop_capabilities():  # root, with no user to drop to (see sandbox)
        print("grading: running as root and could not drop its capabilities; no student code ran", file=sys.stderr)
        return 70
    if job["confine"]:
        abi = sandbox.confine(read=readable(job_dir / "lib") + [job_dir / "inputs.npz"],
                              write=[answers, work, Path("/dev/null")])
        if job["landlock"] and not abi:
            print("grading: Landlock is available but could not confine this process; no student code ran",
                  file=sys.stderr)
            return 70
    inputs = wire.load(job_dir / "inputs.npz")
    fd, state = job.get("report_fd"), {}
    watch(readable(job_dir / "lib") + [job_dir / "inputs.npz"], [answers, work, Path("/dev/null")], fd, state)
    for name, source in job["exercises"].items():
        state["exercise"] = name
        report(fd, f"start {name}")  # the grader's clock for this exercise starts here
        wire.save(answers / f"{name}.npz", solve(name, source, inputs[name], job["timeout"]))
    return 0
