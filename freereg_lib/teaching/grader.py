"""The grading process: scores submissions without running a line of student code.

For each run it draws a seed (new every run unless the teacher fixes one), draws every case's
inputs from it (:mod:`.exercises`) and computes the library's answer to each call, here, in
the only process where the library is. For each submission it reads the notebooks statically,
takes each exercise's solution code (:func:`.notebooks.solution_sources`; a cell that uses
``freereg_lib`` is refused before anything runs), and starts one student process
(:mod:`.student`) with resource limits, a wall-clock limit, an output cap, an import path of
NumPy and the standard library only and (Linux 5.13+) Landlock. It waits, ends everything that
process started (:func:`.sandbox.end_all`), reads the answers it left as data (:mod:`.wire`)
and scores them. Whatever happens in a student's process costs at most that student's grade.
"""
from __future__ import annotations

import contextlib
import copy
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freereg_lib.teaching import check, notebooks as N, sandbox, student, wire
from freereg_lib.teaching.exercises import EXERCISES, Draw, Exercise

CASE_TIMEOUT_S = 30.0     # per call of a student's function (soft: in the student's process)
STUDENT_LIMIT_S = 600.0   # hard wall-clock limit of one student's process
MEMORY_MB = 4096          # address space of one student's process
FILE_MB = 64              # largest file one student's process may write
OUTPUT_BYTES = 2**20      # what a student's process may print before it is stopped
RUNNER = ("student.py", "sandbox.py", "wire.py")  # the student's process runs these, copied; stdlib and NumPy only
NOT_AVAILABLE = ("ModuleNotFoundError", "ImportError", "PermissionError")


@dataclass
class Prepared:
    """One grading run: its seed and, per exercise per case per call, the inputs and the library's answer."""

    seed: int
    inputs: dict[str, list[list[tuple]]]
    want: dict[str, list[list[Any]]]


def prepare(seed: int | None = None, exercises: dict[str, Exercise] = EXERCISES) -> Prepared:
    seed = secrets.randbits(62) if seed is None else int(seed)
    inputs, want = {}, {}
    for index, (name, ex) in enumerate(exercises.items()):
        inputs[name] = [[tuple(c) for c in case.calls(Draw(seed, 100 * index + k))] for k, case in enumerate(ex.cases)]
        want[name] = [[ex.reference(*copy.deepcopy(c)) for c in calls] for calls in inputs[name]]
    return Prepared(seed, inputs, want)


def _message(text: Any) -> str:
    text = " ".join(str(text).split())
    if (any(k in text for k in NOT_AVAILABLE) or check.LIBRARY in text) and check.GRADED_WITH not in text:
        text += f" ({check.GRADED_WITH}, and no file of the course can be read)"
    return text if len(text) <= 400 else text[:397] + "..."


def score_exercise(ex: Exercise, prepared: Prepared | None, answer: Any, problem: str = "not found",
                   status: str = "missing") -> dict:
    """One exercise's score from what the student's process wrote (``answer``, as read); never raises."""
    result = {"exercise": ex.function, "notebook": ex.notebook, "title": ex.title, "score": 0.0,
              "max": ex.max_points, "status": status, "message": _message(problem),
              "cases": [{"name": c.name, "points": 0.0, "max": c.points, "ok": False, "message": "not graded"}
                        for c in ex.cases]}
    if isinstance(answer, dict) and isinstance(answer.get("problem"), str):
        result["message"] = _message(answer["problem"])
    if prepared is None or not isinstance(answer, dict) or "calls" not in answer:
        return result
    records, calls = answer["calls"], prepared.inputs[ex.function]
    if not (isinstance(records, list) and len(records) == len(calls)
            and all(isinstance(r, list) and len(r) == len(c) for r, c in zip(records, calls))):
        result.update(status="failed", message="its answers do not have the shape of the grader's calls")
        return result
    result["cases"] = []
    not_done = 0
    for case, got, wanted in zip(ex.cases, records, prepared.want[ex.function]):
        ok, message = True, ""
        for rec, want in zip(got, wanted):
            if not isinstance(rec, dict) or not ({"value"} == set(rec) or "error" in rec):
                ok, message = False, "not an answer"
            elif "error" in rec:
                ok, message = False, _message(rec["error"])
                not_done += rec.get("kind") == "NotImplementedError"
            else:
                try:
                    ex.check(rec["value"], want)
                except Exception as e:  # noqa: BLE001 - AssertionError, or an answer of the wrong type
                    ok, message = False, _message(e if isinstance(e, AssertionError) else f"{type(e).__name__}: {e}")
            if not ok:
                break
        result["cases"].append({"name": case.name, "points": case.points if ok else 0.0, "max": case.points,
                                "ok": ok, "message": message})
    result["score"] = float(sum(c["points"] for c in result["cases"]))
    if not_done == len(ex.cases):
        result.update(status="not done", message=f"not done: {ex.function} still raises NotImplementedError")
    elif result["score"] == result["max"]:
        result.update(status="ok", message="")
    else:
        result["status"] = "partial" if result["score"] > 0 else "failed"
        result["message"] = next(c["message"] for c in result["cases"] if not c["ok"]) or "wrong answer"
    return result


