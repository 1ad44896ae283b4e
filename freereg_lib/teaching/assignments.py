"""Course assignments from the notebooks: the command, and the names the notebooks import.

The notebooks mark their exercises: a code cell tagged ``solution`` defines one or more
functions named ``student_<thing>``, and the cell tagged ``check`` after it compares them
with the library (``with exercise_check("student_<thing>"): ...``). From that:

* ``python -m freereg_lib.teaching.assignments make [--out assignments/student] [--key DIR]`` writes a
  student version of every notebook (stubs with hints instead of the solutions).
* ``python -m freereg_lib.teaching.assignments dist [--out assignments/handout] [--zip]`` builds what
  students receive: the library, the environment files and the student notebooks as
  ``notebooks/``; no answer key, no tests.
* ``python -m freereg_lib.teaching.assignments grade <notebook-or-folder> [...] [--json scores.json]``
  grades each submission: its solution cells run in a student process of their own (limits,
  Landlock confinement, a hard time limit) that only writes its answers, as data, to inputs
  drawn at grading time; this process, which runs no student code, computes the reference,
  scores, and alone writes the results. One row per path, whatever happened; exit code 0.
* ``python -m freereg_lib.teaching.assignments list`` prints the exercises.

The work is in :mod:`freereg_lib.teaching`; ``assignments/README.md`` is the teacher's guide.
"""
from __future__ import annotations

import argparse
import sys

from freereg_lib.teaching.exercises import EXERCISES, Case, Draw, Exercise, exercise_check, exercise_table  # noqa: F401
from freereg_lib.teaching.grader import (  # noqa: F401
    CASE_TIMEOUT_S,
    MEMORY_MB,
    STUDENT_LIMIT_S,
    format_table,
    grade,
    grade_all,
    prepare,
    summary,
)
from freereg_lib.teaching.notebooks import (  # noqa: F401
    BANNER_ID,
    CHECK_TAG,
    DEFAULT_DIST,
    DEFAULT_OUT,
    METADATA_KEY,
    NOTEBOOKS,
    SOLUTION_TAG,
    _defined_functions,
    _is_solution,
    _read,
    dist,
    fill,
    make,
    markdown_hint,
    stub_source,
    student_notebook,
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m freereg_lib.teaching.assignments", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_make = sub.add_parser("make", help="write the student versions of the notebooks")
    p_make.add_argument("--out", default=str(DEFAULT_OUT), help="folder for the student notebooks "
                        "(default: assignments/student of the project)")
    p_make.add_argument("--notebooks", default=str(NOTEBOOKS), help="the full notebooks (default: notebooks/)")
    p_make.add_argument("--key", default=None, help="also write the answer key (stripped originals) here; "
                        "keep it out of what students receive")
    p_dist = sub.add_parser("dist", help="build the student distribution (no answer key, no tests)")
    p_dist.add_argument("--out", default=str(DEFAULT_DIST), help="its folder (default: assignments/handout)")
    p_dist.add_argument("--notebooks", default=str(NOTEBOOKS), help="the full notebooks (default: notebooks/)")
    p_dist.add_argument("--zip", action="store_true", help="also pack the folder as <out>.zip")
    p_grade = sub.add_parser("grade", help="grade student notebooks and print the scores")
    p_grade.add_argument("paths", nargs="+", help="a student notebook, or a folder of one student's notebooks")
    p_grade.add_argument("--timeout", type=float, default=CASE_TIMEOUT_S,
                         help="seconds allowed per call of a student's function (default 30)")
    p_grade.add_argument("--limit", type=float, default=STUDENT_LIMIT_S,
                         help="hard limit in seconds for one student's process (default 600)")
    p_grade.add_argument("--memory-mb", type=int, default=MEMORY_MB,
                         help="address-space limit of one student's process in MiB (default 4096)")
    p_grade.add_argument("--seed", type=int, default=None,
                         help="the inputs' seed (default: a secret one per run; fix it to re-grade alike)")
    p_grade.add_argument("--json", default=None, help="also write the results to this JSON file")
    p_grade.add_argument("-v", "--verbose", action="store_true", help="list every case, not just the failed ones")
    sub.add_parser("list", help="list the exercises")
    args = parser.parse_args(argv)

    if args.command == "make":
        written = make(args.out, args.notebooks, args.key)
        for path in written:
            names = _read(path).metadata.get(METADATA_KEY, {}).get("exercises", [])
            print(f"{path}: {', '.join(names) if names else 'no exercise'}")
        if args.key:
            print(f"answer key: {args.key} (keep it out of what students receive)")
        return 0
    if args.command == "dist":
        print(f"student distribution: {dist(args.out, args.notebooks, zip_file=args.zip)}")
        return 0
    if args.command == "list":
        print(exercise_table())
        return 0
    grade_all(args.paths, args.timeout, args.limit, args.memory_mb, args.seed, args.json, args.verbose)
    return 0


if __name__ == "__main__":
    sys.exit(main())
