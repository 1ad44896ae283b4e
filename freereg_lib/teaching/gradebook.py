"""A class at a time: collecting the returned notebooks, grading them, the gradebook and the feedback.

* :func:`collect` sorts what students handed back (one zip or folder per student, as an LMS
  download gives them) into ``submissions/<id>/``, notebooks only, keeping their times. A name
  that would leave that folder (``..zip``), or two returns with one id, stop it before it writes.
* :func:`grade_all` checks every id first (:func:`.export.check_ids`: one feedback file each, a
  roster id for one folder only), grades every student (:func:`.grader.grade`) on the same inputs
  and, as each finishes, rewrites ``grades.csv`` and ``canvas.csv`` (:mod:`.export`) and writes
  the student's feedback file, ``feedback/<id>.md``.

The folders it writes (``submissions/``, the grades folder) get a ``.gitignore`` of ``*``: a
``git add -A`` in a course repository does not commit students' work or grades.
"""
from __future__ import annotations

import csv
import os
import sys
import time
import zipfile
from pathlib import Path

from freereg_lib.teaching import grader
from freereg_lib.teaching import notebooks as N
from freereg_lib.teaching.exercises import EXERCISES, points
from freereg_lib.teaching.export import (IdError, check_ids, feedback, feedback_file, write_canvas,  # noqa: F401
                                         write_csv, write_points_possible)

MAX_NOTEBOOK_BYTES = 50 * 2**20  # a returned "notebook" larger than this is not a notebook
IGNORE_ALL = "# Written by freereg_lib.teaching: students' work and grades stay out of git.\n*\n"


def ignore_in_git(folder: Path) -> None:
    """A ``.gitignore`` of ``*`` in ``folder`` (left alone when there is one)."""
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / ".gitignore").exists():
        (folder / ".gitignore").write_text(IGNORE_ALL, encoding="utf-8")


def _return_id(entry: Path) -> str | None:
    """The student id a return's name gives (``<id>.zip`` or ``<id>/``); None for other files."""
    if entry.is_dir():
        return entry.name
    return entry.name[:-4] if entry.name.lower().endswith(".zip") and zipfile.is_zipfile(entry) else None


def _bad_id(sid: str) -> str:
    if sid in ("", ".", "..") or sid.startswith(".") or any(c in sid for c in "/\\\0"):
        return "not a folder name inside the submissions folder (empty, starting with '.', or holding a slash)"
    return ""


def returns(returned: str | Path) -> dict[str, Path]:
    """``{id: return}`` of the folder ``returned``; :class:`IdError` (naming the file) for a name that
    leaves the submissions folder or an id given twice (``alice.zip`` beside ``alice/``)."""
    found: dict[str, Path] = {}
    for entry in sorted(Path(returned).iterdir()):
        if entry.name == ".ipynb_checkpoints":
            continue
        sid = _return_id(entry)
        if sid is None:
            continue
        if why := _bad_id(sid):
            raise IdError(f"{entry}: the id its name gives, {sid!r}, is {why}; rename it <id>.zip or <id>/")
        twin = next((other for other in found if other.casefold() == sid.casefold()), None)
        if twin is not None:
            raise IdError(f"{found[twin]} and {entry} are both returns of student {sid!r}: keep one (or rename one)")
        found[sid] = entry
    return found


def collect(returned: str | Path, out: str | Path) -> dict[str, list[str]]:
    """Copy the notebooks of each student's return (``returned/<id>.zip`` or ``returned/<id>/``)
    into ``out/<id>/``, with their times; returns the notebooks found per student. Paths inside a
    zip are dropped (only the file names are kept), and every id is checked (:func:`returns`)
    before anything is written, so nothing is written outside ``out``."""
    if Path(out).resolve() == Path(returned).resolve() or Path(out).resolve().is_relative_to(Path(returned).resolve()):
        raise IdError(f"--out {out}: inside the returns' folder {returned}, which collect reads; give another folder "
                      "(e.g. submissions/)")
    found: dict[str, list[str]] = {}
    for sid, entry in returns(returned).items():
        target = Path(out) / sid
        if entry.is_dir():
            files = {p.name: (p.read_bytes(), p.stat().st_mtime) for p in N.notebooks_in(entry)  # a link could
                     if not p.is_symlink() and p.stat().st_size <= MAX_NOTEBOOK_BYTES}     # point at your files
        else:
            with zipfile.ZipFile(entry) as z:
                files = {Path(i.filename).name: (z.read(i), time.mktime((*i.date_time, 0, 0, -1)))
                         for i in z.infolist()
                         if i.filename.endswith(".ipynb") and "__MACOSX" not in i.filename
                         and ".ipynb_checkpoints" not in i.filename and i.file_size <= MAX_NOTEBOOK_BYTES}
        ignore_in_git(Path(out))
        target.mkdir(parents=True, exist_ok=True)
        for name, (data, mtime) in files.items():
            (target / name).write_bytes(data)
            os.utime(target / name, (mtime, mtime))  # "the newest of two copies" needs the student's times
        found[sid] = sorted(files)
    return found


def duplicates(folder: Path) -> list[str]:
    """What the grader will say about two versions of one notebook in a student's folder."""
    kept, notes, ties = grader.choose_notebooks(N.notebooks_in(folder))
    return notes + list(ties.values())


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


def _absent(sid: str, why: str) -> dict:
    exercises = [grader.score_exercise(e, None, None, why) for e in EXERCISES.values()]
    return {"id": sid, "path": "", "status": why, "score": 0.0, "max": sum(e["max"] for e in exercises),
            "exercises": exercises}


