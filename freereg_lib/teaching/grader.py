"""The grading process: scores submissions without ever running a line of student code.

For each run (``python -m freereg_lib.teaching.assignments grade PATH [PATH ...]``) it draws a secret
seed, draws every case's inputs from it (:mod:`.exercises`) and computes, in this process, the
library's reference answer to each call and the answer a call of the altered reference would
give (:mod:`.poison`). Then, for each submission in turn, it starts a student process
(:mod:`.student`) in a session of its own, with resource limits, a wall-clock limit, an output
cap and (Linux 5.13+) Landlock confinement, hands it the inputs, waits, ends everything that
process started (:func:`.sandbox.end_all`), reads the answers it left as data
(:func:`.wire.load`) and scores them. Whatever happens in a student's process costs at most
that student's grade: every path gets its row in the results, with a status.
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
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from freereg_lib.teaching import notebooks as N
from freereg_lib.teaching import poison, sandbox, wire
from freereg_lib.teaching.exercises import EXERCISES, Draw, Exercise, points

CASE_TIMEOUT_S = 30.0     # per call of a student's function (soft: in the student's process)
STUDENT_LIMIT_S = 600.0   # hard wall-clock limit of one student's process
MEMORY_MB = 4096          # address space of one student's process (torch alone maps ~1.7 GB)
FILE_MB = 64              # largest file one student's process may write
OUTPUT_BYTES = 2**20      # what a student's process may print before it is stopped


@dataclass
class Prepared:
    """One grading run: the secret draws, and per exercise per case per call, the inputs,
    the reference's answer and the altered reference's answer."""

    seed: int
    poison_key: str
    inputs: dict[str, list[list[tuple]]]
    want: dict[str, list[list[Any]]]
    altered: dict[str, list[list[Any]]]


def prepare(seed: int | None = None, exercises: dict[str, Exercise] = EXERCISES) -> Prepared:
    seed = secrets.randbits(62) if seed is None else int(seed)
    key = secrets.token_hex(16)
    refs = sorted({r for e in exercises.values() for r in e.refs})
    inputs, want, altered = {}, {}, {}
    index = 0
    for name, ex in exercises.items():
        inputs[name], want[name], altered[name] = [], [], []
        for case in ex.cases:
            calls = case.calls(Draw(seed, index))
            index += 1
            inputs[name].append([tuple(c) for c in calls])
            want[name].append([ex.reference(*copy.deepcopy(c)) for c in calls])
            with poison.altered(refs, key):
                altered[name].append([ex.reference(*copy.deepcopy(c)) for c in calls])
    return Prepared(seed, key, inputs, want, altered)


def _message(text: Any) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= 300 else text[:297] + "..."


def score_exercise(ex: Exercise, prepared: Prepared, records: Any, problem: str | None = None,
                   status: str = "missing") -> dict:
    """One exercise's score from the student's answers (``records``, as read); never raises."""
    result = {"exercise": ex.function, "notebook": ex.notebook, "title": ex.title, "score": 0.0,
              "max": ex.max_points, "status": status, "message": "", "cases": []}
    calls = prepared.inputs[ex.function]
    shaped = (isinstance(records, list) and len(records) == len(calls)
              and all(isinstance(r, list) and len(r) == len(c) for r, c in zip(records, calls)))
    if records is not None and not shaped:
        records, problem, status = None, "its answers do not have the shape of the grader's calls", "failed"
        result["status"] = status
    if records is None:
        result["message"] = _message(problem or "not found")
        result["cases"] = [{"name": c.name, "points": 0.0, "max": c.points, "ok": False, "message": "not graded"}
                           for c in ex.cases]
        return result
    not_implemented, from_reference = 0, False
    for k, case in enumerate(ex.cases):
        ok, message = True, ""
        for rec, want, bad in zip(records[k], prepared.want[ex.function][k], prepared.altered[ex.function][k]):
            if not isinstance(rec, dict) or not ({"value"} == set(rec) or "error" in rec):
                ok, message = False, "not an answer"
                break
            if "error" in rec:
                ok, message = False, _message(rec["error"])
                not_implemented += rec.get("kind") == "NotImplementedError"
                break
            try:
                ex.check(rec["value"], want)
            except Exception as e:  # noqa: BLE001 - AssertionError, or an answer of the wrong type
                ok, message = False, _message(f"{type(e).__name__}: {e}" if not isinstance(e, AssertionError) else e)
                with contextlib.suppress(Exception):
                    ex.check(rec["value"], bad)
                    from_reference = True
                break
        result["cases"].append({"name": case.name, "points": case.points if ok else 0.0, "max": case.points,
                                "ok": ok, "message": message})
    if from_reference:
        refs = ", ".join(f"freereg_lib.{r}" for r in ex.refs)
        result.update(score=0.0, status="refused", message=(
            f"its answers are those of the library's reference ({refs}), which answers deliberately wrong "
            "in the student's process: it calls the reference instead of computing; this exercise scores 0"))
        for c in result["cases"]:
            c["points"], c["ok"] = 0.0, False
        return result
    result["score"] = float(sum(c["points"] for c in result["cases"]))
    if not_implemented == len(ex.cases):
        result["status"], result["message"] = "not implemented", "raises NotImplementedError"
    elif result["score"] == result["max"]:
        result["status"] = "ok"
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


def _wanted(path: Path) -> tuple[list[Path], list[str], list[str]]:
    """The notebooks of a submission, the exercises it is graded on, and the unreadable files
    (read statically: nothing of the notebook runs here)."""
    if path.is_dir():
        files, wanted = N.notebooks_in(path), list(EXERCISES)
        skipped = []
        for f in files:
            try:
                N._read(f)
            except Exception as e:  # noqa: BLE001
                skipped.append(f"{f.name}: not a readable notebook ({_message(e)})")
        return files, wanted, skipped
    try:
        return [path], N.relevant(N._read(path), path), []
    except Exception as e:  # noqa: BLE001
        return [path], [], [f"{path.name}: not a readable notebook ({_message(e)})"]


def grade(path: str | Path, prepared: Prepared | None = None, timeout: float = CASE_TIMEOUT_S,
          limit: float = STUDENT_LIMIT_S, memory_mb: int = MEMORY_MB, confine: bool = True,
          verbose: bool = False, print_table: bool = True) -> dict:
    """Grade one submission (a student notebook, or a folder of one student's notebooks).

    A folder is graded on every exercise (one missing from it scores 0); a single notebook on
    the exercises of the project notebook it is a version of, or failing that on the exercise
    functions it defines. Returns ``{"path", "status", "score", "max", "percent", "exercises",
    "skipped", ...}``; ``status`` says how the student's process ended (``graded``, ``stopped``
    at the limit, ``exited`` early, ``killed`` by a signal or a limit).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such notebook or folder")
    prepared = prepared or prepare()
    start = time.time()
    files, wanted, skipped = _wanted(path)
    job = Path(tempfile.mkdtemp(prefix="freereg_grade_"))
    marker = secrets.token_hex(8)
    try:
        if wanted:
            run = _run_student(job, files, wanted, prepared, marker, timeout, limit, memory_mb, confine)
        else:  # nothing to grade: no process
            run = {"status": "graded", "ended": "", "killed": 0}
        loaded = _read_answers(job / "answers" / "loaded.npz")
        exercises = []
        for name in wanted:
            ex = EXERCISES[name]
            records = _read_answers(job / "answers" / f"{name}.npz")
            if records is not None:
                exercises.append(score_exercise(ex, prepared, records))
            elif isinstance(loaded, dict) and name not in loaded.get("found", []):
                problem = (loaded.get("problems") or {}).get(name) if isinstance(loaded.get("problems"), dict) else None
                exercises.append(score_exercise(ex, prepared, None, problem or f"no notebook for {ex.notebook}"))
            else:
                exercises.append(score_exercise(ex, prepared, None, run["ended"], "stopped"))
    finally:
        shutil.rmtree(job, ignore_errors=True)
    if run["status"] == "graded" and any(e["status"] == "stopped" for e in exercises):
        run["status"] = "exited"  # os._exit(0) or the like, before the end
    score = float(sum(e["score"] for e in exercises))
    top = float(sum(e["max"] for e in exercises))
    result = {"path": str(path), "status": run["status"], "score": score, "max": top,
              "percent": 100.0 * score / top if top else 0.0, "exercises": exercises, "skipped": skipped,
              "seconds": round(time.time() - start, 1), "confined": bool(confine and sandbox.landlock_abi()),
              "leftover_processes_killed": run["killed"], "seed": prepared.seed}
    if run["status"] != "graded":
        result["stopped"] = run["ended"]
    if print_table:
        print(format_table(result, verbose))
    return result


