"""The grading process: scores submissions without running a line of student code.

For each run it draws a seed (new every run unless the teacher fixes one), draws every case's
inputs from it (:mod:`.exercises`) and computes the library's answer to each call, here, in
the only process where the library is. For each submission it reads the notebooks statically,
takes each exercise's solution code (:func:`.notebooks.solution_sources`; a cell that uses
``freereg_lib`` is refused before anything runs), and starts one student process
(:mod:`.student`) with resource limits, a wall-clock limit per exercise, an output cap, an import
path of NumPy and the standard library only and (Linux 5.13+) Landlock; as root, as an unprivileged
user or without capabilities (:func:`.sandbox.student_ids`). It waits, ends everything that
process started (:func:`.sandbox.end_all`), reads the answers it left as data (:mod:`.wire`)
and scores them; when the process stops in an exercise (a hang, an exit, a kill), that exercise
scores 0 and a new process grades the ones after it. Whatever happens in a student's process
costs at most that student's grade, and a hang only that exercise.
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
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freereg_lib.teaching import check, notebooks as N, sandbox, student, wire
from freereg_lib.teaching.exercises import EXERCISES, Draw, Exercise

CASE_TIMEOUT_S = 30.0     # per call of a student's function (soft: in the student's process)
STUDENT_LIMIT_S = 120.0   # hard wall-clock limit of each exercise in a student's process (a hang costs that one)
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


SHOW_VALUES = 200  # an argument up to this many values is shown whole (pasteable), a larger one by its ends


def _show(value: Any, depth: int = 0) -> str:
    """An argument as Python a student can paste (an array whole up to :data:`SHOW_VALUES` values, else its
    first and last rows, said in a comment)."""
    if isinstance(value, np.ndarray):
        text = np.array2string(value, separator=", ", precision=6, threshold=SHOW_VALUES, edgeitems=3,
                               max_line_width=100, floatmode="maxprec")
        dtype = "" if value.dtype in (np.float64, np.int64, np.bool_) else f", dtype=np.{value.dtype}"
        return (f"np.array({text}{dtype})"
                + ("" if value.size <= SHOW_VALUES else f"  # shape {value.shape}: its first and last rows only"))
    if isinstance(value, (list, tuple)) and depth < 3:
        inner = ", ".join(_show(v, depth + 1) for v in value)
        return f"({inner}{',' if len(value) == 1 else ''})" if isinstance(value, tuple) else f"[{inner}]"
    return repr(value)


def show_call(args: tuple) -> str:
    """A failed call's arguments, one per line (the inputs are drawn anew each run: showing them gives nothing away)."""
    return "\n".join(f"arg{k} = {_show(a)}" for k, a in enumerate(args or ()))


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
    for case, got, wanted, args in zip(ex.cases, records, prepared.want[ex.function], calls):
        ok, message, failed_call = True, "", None
        for rec, want, call in zip(got, wanted, args):
            failed_call = call
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
                                "ok": ok, "message": message, **({} if ok else {"inputs": show_call(failed_call)})})
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


def _when(path: Path) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(path.stat().st_mtime))


def choose_notebooks(files: list[Path]) -> tuple[list[tuple[Path, Any]], list[str], dict[str, str]]:
    """One student's notebooks read, one per project notebook: where two or more are versions of
    the same one (``03_fusion.ipynb`` beside ``03_fusion-Copy1.ipynb``), the newest is kept and a
    note says so; when the newest cannot be told (the same time), none is, and ``ties`` says why
    per notebook stem. Returns ``(kept, notes, ties)``; ``kept`` holds ``(path, notebook or the read error)``."""
    read: list[tuple[Path, Any, str | None]] = []
    for f in files:
        try:
            nb = N._read(f)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the student's, and a result
            read.append((f, e, None))
            continue
        read.append((f, nb, N._notebook_stem(nb, f)))
    groups: dict[str, list[Path]] = {}
    for f, nb, stem in read:
        if stem is not None and not isinstance(nb, Exception):
            groups.setdefault(stem, []).append(f)
    drop, notes, ties = set(), [], {}
    for stem, paths in groups.items():
        if len(paths) < 2:
            continue
        paths = sorted(paths, key=lambda p: p.stat().st_mtime, reverse=True)
        names = ", ".join(p.name for p in paths)
        if paths[0].stat().st_mtime == paths[1].stat().st_mtime:
            ties[stem] = (f"{names} are all notebook {stem}, saved at the same time ({_when(paths[0])}): the grader "
                          "cannot tell which to grade; keep one and grade again")
            drop |= set(paths)
        else:
            notes.append(f"{names} are all notebook {stem}: graded the newest, {paths[0].name} ({_when(paths[0])})")
            drop |= set(paths[1:])
    return [(f, nb) for f, nb, _ in read if f not in drop], notes, ties


