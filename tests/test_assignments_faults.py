"""Issues 16 and 41: the grader survives its students, and trusts nothing they write.

Each student is graded in a process of their own with a hard time limit, memory and output
limits; a student who hangs (catching the time-out), exits, floods the output or exhausts
memory loses only their own unfinished exercises, and every path gets its row. Monkeypatching
the library or NumPy in the student's process changes nothing the grader computes. The pieces:
answers are read as data only (no pickles, no code), and the reference answers deliberately
wrong in the student's process however it is reached.
"""
import importlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import fusion_key_source, fusion_student

from freereg_lib.teaching import assignments as A
from freereg_lib.teaching import poison, wire

# The hard limit of one student's process below. Every student but the one who hangs must finish
# within it, start-up included: a student process imports nbformat, torch and the library (~6 s of
# CPU, measured on a busy 2-core machine), 2-3x slower when the cores are shared. The hanging
# student costs exactly this long (asleep, no CPU).
LIMIT_S = 45


def _student(folder: Path, fuse_source: str) -> Path:
    """A 03_fusion notebook: the key's student_mutual_nn, and ``fuse_source`` as student_fuse."""
    return fusion_student(folder, fusion_key_source("student_mutual_nn"), fuse_source)


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
np.allclose = lambda *a, **k: True
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""
CALLS_REFERENCE = """
from freereg_lib.features import fuse as combine
def student_fuse(f_d, f_g, w):
    return combine(f_d, f_g, w)
"""
RELOADS = """
import importlib, sys
def student_fuse(f_d, f_g, w):
    sys.modules.pop("freereg_lib.features", None)
    fresh = importlib.import_module("freereg_lib.features")
    return importlib.reload(fresh).fuse(f_d, f_g, w)
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


def test_each_student_in_its_own_process_results_written_as_each_finishes(tmp_path, capsys):
    students = {name: _student(tmp_path / name, source) for name, source in [
        ("hangs", HANGS), ("exits", EXITS), ("patches", PATCHES_IN_CALL), ("numpy", PATCHES_NUMPY),
        ("calls", CALLS_REFERENCE), ("reloads", RELOADS), ("memory", fusion_key_source("student_fuse") + HOGS_MEMORY),
        ("floods", FLOODS),
        ("honest", fusion_key_source("student_fuse"))]}
    report = tmp_path / "scores.json"
    argv = ["grade", *map(str, students.values()), "--json", str(report), "--timeout", "5", "--limit", str(LIMIT_S),
            "--memory-mb", "3072"]
    assert A.main(argv) == 0
    out = capsys.readouterr().out
    results = {Path(r["path"]).parent.name: r for r in json.loads(report.read_text())}
    assert list(results) == list(students)  # every student, the ones after the faults too
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
    for s in ("calls", "reloads"):
        e = by[s]["student_fuse"]
        assert e["score"] == 0 and e["status"] == "refused" and "freereg_lib.features.descriptors.fuse" in e["message"], e
    memory = by["memory"]["student_fuse"]
    assert memory["score"] == 5 and "MemoryError" in memory["cases"][0]["message"], memory
    floods = by["floods"]["student_fuse"]
    assert floods["score"] == 0 and results["floods"]["status"] == "killed" and "printed more than" in floods["message"]
    assert "hard limit" in out and "refused" in out and "Summary" in out


def test_a_top_level_monkeypatch_in_the_solution_cell_changes_nothing_the_grader_computes(tmp_path):
    path = _student(tmp_path / "cell", "from freereg_lib import features\n"
                    "def student_fuse(f_d, f_g, w):\n    return features.fuse(f_d, f_g, w) * 0\n"
                    "features.fuse = student_fuse\n")
    result = A.grade(path, timeout=5, print_table=False, limit=60)
    fuse = next(e for e in result["exercises"] if e["exercise"] == "student_fuse")
    assert fuse["score"] == 0 and fuse["status"] == "failed"


# --------------------------------------------------------------------------------------
# The pieces.

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


def test_the_alteration_beats_every_tolerance_and_the_grader_reproduces_it():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 8)).astype(np.float32)
    y = poison.perturb(x, "k")
    assert y.dtype == x.dtype and (~np.isclose(y, x, atol=1e-6, rtol=1e-4)).all()
    assert np.array_equal(y, poison.perturb(x.copy(), "k")) and not np.array_equal(y, poison.perturb(x, "other"))
    assert poison.perturb(np.zeros(3), "k").any() and poison.perturb(True, "k") is False
    idx = np.arange(10)
    assert not np.array_equal(poison.perturb((idx, idx), "k")[0], idx)
    from freereg_lib import features

    f_d, f_g = rng.normal(size=(5, 3)), rng.normal(size=(5, 4))
    with poison.altered(["features.descriptors.fuse"], "k"):
        altered = features.fuse(f_d, f_g, 0.5)
    assert np.array_equal(altered, poison.perturb(features.fuse(f_d, f_g, 0.5), "k"))


def test_in_the_student_process_the_reference_stays_altered_however_it_is_reached():
    code = textwrap.dedent("""
        import importlib, sys, threading, numpy as np
        from freereg_lib.teaching import poison
        poison.install(["features.descriptors.fuse"], "k")
        from freereg_lib import features
        from freereg_lib.features import fuse as alias
        a, b = np.eye(3), np.ones((3, 2))
        true = np.c_[0.5 * a, 0.5 * b / np.sqrt(2)]
        sys.setprofile(None)
        out = [alias(a, b, 0.5), features.fuse(a, b, 0.5), importlib.reload(features).fuse(a, b, 0.5)]
        sys.modules.pop("freereg_lib.features")
        out.append(importlib.import_module("freereg_lib.features").fuse(a, b, 0.5))
        t = threading.Thread(target=lambda: out.append(alias(a, b, 0.5)))
        t.start(); t.join()
        assert all(np.array_equal(o, out[0]) for o in out), out
        assert out[0].shape == true.shape and (~np.isclose(out[0], true, atol=1e-6, rtol=1e-4)).all(), out[0]
        assert np.allclose(features.l2_normalize(b), b / np.sqrt(2))  # helpers stay as they are
        print("altered", len(out))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "altered 5" in proc.stdout, proc.stderr[-2000:]
    assert abs(importlib.import_module("freereg_lib.features").fuse(np.eye(2), np.eye(2), 0.5)[0, 0] - 0.5) < 1e-4


def test_every_exercise_refuses_the_altered_reference_and_accepts_the_true_one():
    """Scored by the grader: the reference's own answers are full marks; the same calls made where
    the references answer altered (as in a student's process) are refused, exercise by exercise."""
    from freereg_lib.teaching import grader, student
    from freereg_lib.teaching.exercises import EXERCISES

    prepared = grader.prepare(seed=3)
    refs = sorted({r for e in EXERCISES.values() for r in e.refs})
    for name, ex in EXERCISES.items():
        def answers():
            return [[student.answer(ex.reference, tuple(a), None) for a in case] for case in prepared.inputs[name]]

        honest = grader.score_exercise(ex, prepared, answers())
        assert honest["score"] == ex.max_points and honest["status"] == "ok", honest
        with poison.altered(refs, prepared.poison_key):
            cheat = grader.score_exercise(ex, prepared, answers())
        assert cheat["score"] == 0 and cheat["status"] == "refused", (name, cheat["message"])
