"""Answers graded where the library's answer cannot be reached.

The solution code runs in a confined process with NumPy and the standard library only:
``freereg_lib`` is not on its import path and (Landlock) its files cannot be read. The six
ways of calling the reference that beat the previous grader score 0 on the exercise
they cheat, written plainly (refused before anything runs: the cell names ``freereg_lib``) and
disguised (the name spelt in pieces: the import fails in the student's process). So does every
way of importing the library: directly, through ``importlib``, by path, after editing
``sys.path`` or ``sys.meta_path``. The honest student gets full marks, the stub 0 with "not
done", and the process-level cheats still fail: forged answer files, children that
escape with ``setsid()``, reading the answer key, killing the grader. One grading run covers
them all (one confined process per student).
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import key_source, student_notebook

from freereg_lib.teaching import check, gradebook, grader, sandbox
from freereg_lib.teaching.notebooks import make

ROOT = Path(__file__).resolve().parent.parent
LANDLOCK = sandbox.landlock_abi() > 0
PLAIN = "from freereg_lib{package} import {module}\n"
DISGUISED = "import importlib\n{module} = importlib.import_module('freereg' + '_lib{package}.{module}')\n"

# The six cheats: (the exercise, its notebook, the library module it reaches, the cell).
SIX = {
    "hook_fuse": ("student_fuse", "03_fusion", "", "features", """
features.__freereg_graded_reference__ = lambda v: v
def student_fuse(f_d, f_g, w):
    return features.fuse(f_d, f_g, w)
"""),
    "hook_matching": ("student_mutual_nn", "03_fusion", ".features", "matching", """
matching.__freereg_graded_reference__ = lambda v: v
def student_mutual_nn(fa, fb):
    return matching.mutual_nn(fa, fb)
"""),
    "both_cpu": ("student_mutual_nn", "03_fusion", ".features", "matching", """
import torch
def student_mutual_nn(fa, fb):
    ab, ba = matching._both_cpu(torch.as_tensor(fa, dtype=torch.float32), torch.as_tensor(fb, dtype=torch.float32), 2048)
    idx_a = np.nonzero(ba[ab] == np.arange(len(ab)))[0]
    return idx_a, ab[idx_a]
"""),
    "meta_path_fuse": ("student_fuse", "03_fusion", "", "features", """
import sys
sys.meta_path[:] = [f for f in sys.meta_path if "freereg" not in repr(f)]
def student_fuse(f_d, f_g, w):
    return features.fuse(f_d, f_g, w)
"""),
    "meta_path_kabsch": ("student_kabsch", "02_geometric_features", ".geometry", "pose", """
import sys
sys.meta_path[:] = [f for f in sys.meta_path if "freereg" not in repr(f)]
def student_kabsch(src, dst):
    return pose._umeyama(np.asarray(src, float)[None], np.asarray(dst, float)[None], False)[0]
"""),
    "match_distances": ("student_inlier_ratio", "00_preliminaries", ".geometry", "metrics", """
def student_inlier_ratio(uv_image, pts_pc, depth_gt, K_image, T_cam_pc, tau_c=0.3, depth_range=(0.01, 10.0)):
    dist, evaluable, _ = metrics.match_distances(uv_image, pts_pc, depth_gt, K_image, T_cam_pc, depth_range)
    return float(np.mean(dist[evaluable] < tau_c)) if evaluable.sum() >= 3 else 0.0
"""),
}

FUSE = "def student_fuse(f_d, f_g, w):\n    return features.fuse(f_d, f_g, w)\n"
PIECES = "LIB = 'freereg' + '_lib'\nROOT = {root!r}\n"
# Every way of importing the library (student_fuse); all but the first spell its name in pieces.
IMPORTS = {
    "direct": "from freereg_lib import features\n" + FUSE,
    "importlib": DISGUISED.format(package="", module="features") + FUSE,
    "by_path": PIECES + """
import importlib.util, sys
def load(name, path, package=False):
    spec = importlib.util.spec_from_file_location(name, path, submodule_search_locations=[path.rsplit("/", 1)[0]] if package else None)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