class _Output(threading.Thread):
    """Reads what the student's process prints, keeps its tail, and stops the process past the cap."""

    def __init__(self, proc: subprocess.Popen, cap: int):
        super().__init__(daemon=True)
        self.proc, self.cap, self.total, self.tail, self.over = proc, cap, 0, b"", False

    def run(self) -> None:
        while chunk := self.proc.stdout.read1(65536):
            self.total += len(chunk)
            self.tail = (self.tail + chunk)[-2000:]
            if self.total > self.cap and not self.over:
                self.over = True
                with contextlib.suppress(OSError):
                    os.killpg(self.proc.pid, signal.SIGKILL)


def submission(path: Path) -> tuple[dict[str, str], list[str], dict[str, str]]:
    """A submission read statically: the solution code of each exercise found, the exercises it
    is graded on (a folder: all; one notebook: its own), and why any other is missing."""
    files = N.notebooks_in(path) if path.is_dir() else [path]
    wanted = list(EXERCISES) if path.is_dir() else []
    sources: dict[str, str] = {}
    missing = {}
    for f in files:
        try:
            nb = N._read(f)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the student's, and a result
            stem = N._notebook_stem({}, f)  # its name says which notebook it was meant to be
            for name in (n for n, ex in EXERCISES.items() if ex.notebook == stem):
                wanted += [name] if name not in wanted else []
                missing.setdefault(name, f"{f.name} is not a readable notebook ({_message(e)})")
            continue
        names = N.relevant(nb, f)
        wanted += [n for n in names if n not in wanted]
        found = N.solution_sources(nb)
        for name in names:
            if name in found and name not in sources:
                sources[name] = found[name]
            elif name not in sources:
                missing.setdefault(name, f"{name} is not defined in {f.name}")
    for name in wanted:
        missing.setdefault(name, f"no notebook for {EXERCISES[name].notebook}")
    return sources, wanted, missing


