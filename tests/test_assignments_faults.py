"""Issue 16: the grader survives its students.

Each student is graded in a process of their own with a hard time limit; a student who
hangs (catching the time-out) or calls ``os._exit`` loses only their own unfinished
exercises; results are written as each student finishes; a solution that monkeypatches the
reference or just calls it scores zero with a message.
"""
import json
from pathlib import Path

import nbformat

from freereg_lib import assignments as A

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
# The hard limit of one student's grading process in the test below. Every student but the one
# who hangs must finish within it, start-up included: a grading process imports nbformat, torch
# and the library (~6 s of CPU, measured on a busy 2-core machine), and under `pytest -n 2` it
# shares the cores with the other worker and that worker's kernels or subprocesses (2-3x slower),
# so 20 s left too little room. The hanging student costs exactly this long (asleep, no CPU).
LIMIT_S = 60


def _key_source(name: str) -> str:
    nb = nbformat.read(str(NOTEBOOKS / "03_fusion.ipynb"), as_version=4)
    for cell in nb.cells:
        if A._is_solution(cell) and name in A._defined_functions(cell.source):
            return cell.source
    raise KeyError(name)


def _student(folder: Path, fuse_source: str) -> Path:
    """A 03_fusion notebook: the key's student_mutual_nn, and ``fuse_source`` as student_fuse."""
    nb = nbformat.v4.new_notebook()
    for source in (_key_source("student_mutual_nn"), fuse_source):
        cell = nbformat.v4.new_code_cell(source)
        cell.metadata["tags"] = ["solution"]
        nb.cells.append(cell)
    folder.mkdir(parents=True)
    path = folder / "03_fusion.ipynb"
    nbformat.write(nb, str(path))
    return path


HANGS = """
import time
def student_fuse(f_d, f_g, w):
    while True:  # a retry loop that swallows everything, the grader's time-out included
        try:
            time.sleep(0.1)
        except BaseException:
            pass
"""
EXITS = """
import os
def student_fuse(f_d, f_g, w):
    os._exit(0)
"""
PATCHES_IN_CALL = """
import numpy as np
from freereg_lib import features
def student_fuse(f_d, f_g, w):
    features.fuse = lambda a, b, w=0.5: np.zeros((len(a), a.shape[1] + b.shape[1]))
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""
PATCHES_NUMPY = """
import numpy as np
np.isclose = lambda a, b, **kw: np.ones(np.broadcast(a, b).shape, dtype=bool)
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""
CALLS_REFERENCE = """
from freereg_lib.features import fuse as combine
def student_fuse(f_d, f_g, w):
    return combine(f_d, f_g, w)
"""


def test_each_student_in_its_own_process_results_written_as_each_finishes(tmp_path, capsys):
    students = {name: _student(tmp_path / name, source) for name, source in [
        ("hangs", HANGS), ("exits", EXITS), ("patches", PATCHES_IN_CALL), ("numpy", PATCHES_NUMPY),
        ("calls", CALLS_REFERENCE), ("honest", _key_source("student_fuse"))]}
    report = tmp_path / "scores.json"
    argv = ["grade", *map(str, students.values()), "--json", str(report), "--timeout", "2", "--limit", str(LIMIT_S)]
    assert A.main(argv) == 0
    out = capsys.readouterr().out
    results = {Path(r["path"]).parent.name: r for r in json.loads(report.read_text())}
    assert list(results) == list(students)  # every student, the ones after the faults too
    by = {s: {e["exercise"]: e for e in r["exercises"]} for s, r in results.items()}
    for s in students:  # graded before the fault: kept (the hang's limit also covers a slow start)
        if s != "hangs" or by[s]["student_mutual_nn"]["status"] != "stopped":
            assert by[s]["student_mutual_nn"]["score"] == 10, (s, by[s]["student_mutual_nn"])
    assert by["honest"]["student_fuse"]["score"] == 10

    hang = by["hangs"]["student_fuse"]
    assert hang["score"] == 0 and hang["status"] == "stopped" and f"hard limit of {LIMIT_S} s" in hang["message"]
    exits = by["exits"]["student_fuse"]
    assert exits["score"] == 0 and "ended (exit code 0)" in exits["message"]
    for s in ("patches", "numpy"):
        e = by[s]["student_fuse"]
        assert e["score"] == 0 and "monkeypatching" in e["message"], e
    assert "numpy.isclose" in by["numpy"]["student_fuse"]["message"]
    assert "freereg_lib.features.fuse" in by["patches"]["student_fuse"]["message"]
    calls = by["calls"]["student_fuse"]
    assert calls["score"] == 0 and calls["status"] == "refused"
    assert "calls the library's reference freereg_lib.features.fuse" in calls["message"]
    assert "hard limit" in out and "calls the library's reference" in out


def test_a_top_level_monkeypatch_in_the_solution_cell_scores_zero(tmp_path):
    path = _student(tmp_path / "cell", "from freereg_lib import features\n"
                    "def student_fuse(f_d, f_g, w):\n    return features.fuse(f_d, f_g, w) * 0\n"
                    "features.fuse = student_fuse\n")
    result = A.grade(path, timeout=2, print_table=False, limit=60)
    fuse = next(e for e in result["exercises"] if e["exercise"] == "student_fuse")
    assert fuse["score"] == 0 and "monkeypatching" in fuse["message"]
