"""What grading writes for the teacher and the students: ``grades.csv``, the LMS gradebook, the feedback files.

Everything here treats a student's id and a student's message as hostile text:

* :func:`cell`: a CSV cell never starts a formula (``=``, ``+``, ``-``, ``@``, a tab or a line
  break get a leading ``'``, as OWASP advises for CSV injection), so a spreadsheet shows the id
  ``=cmd|' /C calc'!A0`` as text instead of running it.
* :func:`feedback`: the Markdown escapes HTML (``<script>`` shows as text) and Markdown's own
  marks, and holds no absolute path (a message naming ``/home/teacher/submissions/bob/...``
  shows ``.../03_fusion.ipynb``): a student sees neither the teacher's folders nor a classmate's.
* :func:`feedback_file` and :func:`check_ids`: each id has a file of its own; two ids whose file
  names would be the same (``a b`` and ``a_b``; ``Ann`` and ``ann`` on a case-blind disk) are an
  error naming both, before any grading.

The exports: ``grades.csv`` (one row per student: ``id``, the roster's other columns, one column
per exercise, ``total``, and ``attempts``: what the student's code tried to read or write outside
its folder), ``points_possible.csv`` (:func:`write_points_possible`: grades.csv's header and one
``Points Possible`` row, each exercise's maximum and the total's) and ``canvas.csv``
(:func:`write_canvas`, Canvas's gradebook import: a ``Points Possible`` row under the header,
students by ``SIS User ID``). grades.csv keeps no such row: Moodle's grade import, pandas and a
``csv.DictReader`` read every row of it as a student, and a "Points Possible" student would be
imported, averaged and sorted with the class. A spreadsheet user pastes points_possible.csv's
second row under grades.csv's header (the columns are the same, in the same order).
"""
from __future__ import annotations

import csv
import html
import re
from pathlib import Path

from freereg_lib.teaching.exercises import EXERCISES, points

FORMULA_START = ("=", "+", "-", "@", "\t", "\r", "\n")
CANVAS_COLUMNS = ("Student", "ID", "SIS User ID", "SIS Login ID", "Section")
CANVAS_ASSIGNMENT = "FreeReg notebooks"
_MARKDOWN = re.compile(r"[\\`*\[\]|~]|(?<!\w)_|_(?!\w)")  # marks that act mid-line (an intraword _ does not)
_ABSOLUTE = re.compile(r"(?<![\w.~])(?:[A-Za-z]:)?(?:/[^\s/'\"(),:;|]+){2,}/?")


class IdError(ValueError):
    """Two students the gradebook cannot tell apart (one file name, one roster id for two folders)."""


def cell(value) -> str:
    """``value`` as a CSV cell no spreadsheet reads as a formula."""
    text = str(value)
    return "'" + text if text.startswith(FORMULA_START) else text


def feedback_file(out: str | Path, sid: str) -> Path:
    """``out/feedback/<id>.md``: the id with anything but letters, digits, ``.@-_`` replaced by ``_``."""
    name = re.sub(r"[^\w.@-]+", "_", sid).lstrip(".") or "_"
    return Path(out) / "feedback" / f"{name}.md"


def check_ids(ids: dict[str, str]) -> None:
    """Raise :class:`IdError` when two ids of ``{id: where it comes from}`` share a feedback file."""
    taken: dict[str, str] = {}
    for sid in ids:
        name = feedback_file("", sid).name.casefold()
        if name in taken:
            other = taken[name]
            raise IdError(f"ids {other!r} ({ids[other]}) and {sid!r} ({ids[sid]}) share the feedback file "
                          f"feedback/{feedback_file('', sid).name}: give one another id (a roster row: id,folder)")
        taken[name] = sid


def public(text: str) -> str:
    """``text`` without absolute paths: each keeps its last part (``.../03_fusion.ipynb``)."""
    return _ABSOLUTE.sub(lambda m: ".../" + m.group(0).rstrip("/").rsplit("/", 1)[-1], str(text))


def md(text) -> str:
    """``text`` safe in one line of Markdown: no path, no HTML, no Markdown mark, no line break."""
    text = " ".join(public(text).split())
    return _MARKDOWN.sub(lambda m: "\\" + m.group(0), html.escape(text, quote=False))


def _fence(text: str) -> list[str]:
    """``text`` as a fenced code block no line of it can close (HTML shows as text there)."""
    ticks = "`" * max(3, 1 + max((len(m) for m in re.findall(r"`+", text)), default=0))
    return [f"{ticks}python", *public(text).splitlines(), ticks]