def plan(paths: list[str | Path], rows: list[dict[str, str]]) -> list[tuple[Path, str]]:
    """Each submission of ``paths`` and its student's id (the roster's, else its folder's name), checked
    before any grading: :class:`IdError` naming both for a roster id given to two folders, a folder given
    two ids, two submissions with one id, or two ids sharing a feedback file (:func:`.export.check_ids`)."""
    folder_of: dict[str, str] = {}
    id_of: dict[str, str] = {}
    for k, row in enumerate(rows, start=2):
        sid, folder = row["id"], row.get("folder") or row["id"]
        if not sid:
            raise IdError(f"roster line {k}: no id (every row needs one)")
        if sid in folder_of:
            raise IdError(f"roster: id {sid!r} is given to two folders, {folder_of[sid]!r} and {folder!r}: "
                          "give each student their own id")
        if folder in id_of:
            raise IdError(f"roster: folder {folder!r} has two ids, {id_of[folder]!r} and {sid!r}: keep one row")
        folder_of[sid], id_of[folder] = folder, sid
    planned: list[tuple[Path, str]] = []
    where: dict[str, str] = {}
    for path in submissions(paths):
        name = path.parent.resolve().name if path.suffix == ".ipynb" else path.name  # a notebook: its folder
        sid = id_of.get(name, name)
        if sid in where:
            raise IdError(f"{where[sid][5:]} and {str(path)!r} both get the id {sid!r}: rename a folder or map "
                          "them in the roster")
        where[sid] = f"from {str(path)!r}"  # quoted: a folder's name may hold a line break
        planned.append((path, sid))
    for sid in folder_of:
        where.setdefault(sid, "the roster, no submission")
    check_ids(where)
    return planned


def _say(result: dict, verbose: bool) -> None:
    bad = "; ".join(f"{e['exercise']}: {e['message']}" for e in result["exercises"] if e["status"] != "ok")
    print(f"{result['id']}: {points(result['score'])}/{points(result['max'])} {result['status']}"
          + (f"  ({bad})" if bad and verbose else ""), flush=True)
    for note in result.get("chosen", []):
        print(f"  note: {note}", flush=True)
    if result.get("attempts"):
        print(f"  ATTEMPTS outside its folder (refused): {'; '.join(result['attempts'])}", flush=True)


def _write(out: Path, results: list[dict], extra: dict[str, dict[str, str]]) -> None:
    write_csv(results, out / "grades.csv", extra)
    write_points_possible(results, out / "points_possible.csv", extra)
    write_canvas(results, out / "canvas.csv", extra)


def grade_all(paths: list[str | Path], out: str | Path | None = None, roster: str | Path | None = None,
              seed: int | None = None, timeout: float = grader.CASE_TIMEOUT_S, limit: float = grader.STUDENT_LIMIT_S,
              memory_mb: int = grader.MEMORY_MB, confine: bool = True, verbose: bool = False,
              echo: bool = True) -> list[dict]:
    """Grade every submission on the same inputs; with ``out``, ``grades.csv``, ``points_possible.csv``,
    ``canvas.csv`` and ``feedback/`` are (re)written as each student finishes. One result per student, whatever
    happened. The ids are checked first (:func:`plan`: :class:`IdError` before any grading)."""
    rows = read_roster(roster) if roster else []
    planned = plan(paths, rows)
    for path, _ in planned if out else []:  # the grades must not land among what is graded
        if path.is_dir() and Path(out).resolve().is_relative_to(path.resolve()):
            raise IdError(f"--out {out}: inside the submission {path}; give a folder of its own (e.g. grades/)")
    extra = {r["id"]: r for r in rows}
    prepared = grader.prepare(seed)
    if out:
        out = Path(out)
        ignore_in_git(out)
        (out / "feedback").mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    for path, sid in planned:
        try:
            result = grader.grade(path, prepared, timeout, limit, memory_mb, confine)
        except Exception as e:  # noqa: BLE001 - one path's failure (missing, or the grader's own) is that row
            result = _absent(sid, f"not graded: {grader._message(e)}")
        result["id"] = sid
        results.append(result)
        if echo:
            _say(result, verbose)
        if out:
            feedback_file(out, sid).write_text(feedback(result), encoding="utf-8")
            _write(out, results, extra)
    for row in rows:  # the roster's students who handed in nothing
        if row["id"] not in {r["id"] for r in results}:
            results.append(_absent(row["id"], "no submission"))
            if out:
                feedback_file(out, row["id"]).write_text(feedback(results[-1]), encoding="utf-8")
    tried = [f"{r['id']} ({len(r['attempts'])})" for r in results if r.get("attempts")]
    if out:
        _write(out, results, extra)
    if echo:
        if out:
            print(f"{len(results)} students: {out / 'grades.csv'} (its maxima: {out / 'points_possible.csv'}), "
                  f"{out / 'canvas.csv'} and {out / 'feedback'}/")
        if tried:
            print(f"{len(tried)} student(s) tried to read or write outside their folder (refused; listed in the "
                  f"column 'attempts' of grades.csv): {', '.join(tried)}")
    if echo and any(r.get("confined") is False for r in results):
        print("note: graded without confinement (no Landlock, or freereg_lib lies in a folder the students' "
              "process may read): their code could read your files and load the library by path (see the guide)",
              file=sys.stderr)
    return results