def submission(path: Path) -> tuple[dict[str, str], list[str], dict[str, str], list[str]]:
    """A submission read statically: the solution code of each exercise found, the exercises it
    is graded on (a folder: all; one notebook: its own), why any other is missing, and notes on
    the notebooks it chose between (:func:`choose_notebooks`)."""
    files = N.notebooks_in(path) if path.is_dir() else [path]
    wanted = list(EXERCISES) if path.is_dir() else []
    sources: dict[str, str] = {}
    missing = {}
    kept, notes, ties = choose_notebooks(files)
    for stem, why in ties.items():
        for name in (n for n, ex in EXERCISES.items() if ex.notebook == stem):
            wanted += [name] if name not in wanted else []
            missing.setdefault(name, why)
    for f, nb in kept:
        if isinstance(nb, Exception):
            stem = N._notebook_stem({}, f)  # its name says which notebook it was meant to be
            for name in (n for n, ex in EXERCISES.items() if ex.notebook == stem):
                wanted += [name] if name not in wanted else []
                missing.setdefault(name, f"{f.name} is not a readable notebook ({_message(nb)})")
            continue
        names = N.relevant(nb, f)
        wanted += [n for n in names if n not in wanted]
        found = N.solution_sources(nb)
        for name in names:
            if name in found and name not in sources and EXERCISES[name].notebook not in ties:
                sources[name] = found[name]
            elif name not in sources:
                missing.setdefault(name, f"{name} is not defined in {f.name}")
    for name in wanted:
        missing.setdefault(name, f"no notebook for {EXERCISES[name].notebook}")
    return sources, wanted, missing, notes


