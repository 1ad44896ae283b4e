"""Issue 41: a grade a teacher can trust. Six students try to cheat on ``student_fuse``, one is
honest; one command grades them all.

The students' solution cells run in a process of their own that only writes answers as data;
the score is computed in the grading process, which runs no student code. Each cheat:
(1) forges the grader's records from ``sys.argv`` and calls ``os._exit(0)``; (2) replaces the
grading module's ``_assert_close`` with a no-op; (3) calls the library's reference after
``sys.setprofile(None)``; (4) calls it from a thread; (5) executes the answer key's cell, read
from the project's ``notebooks/``; (6) leaves children behind that called ``setsid()`` (one
with a clean environment). None scores above 0 on ``student_fuse``, the honest student gets
20/20, and no process of theirs survives the grading. Where Landlock scopes signals (Linux
6.12+) a seventh tries to SIGKILL the grading process, which here is pytest itself.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
from conftest import fusion_key_source, fusion_student

from freereg_lib.teaching import assignments as A
from freereg_lib.teaching import sandbox

WRONG = """
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
"""
FORGES = """
import json, os, sys
from pathlib import Path
line = json.dumps({"result": {"score": 20.0, "max": 20.0, "percent": 100.0, "exercises": []}})
for arg in sys.argv[1:]:
    for p in [Path(arg), *Path(arg).rglob("*")] if Path(arg).is_dir() else [Path(arg)]:
        try:
            if p.is_file():
                with open(p, "a") as f:
                    f.write(line + "\\n")
        except OSError:
            pass
    try:  # and an answers file of its own making, in every place it might be read from
        for name in ("student_fuse.npz", "student_fuse.json", "progress.jsonl", "result.json"):
            for d in (Path(arg), Path(arg) / "answers"):
                (d / name).write_text(line)
    except OSError:
        pass
def student_fuse(f_d, f_g, w):
    return np.zeros((len(f_d), f_d.shape[1] + f_g.shape[1]))
os._exit(0)
"""
PATCHES_CHECKER = """
import freereg_lib.teaching.assignments as A
from freereg_lib.teaching import exercises, grader
exercises._assert_close = lambda *a, **k: None
for e in exercises.EXERCISES.values():
    e.check = lambda got, want: None
A.grade = grader.grade = lambda *a, **k: {"score": 20.0}
""" + WRONG
NO_PROFILE = """
import sys
from freereg_lib import features
def student_fuse(f_d, f_g, w):
    sys.setprofile(None)
    return features.fuse(f_d, f_g, w)
"""
THREAD = """
import threading
from freereg_lib.features import fuse as combine
def student_fuse(f_d, f_g, w):
    out = []
    t = threading.Thread(target=lambda: out.append(combine(f_d, f_g, w)))
    t.start()
    t.join()
    return out[0]
"""
RUNS_KEY = """
import json
from pathlib import Path
import freereg_lib
key = Path(freereg_lib.__file__).resolve().parents[1] / "notebooks" / "03_fusion.ipynb"
cells = json.loads(key.read_text())["cells"]
for cell in cells:
    source = "".join(cell["source"])
    if "solution" in cell.get("metadata", {}).get("tags", []) and "def student_fuse" in source:
        exec(source)
"""
ESCAPES = """
import os, subprocess, time
if os.fork() == 0:  # a child in a session of its own, keeping the marker
    os.setsid()
    time.sleep(300)
    os._exit(0)
subprocess.Popen(["sleep", "4242"], env={}, start_new_session=True)  # no marker, no session
""" + WRONG


KILLS_GRADER = """
import os, signal
try:
    os.kill(os.getppid(), signal.SIGKILL)  # the grading process (here: pytest itself)
except OSError:
    pass
""" + WRONG


def _marked() -> list[int]:
    """Processes that carry a grading marker."""
    found = []
    for pid in sandbox._user_pids():
        try:
            if sandbox.MARKER_ENV.encode() + b"=" in Path(f"/proc/{pid}/environ").read_bytes():
                found.append(pid)
        except OSError:
            pass
    return found


def _sleepers() -> list[int]:
    """The escaping student's ``sleep 4242``, wherever it is."""
    found = []
    for pid in sandbox._user_pids():
        try:
            if Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[:2] == [b"sleep", b"4242"]:
                found.append(pid)
        except OSError:
            pass
    return found


def test_six_cheats_score_zero_the_honest_student_full_marks_and_nothing_survives(tmp_path, capsys, monkeypatch):
    # No cgroup, even where the grader could make one: the scan alone must find every leftover.
    monkeypatch.setattr(sandbox, "make_cgroup", lambda token: None)
    mnn = fusion_key_source("student_mutual_nn")
    students = {
        "forges": fusion_student(tmp_path / "forges", FORGES),
        "patches_checker": fusion_student(tmp_path / "patches_checker", PATCHES_CHECKER),
        "no_profile": fusion_student(tmp_path / "no_profile", NO_PROFILE),
        "thread": fusion_student(tmp_path / "thread", THREAD),
        "runs_key": fusion_student(tmp_path / "runs_key", RUNS_KEY),
        "escapes": fusion_student(tmp_path / "escapes", ESCAPES),
        "honest": fusion_student(tmp_path / "honest", mnn, fusion_key_source("student_fuse")),
    }
    if sandbox.landlock_abi() >= 6:  # Landlock's signal scope (Linux 6.12+): a seventh, who tries to kill the grader
        students["kills_grader"] = fusion_student(tmp_path / "kills_grader", KILLS_GRADER)
    report = tmp_path / "scores.json"
    start = time.time()
    assert A.main(["grade", *map(str, students.values()), "--json", str(report), "--timeout", "10",
                   "--limit", "120"]) == 0
    seconds = time.time() - start
    out = capsys.readouterr().out
    results = {Path(r["path"]).parent.name: r for r in json.loads(report.read_text())}
    assert list(results) == list(students)
    fuse = {s: next(e for e in r["exercises"] if e["exercise"] == "student_fuse") for s, r in results.items()}
    print({s: (f["score"], f["status"]) for s, f in fuse.items()}, f"{seconds:.0f} s")

    assert results["honest"]["score"] == results["honest"]["max"] == 20
    assert fuse["honest"]["status"] == "ok" and results["honest"]["status"] == "graded"
    for s in students:
        if s != "honest":
            assert fuse[s]["score"] == 0, (s, fuse[s])
            assert results[s]["score"] == 0, (s, results[s]["score"])
    assert results["forges"]["status"] == "exited" and fuse["forges"]["status"] == "stopped"
    assert fuse["patches_checker"]["status"] == "failed"
    for s in ("no_profile", "thread"):
        assert fuse[s]["status"] == "refused" and "freereg_lib.features.descriptors.fuse" in fuse[s]["message"], fuse[s]
    if sandbox.landlock_abi():
        assert results["runs_key"]["confined"] is True
        assert fuse["runs_key"]["status"] == "missing" and "PermissionError" in fuse["runs_key"]["message"]
    assert results["escapes"]["leftover_processes_killed"] >= 2
    assert not _marked() and not _sleepers(), "a student's process survived the grading"
    assert "Summary" in out and "refused" in out