load(LIB, ROOT + "/" + LIB + "/__init__.py", package=True)
features = load(LIB + ".features", ROOT + "/" + LIB + "/features/__init__.py", package=True)
""" + FUSE,
    "sys_path": PIECES + "import sys, importlib\nsys.path.insert(0, ROOT)\nfeatures = importlib.import_module(LIB + '.features')\n" + FUSE,
    "meta_path": PIECES + """
import sys, importlib, importlib.abc, importlib.util
class Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == LIB:
            base = ROOT + "/" + name.replace(".", "/")
            return importlib.util.spec_from_file_location(name, base + "/__init__.py", submodule_search_locations=[base])
sys.meta_path.insert(0, Finder())
features = importlib.import_module(LIB + '.features')
""" + FUSE,
}

FORGES = """
import os, sys
from pathlib import Path
for d in [Path(a) for a in sys.argv[1:]] + [Path.cwd().parent / "answers"]:
    for name in ("student_fuse.npz", "result.json", "grades.csv"):
        try:
            (d / name).write_text('{"score": 20}')
        except OSError:
            pass
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
os._exit(0)
"""
ESCAPES = """
import os, subprocess, time
if os.fork() == 0:  # a child in a session of its own, keeping the marker
    os.setsid()
    time.sleep(300)
    os._exit(0)
subprocess.Popen(["sleep", "4242"], env={}, start_new_session=True)  # no marker, no session
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""
READS_KEY = PIECES.format(root=str(ROOT)) + """
def student_fuse(f_d, f_g, w):
    raise NotImplementedError("replaced by the key's, if it can be read")
import json
cells = json.loads(open(ROOT + "/notebooks/03_fusion.ipynb").read())["cells"]
for cell in cells:
    if "solution" in cell.get("metadata", {}).get("tags", []) and "def student_fuse" in "".join(cell["source"]):
        exec("".join(cell["source"]))
"""
KILLS_GRADER = """
import os, signal
try:
    os.kill(os.getppid(), signal.SIGKILL)  # the grading process (here: pytest itself)
except OSError:
    pass
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""


def _leftovers() -> list[int]:
    """Processes that carry a grading marker, or the escaping student's ``sleep 4242``."""
    found = []
    for pid in sandbox._user_pids():
        try:
            marked = sandbox.MARKER_ENV.encode() + b"=" in Path(f"/proc/{pid}/environ").read_bytes()
            sleeper = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[:2] == [b"sleep", b"4242"]
        except OSError:
            continue
        if marked or sleeper:
            found.append(pid)
    return found


@pytest.fixture(scope="module")
def graded(tmp_path_factory):
    """Every student of this file, graded in one run: {student: {exercise: result}}, the rows."""
    room = tmp_path_factory.mktemp("class")
    for name, (fn, stem, package, module, cell) in SIX.items():
        student_notebook(room / f"plain_{name}", stem, PLAIN.format(package=package, module=module) + cell)
        student_notebook(room / f"disguised_{name}", stem, DISGUISED.format(package=package, module=module) + cell)
    for name, cell in IMPORTS.items():
        student_notebook(room / f"import_{name}", "03_fusion", cell.replace("{root!r}", repr(str(ROOT))))
    for name, cell in [("forges", FORGES), ("escapes", ESCAPES), ("reads_key", READS_KEY)] + (
            [("kills_grader", KILLS_GRADER)] if sandbox.landlock_abi() >= 6 else []):
        student_notebook(room / name, "03_fusion", cell)
    shutil.copytree(ROOT / "notebooks", room / "honest", ignore=shutil.ignore_patterns(".*"))
    make(room / "stub")
    with pytest.MonkeyPatch.context() as mp:  # no cgroup, even where one could be made: the scan must find all
        mp.setattr(sandbox, "make_cgroup", lambda token: None)
        rows = gradebook.grade_all([room], out=room.parent / "grades", timeout=10, limit=120, echo=False)
    return {r["id"]: {e["exercise"]: e for e in r["exercises"]} for r in rows}, {r["id"]: r for r in rows}


