"""A class at a time: collecting the returned notebooks, grading them, the gradebook and the feedback.

* :func:`collect` sorts what students handed back (one zip or folder per student, as an LMS
  download gives them) into ``submissions/<id>/``, notebooks only.
* :func:`grade_all` grades every student (:func:`.grader.grade`, one confined process each) on
  the same inputs and, as each finishes, rewrites ``grades.csv`` (one row per student: the id
  from the roster or the folder's name, a column per exercise, the total) and writes the
  student's feedback file, ``feedback/<id>.md``: each exercise's checks, their results and
  messages.
"""
from __future__ import annotations

import csv
import re
import sys
import zipfile
from pathlib import Path

from freereg_lib.teaching import grader
from freereg_lib.teaching import notebooks as N
from freereg_lib.teaching.exercises import EXERCISES, points

MAX_NOTEBOOK_BYTES = 50 * 2**20  # a returned "notebook" larger than this is not a notebook


def collect(returned: str | Path, out: str | Path) -> dict[str, list[str]]:
    """Copy the notebooks of each student's return (``returned/<id>.zip`` or ``returned/<id>/``)
    into ``out/<id>/``; returns the notebooks found per student. Paths inside a zip are dropped
    (only the file names are kept), so nothing is written outside ``out``."""
    found: dict[str, list[str]] = {}
    for entry in sorted(Path(returned).iterdir()):
        sid = entry.stem if entry.suffix == ".zip" else entry.name
        target = Path(out) / sid
        if entry.is_dir():
            files = {p.name: p.read_bytes() for p in N.notebooks_in(entry)  # a link could point at your files
                     if not p.is_symlink() and p.stat().st_size <= MAX_NOTEBOOK_BYTES}
        elif zipfile.is_zipfile(entry):
            with zipfile.ZipFile(entry) as z:
                files = {Path(i.filename).name: z.read(i) for i in z.infolist()
                         if i.filename.endswith(".ipynb") and "__MACOSX" not in i.filename
                         and ".ipynb_checkpoints" not in i.filename and i.file_size <= MAX_NOTEBOOK_BYTES}
        else:
            continue
        target.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            (target / name).write_bytes(data)
        found[sid] = sorted(files)
    return found


def read_roster(path: str | Path) -> list[dict[str, str]]:
    """A roster CSV: a column ``id`` (the id the LMS knows), optionally ``folder`` (the submission
    folder's name, when it is not the id) and any others (``name``, ...)."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = [{k.strip(): (v or "").strip() for k, v in row.items() if k} for row in csv.DictReader(f)]
    if not rows or "id" not in rows[0]:
        raise ValueError(f"{path}: a roster needs a header with a column 'id' (and optionally 'folder', 'name')")
    return rows


def submissions(paths: list[str | Path]) -> list[Path]:
    """Each student's submission: a folder of student folders counts as its sub-folders."""
    out = []
    for p in map(Path, paths):
        subs = sorted(d for d in p.iterdir() if d.is_dir() and N.notebooks_in(d)) if p.is_dir() else []
        out += subs if subs and not list(p.glob("*.ipynb")) else [p]
    return out


def _file(out: str | Path, sid: str) -> Path:
    return Path(out) / "feedback" / (re.sub(r"[^\w.@-]+", "_", sid).lstrip(".") + ".md")


def _absent(sid: str, why: str) -> dict:
    exercises = [grader.score_exercise(e, None, None, why) for e in EXERCISES.values()]
    return {"id": sid, "path": "", "status": why, "score": 0.0, "max": sum(e["max"] for e in exercises),
            "exercises": exercises}