def _read_answers(path: Path) -> Any:
    try:
        return wire.load(path)
    except wire.WireError:
        return None


def _run_student(job: Path, files: list[Path], wanted: list[str], prepared: Prepared, marker: str,
                 timeout: float, limit: float, memory_mb: int, confine: bool) -> dict:
    """Start the student's process for one submission, wait for it, end all it started."""
    (job / "answers").mkdir()
    (job / "work" / "tmp").mkdir(parents=True)
    package = Path(__file__).resolve().parent.parent
    refs = sorted({r for e in EXERCISES.values() for r in e.refs})
    spec = {"notebooks": [str(f.resolve()) for f in files], "wanted": wanted, "refs": refs,
            "poison": prepared.poison_key, "timeout": timeout, "memory_mb": memory_mb,
            "cpu_s": int(limit) + 5, "file_mb": FILE_MB, "root": str(package.parent), "confine": confine,
            "landlock": sandbox.landlock_abi(), "cgroup": None}
    wire.save(job / "inputs.npz", {n: prepared.inputs[n] for n in wanted})
    cgroup = sandbox.make_cgroup(marker)
    spec["cgroup"] = str(cgroup) if cgroup else None
    (job / "job.json").write_text(json.dumps(spec))
    work = job / "work"
    env = {k: v for k, v in os.environ.items() if k != sandbox.MARKER_ENV}
    env.update({sandbox.MARKER_ENV: marker, "HOME": str(work), "TMPDIR": str(work / "tmp"),
                "MPLCONFIGDIR": str(work / "tmp"), "PYTHONDONTWRITEBYTECODE": "1",
                "PYTHONPATH": os.pathsep.join([str(package.parent)]
                                              + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])})
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")
    sandbox.subreaper(True)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "freereg_lib.teaching.student", str(job)], cwd=work, env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                start_new_session=True)
        out = _Output(proc, OUTPUT_BYTES)
        out.start()
        try:
            code = proc.wait(timeout=limit)
            timed_out = False
        except subprocess.TimeoutExpired:
            timed_out, code = True, None
        killed = sandbox.end_all(proc.pid, marker, cgroup)
        code = proc.wait() if code is None else code
        out.join(timeout=10)
    finally:
        sandbox.subreaper(False)
    tail = out.tail.decode("utf-8", "replace").strip().splitlines()
    last = f" (it printed last: {_message(tail[-1])})" if tail and code else ""
    if out.over:
        status, ended = "killed", f"its process printed more than {OUTPUT_BYTES // 1024} KiB and was stopped"
    elif timed_out:
        status, ended = "stopped", (f"its process was stopped at the hard limit of {limit:g} s "
                                    "(code that never returns, or catches the time-out)")
    elif code == 0:
        status, ended = "graded", "its process ended (exit code 0) before finishing this exercise"
    elif code < 0:
        name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else str(-code)
        why = {"SIGXCPU": "its CPU-time limit", "SIGXFSZ": "its file-size limit",
               "SIGKILL": "a kill (memory, CPU or a limit)"}.get(name, name)
        status, ended = "killed", f"its process was killed by {name} ({why}){last}"
    else:
        status, ended = "exited", f"its process ended (exit code {code}) before finishing this exercise{last}"
    return {"status": status, "ended": ended, "killed": killed}