@pytest.mark.parametrize("form", ["plain", "disguised"])
@pytest.mark.parametrize("cheat", list(SIX))
def test_each_cheat_that_beat_the_old_grader_scores_zero_on_its_exercise(graded, cheat, form):
    by, rows = graded
    e = by[f"{form}_{cheat}"][SIX[cheat][0]]
    assert e["score"] == 0 and rows[f"{form}_{cheat}"]["score"] == 0, e
    assert check.GRADED_WITH in e["message"], e["message"]
    if form == "plain":  # refused from its source: nothing of it ran
        assert e["status"] == "refused" and "imports freereg_lib" in e["message"], e
    else:  # it ran, and the library was not there
        assert e["status"] == "missing" and "No module named 'freereg_lib" in e["message"], e


@pytest.mark.parametrize("way", list(IMPORTS))
def test_a_solution_importing_the_library_scores_zero_and_is_told_why(graded, way):
    if way in ("by_path", "sys_path", "meta_path") and not LANDLOCK:
        pytest.skip("without Landlock the library's files can be read by path (the guide says so)")
    e = graded[0][f"import_{way}"]["student_fuse"]
    assert e["score"] == 0 and e["status"] in ("refused", "missing"), e
    assert check.GRADED_WITH in e["message"], e["message"]
    expected = {"direct": "imports freereg_lib", "importlib": "No module named 'freereg_lib",
                "by_path": "PermissionError", "sys_path": "No module named 'freereg_lib",
                "meta_path": "PermissionError"}[way]
    assert expected in e["message"], e["message"]


def test_the_honest_student_scores_full_marks_and_the_stub_zero_not_done(graded):
    by, rows = graded
    assert rows["honest"]["score"] == rows["honest"]["max"] == 60 and rows["honest"]["status"] == "graded"
    assert all(e["status"] == "ok" for e in by["honest"].values())
    assert rows["stub"]["score"] == 0 and rows["stub"]["max"] == 60
    for e in by["stub"].values():
        assert e["status"] == "not done" and e["message"].startswith("not done"), e


def test_forged_answers_escaping_children_and_the_answer_key_get_nothing(graded):
    by, rows = graded
    assert by["forges"]["student_fuse"]["score"] == 0 and rows["forges"]["status"] == "exited"
    assert by["escapes"]["student_fuse"]["score"] == 0
    assert rows["escapes"]["leftover_processes_killed"] >= 2
    assert not _leftovers(), "a student's process survived the grading"
    key = by["reads_key"]["student_fuse"]
    assert key["score"] == 0
    if LANDLOCK:
        assert rows["reads_key"]["confined"] is True and "PermissionError" in key["message"], key
    if "kills_grader" in rows:  # we are still here: Landlock scoped the signal
        assert by["kills_grader"]["student_fuse"]["score"] == 0


def test_without_landlock_the_import_path_still_holds_no_library(tmp_path):
    path = student_notebook(tmp_path / "eve", "03_fusion", IMPORTS["importlib"])
    result = grader.grade(path, grader.prepare(seed=1), timeout=10, limit=60, confine=False)
    e = next(e for e in result["exercises"] if e["exercise"] == "student_fuse")
    assert result["confined"] is False
    assert e["score"] == 0 and "No module named 'freereg_lib" in e["message"], e
    mnn = student_notebook(tmp_path / "ann", "03_fusion", key_source("student_mutual_nn"))
    assert grader.grade(mnn, grader.prepare(seed=1), limit=60, confine=False)["score"] == 10


def test_a_library_installed_where_the_student_may_read_is_reported_unconfined(monkeypatch):
    from freereg_lib.teaching import student

    assert not grader.library_readable()  # here: the project folder is none of the readable ones
    monkeypatch.setattr(student, "SYSTEM", (*student.SYSTEM, str(ROOT)))  # as if installed under /usr
    assert grader.library_readable()