def feedback(result: dict) -> str:
    """One student's feedback, as Markdown: score, each exercise's status, each check, and a failed
    check's inputs (drawn anew each grading run, so they can be shown)."""
    lines = [f"# Feedback: {md(result['id'])}", "",
             f"**{points(result['score'])} / {points(result['max'])} points** ({md(result['status'])}).", ""]
    if result.get("stopped"):
        lines += [f"Your notebooks' process did not finish: {md(result['stopped'])}.", ""]
    for note in result.get("chosen", []):
        lines += [f"Note: {md(note)}.", ""]
    lines += ["| notebook | exercise | points | result |", "|---|---|---|---|"]
    lines += [f"| {md(e['notebook'])} | {md(e['exercise'])} | {points(e['score'])} / {points(e['max'])} | "
              f"{md(e['status'])} |" for e in result["exercises"]]
    for e in result["exercises"]:
        lines += ["", f"## {md(e['exercise'])}: {md(e['title'])} ({points(e['score'])} / {points(e['max'])})", ""]
        if e["message"] and e["status"] not in ("partial", "failed"):
            lines.append(md(e["message"]))
        if e["status"] in ("ok", "partial", "failed"):
            for c in e["cases"]:
                lines.append(f"- {'passed' if c['ok'] else 'FAILED'} ({points(c['points'])} / {points(c['max'])}) "
                             f"{md(c['name'])}" + (f": {md(c['message'])}" if c["message"] else ""))
                if c.get("inputs"):
                    lines += ["", "  Its inputs (call your function with them to see it):", "",
                              *[f"  {line}" for line in _fence(c["inputs"])], ""]
    if result.get("attempts"):
        lines += ["", f"Your code tried to read or write outside its folder ({len(result['attempts'])} time(s)); "
                  "the grader refused it and your teacher is told."]
    if result.get("confined") is False:
        lines += ["", "_Graded without confinement (no Landlock): the student's code could read files._"]
    return "\n".join(lines) + "\n"


def _atomic_csv(path: Path, rows: list[list[str]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        csv.writer(f).writerows([[cell(v) for v in row] for row in rows])
    tmp.replace(path)


def write_csv(results: list[dict], path: Path, extra: dict[str, dict[str, str]]) -> None:
    """``grades.csv``: one row per student (id, the roster's other columns, each exercise, total, attempts)."""
    more = _columns(extra)
    rows = [["id", *more, *EXERCISES, "total", "attempts"]]
    for r in results:
        scores = {e["exercise"]: points(e["score"]) for e in r["exercises"]}
        rows.append([r["id"], *(extra.get(r["id"], {}).get(k, "") for k in more),
                     *(scores.get(n, "0") for n in EXERCISES), points(r["score"]), "; ".join(r.get("attempts", []))])
    _atomic_csv(path, rows)


def _columns(extra: dict[str, dict[str, str]]) -> list[str]:
    """grades.csv's roster columns (besides ``id`` and ``folder``), sorted."""
    return sorted({k for row in extra.values() for k in row} - {"id", "folder"})


def write_points_possible(results: list[dict], path: Path, extra: dict[str, dict[str, str]]) -> None:
    """``points_possible.csv``: grades.csv's header, then one row ``Points Possible`` with each
    exercise's maximum and the total's (the roster's columns and ``attempts`` empty)."""
    more = _columns(extra)
    top = max((r["max"] for r in results), default=sum(e.max_points for e in EXERCISES.values()))
    _atomic_csv(path, [["id", *more, *EXERCISES, "total", "attempts"],
                       ["Points Possible", *("" for _ in more), *(points(e.max_points) for e in EXERCISES.values()),
                        points(top), ""]])


def write_canvas(results: list[dict], path: Path, extra: dict[str, dict[str, str]],
                 assignment: str = CANVAS_ASSIGNMENT) -> None:
    """``canvas.csv``, as Canvas's gradebook import reads it: the columns ``Student, ID, SIS User ID,
    SIS Login ID, Section``, then the assignment (its total); a second row ``Points Possible`` holds
    its maximum. The roster's ``id`` goes to ``SIS User ID`` (Canvas matches students on it or on
    ``ID``); its columns ``name``, ``canvas_id``, ``login`` and ``section`` fill the others."""
    top = max((r["max"] for r in results), default=sum(e.max_points for e in EXERCISES.values()))
    rows = [[*CANVAS_COLUMNS, assignment], ["Points Possible", "", "", "", "", points(top)]]
    for r in results:
        more = extra.get(r["id"], {})
        rows.append([more.get("name") or r["id"], more.get("canvas_id", ""), r["id"], more.get("login", ""),
                     more.get("section", ""), points(r["score"])])
    _atomic_csv(path, rows)