def grade_all(paths: list[str | Path], timeout: float = CASE_TIMEOUT_S, limit: float = STUDENT_LIMIT_S,
              memory_mb: int = MEMORY_MB, seed: int | None = None, json_path: str | Path | None = None,
              verbose: bool = False, print_table: bool = True, confine: bool = True) -> list[dict]:
    """Grade every path, one student process each; the results (and ``json_path``, rewritten as
    each student finishes) have one entry per path, whatever happened to the others."""
    prepared = prepare(seed)
    results = []
    sandbox.guard_grader(True)
    try:
        _grade_each(paths, prepared, results, timeout, limit, memory_mb, json_path, verbose, print_table, confine)
    finally:
        sandbox.guard_grader(False)
    if print_table and len(results) > 1:
        print("\n" + summary(results))
    return results


def _grade_each(paths, prepared, results, timeout, limit, memory_mb, json_path, verbose, print_table, confine):
    for i, path in enumerate(paths):
        if print_table and i:
            print()
        try:
            results.append(grade(path, prepared, timeout, limit, memory_mb, confine, verbose, print_table))
        except FileNotFoundError as e:
            if print_table:
                print(f"Autograder: {e}")
            results.append({"path": str(path), "status": "no submission", "score": 0.0, "max": 0.0,
                            "percent": 0.0, "exercises": [], "skipped": [], "error": str(e)})
        except Exception as e:  # noqa: BLE001 - the grader's own failure on one path: that row says so
            results.append({"path": str(path), "status": "grader error", "score": 0.0, "max": 0.0,
                            "percent": 0.0, "exercises": [], "skipped": [], "error": _message(repr(e))})
        sys.stdout.flush()
        if json_path:
            _write_json(Path(json_path), results if len(paths) > 1 else results[0])


