"""The grader survives its students, and trusts nothing they write.

Each student is graded in a process of their own with a hard time limit, memory and output
limits; a student who hangs (catching the time-out), exits, floods the output or exhausts
memory loses only their own unfinished exercises, and every path gets its row. Monkeypatching
NumPy or the runner in the student's process changes nothing the grader computes, and answers
are read as data only (no pickles, no code).
"""
from pathlib import Path

import numpy as np
import pytest
from conftest import HANGING_FUSE, fusion_key_source, fusion_student

from freereg_lib.teaching import gradebook, wire

# The hard limit of one student's process below. Every student but the one who hangs must finish
# within it, start-up included (a student process imports only NumPy: each of the others took
# ~0.2 s alone, more when the cores are shared). The hanging student costs exactly this long
# (asleep, no CPU), after catching its case's 3 s time-out: the limit must come after that.
LIMIT_S = 6


def _student(folder: Path, fuse_source: str) -> Path:
    """A 03_fusion notebook: the key's student_mutual_nn, and ``fuse_source`` as student_fuse."""
    return fusion_student(folder, fusion_key_source("student_mutual_nn"), fuse_source)


EXITS = """
import os
def student_fuse(f_d, f_g, w):
    os._exit(0)
"""
PATCHES_RUNNER = """
import numpy as np
from grading import student  # the runner's own module: patching it changes only this process's data
student.answer = lambda f, args, timeout: {"value": np.zeros((len(args[0]), args[0].shape[1] + args[1].shape[1]))}
def student_fuse(f_d, f_g, w):
    return np.zeros(3)
"""
PATCHES_NUMPY = """
import numpy as np
np.isclose = lambda a, b, **kw: np.ones(np.broadcast(a, b).shape, dtype=bool)
np.allclose = lambda *a, **k: True
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""
HOGS_MEMORY = """
_honest = student_fuse
def student_fuse(f_d, f_g, w):
    if w == 0.5:
        return np.ones(2**33)  # 64 GiB
    return _honest(f_d, f_g, w)
"""
FLOODS = """
import os
def student_fuse(f_d, f_g, w):
    while True:
        os.write(1, b"x" * 65536)
"""


def test_each_student_in_its_own_process_results_written_as_each_finishes(tmp_path):
    students = {name: _student(tmp_path / "class" / name, source) for name, source in [
        ("hangs", HANGING_FUSE), ("exits", EXITS), ("patches", PATCHES_RUNNER), ("numpy", PATCHES_NUMPY),
        ("memory", fusion_key_source("student_fuse") + HOGS_MEMORY), ("floods", FLOODS),
        ("honest", fusion_key_source("student_fuse"))]}
    out = tmp_path / "grades"
    rows = gradebook.grade_all([tmp_path / "class"], out=out, timeout=3, limit=LIMIT_S, memory_mb=3072, echo=False)
    results = {r["id"]: r for r in rows}
    assert list(results) == sorted(students)  # every student, the ones after the faults too
    by = {s: {e["exercise"]: e for e in r["exercises"]} for s, r in results.items()}
    for s in students:  # graded before the fault: kept (the hang's limit also covers a slow start)
        if s != "hangs" or by[s]["student_mutual_nn"]["status"] != "stopped":
            assert by[s]["student_mutual_nn"]["score"] == 10, (s, by[s]["student_mutual_nn"])
    assert by["honest"]["student_fuse"]["score"] == 10 and results["honest"]["status"] == "graded"

    hang = by["hangs"]["student_fuse"]
    assert hang["score"] == 0 and hang["status"] == "stopped" and f"hard limit of {LIMIT_S} s" in hang["message"]
    assert results["hangs"]["status"] == "stopped"
    exits = by["exits"]["student_fuse"]
    assert exits["score"] == 0 and "ended (exit code 0)" in exits["message"] and results["exits"]["status"] == "exited"
    for s in ("patches", "numpy"):  # their monkeypatches live and die in their own process
        e = by[s]["student_fuse"]
        assert e["score"] == 0 and e["status"] == "failed" and "values differ" in e["message"], e
    memory = by["memory"]["student_fuse"]
    assert memory["score"] == 5 and "MemoryError" in memory["cases"][0]["message"], memory
    floods = by["floods"]["student_fuse"]
    assert floods["score"] == 0 and results["floods"]["status"] == "killed" and "printed more than" in floods["message"]
    # The gradebook: a row per student, and each one's feedback says what stopped them.
    assert len((out / "grades.csv").read_text().splitlines()) == 1 + len(students)
    assert f"hard limit of {LIMIT_S} s" in (out / "feedback" / "hangs.md").read_text()


def test_answers_are_read_as_data_only(tmp_path):
    value = [({"value": np.arange(3.0)}, {"error": "x", "kind": "ValueError"}), 1.5, float("nan"), None, True]
    wire.save(tmp_path / "ok.npz", value)
    back = wire.load(tmp_path / "ok.npz")
    assert back[0][0]["value"].tolist() == [0.0, 1.0, 2.0] and back[1:4:2] == [1.5, None] and np.isnan(back[2])
    np.savez(tmp_path / "pickled.npz", __structure__=np.frombuffer(b'{"nd": "a0"}', np.uint8),
             a0=np.array([object()], dtype=object))
    (tmp_path / "junk.npz").write_text('{"result": {"score": 20}}')
    np.savez(tmp_path / "code.npz", __structure__=np.frombuffer(b'{"eval": "__import__(\'os\')"}', np.uint8))
    for name in ("pickled", "junk", "code", "absent"):
        with pytest.raises(wire.WireError):
            wire.load(tmp_path / f"{name}.npz")
    with pytest.raises(wire.WireError):
        wire.save(tmp_path / "obj.npz", object())