def feedback(result: dict) -> str:
    """One student's feedback, as Markdown."""
    lines = [f"# Feedback: {result['id']}", "",
             f"**{points(result['score'])} / {points(result['max'])} points** ({result['status']}).", ""]
    if result.get("stopped"):
        lines += [f"Your notebooks' process did not finish: {result['stopped']}.", ""]
    lines += ["| notebook | exercise | points | result |", "|---|---|---|---|"]
    lines += [f"| {e['notebook']} | `{e['exercise']}` | {points(e['score'])} / {points(e['max'])} | {e['status']} |"
              for e in result["exercises"]]
    for e in result["exercises"]:
        lines += ["", f"## `{e['exercise']}`: {e['title']} ({points(e['score'])} / {points(e['max'])})", ""]
        if e["message"] and e["status"] not in ("partial", "failed"):
            lines.append(e["message"])
        if e["status"] in ("ok", "partial", "failed"):
            lines += [f"- {'passed' if c['ok'] else 'FAILED'} ({points(c['points'])} / {points(c['max'])}) "
                      f"{c['name']}" + (f": {c['message']}" if c["message"] else "") for c in e["cases"]]
    if result.get("confined") is False:
        lines += ["", "_Graded without confinement (no Landlock): the student's code could read files._"]
    return "\n".join(lines) + "\n"


def write_csv(results: list[dict], path: Path, extra: dict[str, dict[str, str]]) -> None:
    """``grades.csv``: one row per student (id, the roster's other columns, each exercise, total)."""
    more = sorted({k for row in extra.values() for k in row} - {"id", "folder"})
    with open(path.with_name(path.name + ".tmp"), "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["id", *more, *EXERCISES, "total"])
        for r in results:
            scores = {e["exercise"]: points(e["score"]) for e in r["exercises"]}
            w.writerow([r["id"], *(extra.get(r["id"], {}).get(k, "") for k in more),
                        *(scores.get(n, "0") for n in EXERCISES), points(r["score"])])
    path.with_name(path.name + ".tmp").replace(path)


def grade_all(paths: list[str | Path], out: str | Path | None = None, roster: str | Path | None = None,
              seed: int | None = None, timeout: float = grader.CASE_TIMEOUT_S, limit: float = grader.STUDENT_LIMIT_S,
              memory_mb: int = grader.MEMORY_MB, confine: bool = True, verbose: bool = False,
              echo: bool = True) -> list[dict]:
    """Grade every submission on the same inputs; with ``out``, ``grades.csv`` and ``feedback/``
    are (re)written as each student finishes. One result per student, whatever happened."""
    prepared = grader.prepare(seed)
    rows = read_roster(roster) if roster else []
    ids = {r.get("folder") or r["id"]: r["id"] for r in rows}
    if out:
        (Path(out) / "feedback").mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    for path in submissions(paths):
        name = path.parent.resolve().name if path.suffix == ".ipynb" else path.name  # a notebook: its folder
        try:
            result = grader.grade(path, prepared, timeout, limit, memory_mb, confine)
        except Exception as e:  # noqa: BLE001 - one path's failure (missing, or the grader's own) is that row
            result = _absent(name, f"not graded: {grader._message(e)}")
        result["id"] = ids.get(name, name)
        results.append(result)
        if echo:
            bad = "; ".join(f"{e['exercise']}: {e['message']}" for e in result["exercises"] if e["status"] != "ok")
            print(f"{result['id']}: {points(result['score'])}/{points(result['max'])} {result['status']}"
                  + (f"  ({bad})" if bad and verbose else ""), flush=True)
        if out:
            _file(out, result["id"]).write_text(feedback(result), encoding="utf-8")
            write_csv(results, Path(out) / "grades.csv", {r["id"]: r for r in rows})
    for row in rows:  # the roster's students who handed in nothing
        if row["id"] not in {r["id"] for r in results}:
            results.append(_absent(row["id"], "no submission"))
            if out:
                _file(out, row["id"]).write_text(feedback(results[-1]), encoding="utf-8")
    if out:
        write_csv(results, Path(out) / "grades.csv", {r["id"]: r for r in rows})
        if echo:
            print(f"{len(results)} students: {Path(out) / 'grades.csv'} and {Path(out) / 'feedback'}/")
    if echo and any(r.get("confined") is False for r in results):
        print("note: graded without confinement (no Landlock, or freereg_lib lies in a folder the students' "
              "process may read): their code could read your files and load the library by path (see the guide)",
              file=sys.stderr)
    return results