def grade(path: str | Path, prepared: Prepared | None = None, timeout: float = CASE_TIMEOUT_S,
          limit: float = STUDENT_LIMIT_S, memory_mb: int = MEMORY_MB, confine: bool = True) -> dict:
    """Grade one submission (a student notebook, or a folder of one student's notebooks).

    Returns ``{"path", "status", "score", "max", "exercises", "confined", "attempts", ...}``;
    ``status`` says how the student's processes ended (``graded``, ``stopped`` at an exercise's
    limit, ``exited`` early, ``killed`` by a signal or a limit). Each exercise has ``limit``
    seconds of its own: when the process stops in one, a new process grades the ones after it.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such notebook or folder")
    prepared = prepared or prepare()
    sources, wanted, missing, notes = submission(path)
    uses = {n: where for n, s in sources.items() if (where := check.library_use(s))}
    to_run = {n: s for n, s in sources.items() if n not in uses}
    job = Path(tempfile.mkdtemp(prefix="freereg_grade_"))
    runs: list[dict] = []
    ends: dict[str, str] = {}  # exercise -> how its process ended during it
    try:
        remaining = dict(to_run)
        while remaining:  # at most one process per exercise: each run answers or ends in one at least
            run = _run_student(job, remaining, prepared, timeout, limit, memory_mb, confine)
            runs.append(run)
            order = list(remaining)
            at = run.get("at") if run.get("at") in remaining else None
            if run["status"] == "graded" and at is None:
                break
            at = at or next((n for n in order if not (job / "answers" / f"{n}.npz").exists()), None)
            if at is None:
                break
            ends[at] = run["ended"]
            (job / "answers" / f"{at}.npz").unlink(missing_ok=True)  # nothing it left for that one counts
            remaining = {n: remaining[n] for n in order[order.index(at) + 1:]}
            for n in remaining:  # answered again by the next process, not by what this one left
                (job / "answers" / f"{n}.npz").unlink(missing_ok=True)
        exercises = []
        for name in wanted:
            ex = EXERCISES[name]
            if name in uses:
                exercises.append(score_exercise(ex, prepared, None, status="refused", problem=(
                    f"its solution cell uses {check.LIBRARY} ({uses[name]}): {check.GRADED_WITH}; it scores 0")))
            elif name not in to_run:
                exercises.append(score_exercise(ex, prepared, None, missing[name]))
            elif name in ends:
                exercises.append(score_exercise(ex, prepared, None, ends[name], "stopped"))
            else:
                try:
                    exercises.append(score_exercise(ex, prepared, wire.load(job / "answers" / f"{name}.npz")))
                except wire.WireError:
                    exercises.append(score_exercise(ex, prepared, None, "its process ended before answering it",
                                                    "stopped"))
    finally:
        shutil.rmtree(job, ignore_errors=True)
    bad = [r for r in runs if r["status"] != "graded"]
    status = bad[0]["status"] if bad else "graded"
    if status == "graded" and any(e["status"] == "stopped" for e in exercises):
        status = "exited"  # os._exit(0) or the like, before the end
    result = {"path": str(path), "status": status, "score": float(sum(e["score"] for e in exercises)),
              "max": float(sum(e["max"] for e in exercises)), "exercises": exercises,
              "confined": bool(confine and sandbox.landlock_abi()) and not library_readable(),
              "leftover_processes_killed": sum(r["killed"] for r in runs),
              "attempts": [a for r in runs for a in r["attempts"]],
              "seed": prepared.seed, "chosen": notes}
    if ends:
        result["stopped"] = "; ".join(f"in {name}, {why}" for name, why in ends.items())
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


class _Reports(threading.Thread):
    """Reads the student process's report pipe: which exercise runs since when, and its attempts
    outside its folders (:func:`.student.watch`)."""

    def __init__(self, fd: int):
        super().__init__(daemon=True)
        self.file, self.current, self.since, self.attempts = os.fdopen(fd, "rb"), None, time.monotonic(), []

    def run(self) -> None:
        total = 0
        while raw := self.file.readline(4096):  # a line without end cannot grow the grader's memory
            total += len(raw)
            if total > OUTPUT_BYTES:
                continue  # read on (a full pipe would block the writer), keep nothing more
            line = raw.decode("utf-8", "replace").strip()
            if line.startswith("start "):
                self.current, self.since = line[6:], time.monotonic()
            elif line.startswith("attempt ") and len(self.attempts) < 50:
                self.attempts.append(_message(line[8:]))
        self.file.close()


def _prepare_job(job: Path, ids: tuple[int, int] | None) -> Path:
    """The job's folders and runner; as root, made usable by the students' user (who writes only answers/ and work/)."""
    for folder in ("answers", "work/tmp"):
        (job / folder).mkdir(parents=True, exist_ok=True)
    lib = job / "lib"
    if not lib.exists():
        _runner(job)
    if ids is not None:
        job.chmod(0o755)
        for folder in (job / "answers", job / "work", job / "work" / "tmp"):
            os.chown(folder, *ids)
    return lib


def _run_student(job: Path, sources: dict[str, str], prepared: Prepared, timeout: float, limit: float,
                 memory_mb: int, confine: bool) -> dict:
    """Start a student process for the exercises ``sources`` (in order), each with ``limit`` seconds
    from its start; wait, end all it started. ``at``: the exercise it was in when it ended."""
    ids = sandbox.student_ids()
    lib = _prepare_job(job, ids)
    marker = secrets.token_hex(8)
    cgroup = sandbox.make_cgroup(marker)
    read_end, write_end = os.pipe()
    (job / "job.json").write_text(json.dumps({
        "exercises": sources, "timeout": timeout, "memory_mb": memory_mb, "cpu_s": int(limit) * len(sources) + 5,
        "file_mb": FILE_MB, "confine": confine, "landlock": sandbox.landlock_abi(), "report_fd": write_end,
        "cgroup": str(cgroup) if cgroup else None}))
    (job / "job.json").chmod(0o644)
    wire.save(job / "inputs.npz", {n: prepared.inputs[n] for n in sources})
    (job / "inputs.npz").chmod(0o644)
    work = job / "work"
    env = {sandbox.MARKER_ENV: marker, "HOME": str(work), "TMPDIR": str(work / "tmp"), "PATH": "/usr/bin:/bin",
           "LANG": "C.UTF-8", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    boot = (f"import sys; sys.path[:0] = [{str(lib)!r}]; "
            "from grading import student; sys.exit(student.main(sys.argv[1]))")
    as_user = {"user": ids[0], "group": ids[1], "extra_groups": []} if ids else {}
    sandbox.subreaper(True)
    try:
        try:
            proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", boot, str(job)], cwd=work, env=env,
                                    stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    start_new_session=True, pass_fds=(write_end,), **as_user)
        finally:
            os.close(write_end)
        if cgroup is not None:  # the student's user may not write the grader's cgroup: put it there from here
            with contextlib.suppress(OSError):
                (cgroup / "cgroup.procs").write_text(str(proc.pid))
        out, reports = _Output(proc, OUTPUT_BYTES), _Reports(read_end)
        out.start()
        reports.start()
        started, timed_out, code = time.monotonic(), False, None
        while code is None:
            try:
                code = proc.wait(timeout=0.05)
            except subprocess.TimeoutExpired:
                now = time.monotonic()  # each exercise's own budget, and all of them as a bound for the whole
                if now - reports.since > limit or now - started > limit * len(sources) + 5:
                    timed_out = True
                    break
        killed = sandbox.end_all(proc.pid, marker, cgroup)
        code = proc.wait() if code is None else code
        out.join(timeout=10)
        reports.join(timeout=10)
    finally:
        sandbox.subreaper(False)
    tail = out.tail.decode("utf-8", "replace").strip().splitlines()
    last = f" (it printed last: {_message(tail[-1])})" if tail and code else ""
    at = reports.current  # the exercise it was in; none when it ended as it should, after its last answer
    if code == 0 and not (timed_out or out.over) and (at is None or (job / "answers" / f"{at}.npz").exists()):
        at = None
    base = {"killed": killed, "at": at, "attempts": reports.attempts}
    if out.over:
        return {**base, "status": "killed",
                "ended": f"its process printed more than {OUTPUT_BYTES // 1024} KiB and was stopped"}
    if timed_out:
        return {**base, "status": "stopped", "ended": f"its process was stopped at the hard limit of {limit:g} s "
                "for one exercise (code that never returns, or catches the time-out)"}
    if code < 0:
        name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else str(-code)
        why = {"SIGXCPU": "its CPU-time limit", "SIGXFSZ": "its file-size limit",
               "SIGKILL": "a kill (memory, CPU or a limit)"}.get(name, name)
        return {**base, "status": "killed", "ended": f"its process was killed by {name} ({why}){last}"}
    return {**base, "status": "graded" if code == 0 else "exited",
            "ended": f"its process ended (exit code {code}) before finishing this exercise{last}"}
