"""grades.csv's maxima: ``points_possible.csv`` holds grades.csv's header and one
``Points Possible`` row; grades.csv stays one row per student (Moodle's import and pandas read
every row of it as a student); canvas.csv keeps its own row. Formula-like cells stay escaped."""
from __future__ import annotations

import csv

from freereg_lib.teaching import export
from freereg_lib.teaching.exercises import EXERCISES, points

FORMULA = "=HYPERLINK(\"http://x\")"


def _result(sid: str, scores: dict[str, float]) -> dict:
    exercises = [{"exercise": n, "score": scores.get(n, 0.0), "max": e.max_points} for n, e in EXERCISES.items()]
    return {"id": sid, "score": sum(scores.values()), "max": sum(e.max_points for e in EXERCISES.values()),
            "exercises": exercises, "attempts": []}


def test_points_possible_sits_beside_grades_csv_with_its_columns(tmp_path):
    first = next(iter(EXERCISES))
    results = [_result("s001", {first: 3.0}), _result(FORMULA, {})]
    extra = {"s001": {"id": "s001", "folder": "a", "name": "Ann", "-section": "@A"}, FORMULA: {"name": "+Eve"}}
    export.write_csv(results, tmp_path / "grades.csv", extra)
    export.write_points_possible(results, tmp_path / "points_possible.csv", extra)
    export.write_canvas(results, tmp_path / "canvas.csv", extra)
    grades = list(csv.reader(open(tmp_path / "grades.csv", newline="")))
    maxima = list(csv.reader(open(tmp_path / "points_possible.csv", newline="")))
    total = sum(e.max_points for e in EXERCISES.values())
    assert maxima[0] == grades[0] == ["id", "'-section", "name", *EXERCISES, "total", "attempts"]
    assert maxima[1] == ["Points Possible", "", "", *(points(e.max_points) for e in EXERCISES.values()),
                         points(total), ""]
    assert len(maxima) == 2 and len(grades) == 1 + len(results)  # grades.csv: a row per student, no more
    assert [r[0] for r in grades[1:]] == ["s001", "'" + FORMULA]
    assert grades[1][1:3] == ["'@A", "Ann"] and grades[2][2] == "'+Eve"
    assert not any(c and c[0] in "=+-@" for f in (grades, maxima) for r in f for c in r)
    canvas = list(csv.reader(open(tmp_path / "canvas.csv", newline="")))
    assert canvas[1] == ["Points Possible", "", "", "", "", points(total)]