def summary(results: list[dict]) -> str:
    width = max(len(r["path"]) for r in results)
    lines = ["Summary"]
    for r in results:
        lines.append(f"{r['path'].ljust(width)}  {points(r['score'])}/{points(r['max'])}  "
                     f"({r['percent']:.1f} %)  {r['status']}")
    return "\n".join(lines)


def _write_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(path)


def format_table(result: dict, verbose: bool = False) -> str:
    """The score table of one ``grade`` result, as plain text."""
    rows = [("notebook", "exercise", "score", "status")]
    notes = {}
    for e in result["exercises"]:
        rows.append((e["notebook"], e["exercise"], f"{points(e['score'])}/{points(e['max'])}", e["status"]))
        lines = []
        if e["status"] in ("missing", "stopped", "refused"):
            lines.append(e.get("message", ""))
        elif e["status"] != "not implemented":
            for c in e["cases"]:
                if verbose or not c["ok"]:
                    mark = "ok  " if c["ok"] else "FAIL"
                    text = f"{mark} {points(c['points'])}/{points(c['max'])}  {c['name']}"
                    lines.append(text + (f": {c['message']}" if c["message"] else ""))
        notes[len(rows) - 1] = lines
    rows.append(("total", "", f"{points(result['score'])}/{points(result['max'])}", f"{result['percent']:.1f} %"))
    if result.get("stopped"):
        notes[len(rows) - 1] = [f"{result['status']}: {result['stopped']}"]
    widths = [max(len(r[k]) for r in rows) for k in range(4)]
    out = [f"Autograder: {result['path']}"]
    for i, row in enumerate(rows):
        if i == len(rows) - 1:
            out.append("  ".join("-" * w for w in widths))
        out.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
        if i == 0:
            out.append("  ".join("-" * w for w in widths))
        for line in notes.get(i, []):
            out.append(" " * 4 + line)
    if not result["exercises"]:
        out.append("(no exercise found)")
    for line in result.get("skipped", []):
        out.append(f"skipped {line}")
    if result.get("confined") is False:
        out.append("note: the student's process was not confined (no Landlock here): it could read your files")
    return "\n".join(out)