def grade(path: str | Path, prepared: Prepared | None = None, timeout: float = CASE_TIMEOUT_S,
          limit: float = STUDENT_LIMIT_S, memory_mb: int = MEMORY_MB, confine: bool = True) -> dict:
    """Grade one submission (a student notebook, or a folder of one student's notebooks).

    Returns ``{"path", "status", "score", "max", "exercises", "confined", ...}``; ``status`` says
    how the student's process ended (``graded``, ``stopped`` at the limit, ``exited`` early,
    ``killed`` by a signal or a limit).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such notebook or folder")
    prepared = prepared or prepare()
    sources, wanted, missing = submission(path)
    uses = {n: where for n, s in sources.items() if (where := check.library_use(s))}
    to_run = {n: s for n, s in sources.items() if n not in uses}
    job = Path(tempfile.mkdtemp(prefix="freereg_grade_"))
    try:
        run = (_run_student(job, to_run, prepared, timeout, limit, memory_mb, confine) if to_run
               else {"status": "graded", "ended": "", "killed": 0})
        exercises = []
        for name in wanted:
            ex = EXERCISES[name]
            if name in uses:
                exercises.append(score_exercise(ex, prepared, None, status="refused", problem=(
                    f"its solution cell uses {check.LIBRARY} ({uses[name]}): {check.GRADED_WITH}; it scores 0")))
            elif name not in to_run:
                exercises.append(score_exercise(ex, prepared, None, missing[name]))
            else:
                try:
                    exercises.append(score_exercise(ex, prepared, wire.load(job / "answers" / f"{name}.npz")))
                except wire.WireError:
                    exercises.append(score_exercise(ex, prepared, None, run["ended"], "stopped"))
    finally:
        shutil.rmtree(job, ignore_errors=True)
    if run["status"] == "graded" and any(e["status"] == "stopped" for e in exercises):
        run["status"] = "exited"  # os._exit(0) or the like, before the end
    result = {"path": str(path), "status": run["status"], "score": float(sum(e["score"] for e in exercises)),
              "max": float(sum(e["max"] for e in exercises)), "exercises": exercises,
              "confined": bool(confine and sandbox.landlock_abi()) and not library_readable(),
              "leftover_processes_killed": run["killed"],
              "seed": prepared.seed}
    if run["status"] != "graded":
        result["stopped"] = run["ended"]
    return result


def library_readable() -> bool:
    """Whether the library's files lie in a folder the confined process may read (the Python's own
    folders, NumPy's, the system's: a library installed into /usr, say); Landlock cannot hide them then."""
    package, home = Path(__file__).resolve().parents[1], Path(np.__file__).resolve().parent
    places = [sysconfig.get_path(k) for k in ("stdlib", "platstdlib")]
    places += [*student.SYSTEM, home, home.parent / "numpy.libs"]
    return any(package.is_relative_to(Path(p).resolve()) for p in places if Path(p).exists())


def _runner(job: Path) -> Path:
    """The student process's import path: the runner's modules and links to NumPy, nothing else."""
    lib = job / "lib"
    (lib / "grading").mkdir(parents=True)
    (lib / "grading" / "__init__.py").write_text("")
    for name in RUNNER:
        shutil.copy2(Path(__file__).with_name(name), lib / "grading" / name)
    home = Path(np.__file__).resolve().parent
    for entry in (home, home.with_name("numpy.libs")):
        if entry.exists():
            (lib / entry.name).symlink_to(entry, target_is_directory=True)
    return lib


def _run_student(job: Path, sources: dict[str, str], prepared: Prepared, timeout: float, limit: float,
                 memory_mb: int, confine: bool) -> dict:
    """Start the student's process for one submission, wait for it, end all it started."""
    for folder in ("answers", "work/tmp"):
        (job / folder).mkdir(parents=True)
    lib = _runner(job)
    marker = secrets.token_hex(8)
    cgroup = sandbox.make_cgroup(marker)
    (job / "job.json").write_text(json.dumps({
        "exercises": sources, "timeout": timeout, "memory_mb": memory_mb, "cpu_s": int(limit) + 5,
        "file_mb": FILE_MB, "confine": confine, "landlock": sandbox.landlock_abi(),
        "cgroup": str(cgroup) if cgroup else None}))
    wire.save(job / "inputs.npz", {n: prepared.inputs[n] for n in sources})
    work = job / "work"
    env = {sandbox.MARKER_ENV: marker, "HOME": str(work), "TMPDIR": str(work / "tmp"), "PATH": "/usr/bin:/bin",
           "LANG": "C.UTF-8", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    boot = (f"import sys; sys.path[:0] = [{str(lib)!r}]; "
            "from grading import student; sys.exit(student.main(sys.argv[1]))")
    sandbox.subreaper(True)
    try:
        proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", boot, str(job)], cwd=work, env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                start_new_session=True)
        out = _Output(proc, OUTPUT_BYTES)
        out.start()
        try:
            code, timed_out = proc.wait(timeout=limit), False
        except subprocess.TimeoutExpired:
            code, timed_out = None, True
        killed = sandbox.end_all(proc.pid, marker, cgroup)
        code = proc.wait() if code is None else code
        out.join(timeout=10)
    finally:
        sandbox.subreaper(False)
    tail = out.tail.decode("utf-8", "replace").strip().splitlines()
    last = f" (it printed last: {_message(tail[-1])})" if tail and code else ""
    if out.over:
        return {"status": "killed", "killed": killed,
                "ended": f"its process printed more than {OUTPUT_BYTES // 1024} KiB and was stopped"}
    if timed_out:
        return {"status": "stopped", "killed": killed, "ended": f"its process was stopped at the hard limit of "
                f"{limit:g} s (code that never returns, or catches the time-out)"}
    if code < 0:
        name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else str(-code)
        why = {"SIGXCPU": "its CPU-time limit", "SIGXFSZ": "its file-size limit",
               "SIGKILL": "a kill (memory, CPU or a limit)"}.get(name, name)
        return {"status": "killed", "killed": killed, "ended": f"its process was killed by {name} ({why}){last}"}
    return {"status": "graded" if code == 0 else "exited", "killed": killed,
            "ended": f"its process ended (exit code {code}) before finishing this exercise{last}"}
