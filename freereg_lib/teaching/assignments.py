"""Course assignments from the notebooks: the command, and the name the notebooks' check cells import.

* ``make [--out assignments/student] [--key DIR]`` writes a student version of every notebook
  (stubs with hints instead of the solutions).
* ``dist [--out assignments/handout] [--zip]`` builds what students receive: the student
  notebooks as ``notebooks/`` and the part of the library they import; no answer key, no grader.
* ``collect RETURNED --out submissions`` sorts the returned notebooks (a zip or a folder per
  student) into ``submissions/<id>/``.
* ``grade PATH [...] [--roster roster.csv] [--out grades]`` grades each student: the solution
  code of each exercise runs in a confined process with NumPy and the standard library only;
  this process alone computes the library's answers and scores. ``grades.csv`` and one
  feedback file per student go to ``--out``, with ``canvas.csv`` for an LMS. Exit code 0
  whatever the students did; 2 (one line, before any grading) for ids it cannot tell apart.
* ``list`` prints the exercises.

``assignments/README.md`` is the teacher's guide.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from freereg_lib.teaching import gradebook, grader, handout
from freereg_lib.teaching.check import exercise_check  # noqa: F401 - the check cells import it from here
from freereg_lib.teaching.exercises import exercise_table
from freereg_lib.teaching.notebooks import DEFAULT_OUT, METADATA_KEY, NOTEBOOKS, _read, make


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m freereg_lib.teaching.assignments",
                                     description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_make = sub.add_parser("make", help="write the student versions of the notebooks")
    p_make.add_argument("--out", default=str(DEFAULT_OUT), help="their folder (default: assignments/student)")
    p_make.add_argument("--notebooks", default=str(NOTEBOOKS), help="the full notebooks (default: notebooks/)")
    p_make.add_argument("--key", default=None, help="also write the answer key (stripped originals) here")
    p_dist = sub.add_parser("dist", help="build the student handout (no answer key, no grader)")
    p_dist.add_argument("--out", default=str(handout.DEFAULT_DIST), help="its folder (default: assignments/handout)")
    p_dist.add_argument("--notebooks", default=str(NOTEBOOKS), help="the full notebooks (default: notebooks/)")
    p_dist.add_argument("--zip", action="store_true", help="also pack the folder as <out>.zip")
    p_collect = sub.add_parser("collect", help="sort returned notebooks into one folder per student")
    p_collect.add_argument("returned", help="a folder holding one zip (<id>.zip) or folder (<id>/) per student")
    p_collect.add_argument("--out", default="submissions", help="where the students' folders go (default: submissions)")
    p_grade = sub.add_parser("grade", help="grade the students; write grades.csv and their feedback")
    p_grade.add_argument("paths", nargs="+", help="a folder of student folders, a student's folder or a notebook")
    p_grade.add_argument("--out", default=None, help="write grades.csv and feedback/<id>.md here")
    p_grade.add_argument("--roster", default=None, help="a CSV with a column id (and optionally folder, name)")
    p_grade.add_argument("--timeout", type=float, default=grader.CASE_TIMEOUT_S,
                         help="seconds allowed per call of a student's function (default 30)")
    p_grade.add_argument("--limit", type=float, default=grader.STUDENT_LIMIT_S,
                         help="hard limit in seconds for each exercise of a student (default 120)")
    p_grade.add_argument("--memory-mb", type=int, default=grader.MEMORY_MB,
                         help="address-space limit of one student's process in MiB (default 4096)")
    p_grade.add_argument("--seed", type=int, default=None, help="the inputs' seed (default: new each run)")
    p_grade.add_argument("-v", "--verbose", action="store_true", help="say why each exercise lost points")
    sub.add_parser("list", help="list the exercises")
    args = parser.parse_args(argv)

    if args.command == "make":
        for path in make(args.out, args.notebooks, args.key):
            names = _read(path).metadata.get(METADATA_KEY, {}).get("exercises", [])
            print(f"{path}: {', '.join(names) if names else 'no exercise'}")
        if args.key:
            print(f"answer key: {args.key} (keep it out of what students receive)")
    elif args.command == "dist":
        print(f"student handout: {handout.dist(args.out, args.notebooks, zip_file=args.zip)}")
    elif args.command == "collect":
        try:
            collected = gradebook.collect(args.returned, args.out)
        except (gradebook.IdError, OSError) as exc:  # before anything is written: one line, exit 2
            print(f"collect: {exc}", file=sys.stderr)
            return 2
        for sid, names in collected.items():
            print(f"{sid}: {len(names)} notebook(s){': ' + ', '.join(names) if names else ''}")
            for note in gradebook.duplicates(Path(args.out) / sid):
                print(f"  note: {note}")
    elif args.command == "list":
        print(exercise_table())
    else:
        try:
            gradebook.grade_all(args.paths, args.out, args.roster, args.seed, args.timeout, args.limit,
                                args.memory_mb, verbose=args.verbose)
        except (gradebook.IdError, ValueError, OSError) as exc:  # the ids and the roster, checked before grading
            print(f"grade: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
