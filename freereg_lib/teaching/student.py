"""The student's process: run the solution cells, answer the grader's inputs, write the answers.

Started by the grader (``python -m freereg_lib.teaching.student JOB_DIR``) in a session of its
own, one per submission. Before any student code runs it puts its resource limits on
(:func:`.sandbox.limit`), compiles the library's reference functions with their answers
altered (:func:`.poison.install`), reads the notebooks and then confines itself
(:func:`.sandbox.confine`: the project's notebooks, the answer keys and the rest of your files
become unreadable). Then it runs each ``solution`` cell (each on its own, in a fresh namespace
with ``numpy as np``, the notebook's imports and the ``freereg_lib`` modules; nothing else of
the notebook runs), reads the inputs the grader drew, calls each exercise's function on them
and writes what came back, as data (:mod:`.wire`), one file per exercise as it finishes.

It decides nothing: whatever it writes (or forges) is only ever read as arrays and numbers
by the grading process, which compares them with the reference it computes itself.
"""
from __future__ import annotations

import ast
import contextlib
import copy
import io
import json
import os
import re
import signal
import sys
import threading
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np

from freereg_lib.teaching import poison, sandbox, wire


class _Namespace(dict):
    """Globals for the students' code: a name the notebook imports is imported on first use.

    Functions defined here look their globals up through ``__missing__`` (a dict subclass as
    globals disables CPython's fast path), so ``pd`` or ``cameras`` cost nothing unless used.
    """

    def __init__(self, lazy: dict[str, str]):
        super().__init__(__name__="__student__", __builtins__=__builtins__, np=np)
        self._lazy = lazy

    def __missing__(self, name: str):
        statement = self._lazy.pop(name, None)
        if statement is None:
            raise KeyError(name)
        scratch: dict = {}
        exec(statement, scratch)
        value = scratch[name]
        self[name] = value
        return value


@contextlib.contextmanager
def _time_limit(seconds: float | None):
    """A soft per-call limit (the code can catch it: the grader's hard limit is the real one)."""
    usable = (seconds and seconds > 0 and hasattr(signal, "setitimer")
              and threading.current_thread() is threading.main_thread())
    if not usable:
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


def load_functions(nb, name: str, timeout: float | None) -> tuple[dict[str, Callable], dict[str, str]]:
    """The exercise functions a student notebook defines, and why any could not be read.

    Runs every cell tagged ``solution`` (each on its own, so one broken cell spoils only its
    own functions) in a fresh namespace with ``numpy as np``, the notebook's imports and the
    ``freereg_lib`` modules. A function the student defined in an untagged cell is taken from
    there (only its ``def``). Nothing else of the notebook runs.
    """
    from freereg_lib.teaching import notebooks as N

    ns = _Namespace(N._import_statements(nb))
    problems: dict[str, str] = {}
    for i, cell in enumerate(nb.cells):
        if not N._is_solution(cell):
            continue
        try:
            code = compile(N._python(cell.source), f"<{name} cell {i}>", "exec")
            with _quiet(), _time_limit(timeout):
                exec(code, ns)
        except BaseException as e:  # noqa: BLE001 - any failure of the student's cell is a result
            if isinstance(e, KeyboardInterrupt):
                raise
            names = N._defined_functions(cell.source) or re.findall(r"^def\s+(\w+)", cell.source, re.MULTILINE)
            for fn in names or [f"cell {i}"]:
                problems[fn] = f"its solution cell failed: {describe(e)}"
    found = {fn: dict.get(ns, fn) for fn in N.EXERCISES if callable(dict.get(ns, fn))}
    missing = set(N.EXERCISES) - set(found)
    trees = list(N._parsed_cells(nb)) if missing else []
    for fn in missing:  # a function defined outside its solution cell (an untagged cell) still counts
        for tree in trees:
            defs = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name == fn]
            if defs:
                try:
                    with _quiet(), _time_limit(timeout):
                        exec(compile(ast.Module(body=defs[-1:], type_ignores=[]), f"<{name}>", "exec"), ns)
                    found[fn] = dict.get(ns, fn)
                    problems.pop(fn, None)
                except Exception as e:  # noqa: BLE001
                    problems[fn] = f"its definition failed: {describe(e)}"
    return found, problems


def _plain(value: Any, depth: int = 0) -> Any:
    """What the student's function returned, as data the wire carries (or TypeError)."""
    arrays: dict = {}
    try:
        wire.encode(value, arrays)
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


def _readable(root: Path) -> list[Path]:
    """What the confined process may read: Python, its packages, the system, ``freereg_lib``."""
    package = Path(__file__).resolve().parent.parent
    places = {Path(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix)}
    places |= {Path(p).resolve() for p in sys.path if p and Path(p).is_dir()}
    places |= {Path(p) for p in ("/usr", "/lib", "/lib64", "/lib32", "/bin", "/sbin", "/etc", "/opt",
                                 "/proc", "/sys", "/dev")}
    keep = []
    for p in places:
        p = p.resolve() if p.exists() else p
        if root == p or root.is_relative_to(p):  # the project (or a folder above it): no
            continue
        if p.is_relative_to(root) and not p.is_relative_to(root / ".venv"):
            continue
        keep.append(p)
    return sorted(keep) + [package]


def run(job_dir: Path) -> int:
    job = json.loads((job_dir / "job.json").read_text())
    answers = job_dir / "answers"
    if job.get("cgroup"):
        with contextlib.suppress(OSError):
            (Path(job["cgroup"]) / "cgroup.procs").write_text(str(os.getpid()))
    sandbox.limit(job["memory_mb"], job["cpu_s"], job["file_mb"])
    poison.install(job["refs"], job["poison"])
    import nbformat

    from freereg_lib.teaching import notebooks as N

    books, skipped = [], []
    for path in job["notebooks"]:
        try:
            books.append((Path(path), nbformat.read(path, as_version=4)))
        except Exception as e:  # noqa: BLE001
            skipped.append(f"{Path(path).name}: not a readable notebook ({describe(e)})")
    root = Path(job["root"])
    abi = sandbox.confine(read=_readable(root) + [job_dir / "inputs.npz"], read_dir_only=[root],
                          write=[answers, job_dir / "work", Path("/dev/null")]) if job["confine"] else 0
    if job["confine"] and job.get("landlock") and not abi:
        print("grading: Landlock is available but could not confine this process; no student code ran",
              file=sys.stderr)
        return 70
    found: dict[str, Callable] = {}
    problems: dict[str, str] = {}
    for path, nb in books:
        names = N.relevant(nb, path)
        if not names:
            continue
        functions, trouble = load_functions(nb, path.name, job["timeout"])
        for fn in names:  # the first notebook that defines a function gives it
            if functions.get(fn) is not None and fn not in found:
                found[fn] = functions[fn]
                problems.pop(fn, None)
            elif fn not in found and fn not in problems:
                other = "; ".join(f"{k}: {v}" for k, v in trouble.items() if k.startswith("cell "))
                problems[fn] = trouble.get(fn) or f"not defined in {path.name}" + (f" ({other})" if other else "")
    wire.save(answers / "loaded.npz", {"found": sorted(found), "problems": problems, "skipped": skipped,
                                        "landlock": abi})
    inputs = wire.load(job_dir / "inputs.npz", series=True)
    for fn in job["wanted"]:
        f = found.get(fn)
        if f is None:
            continue
        records = [[answer(f, tuple(args), job["timeout"]) for args in case] for case in inputs[fn]]
        wire.save(answers / f"{fn}.npz", records)
    return 0


if __name__ == "__main__":
    sys.exit(run(Path(sys.argv[1])))
