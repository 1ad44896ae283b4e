"""The grader, round 5: grades a teacher can sign, and feedback a student can read safely.

One small class (notebook 03_fusion only: two exercises each) is graded once, in one run:
a student whose first exercise hangs (catching the time-out), one who probes the teacher's
files and root's, one who hands in an unsolved copy beside the solved notebook, and one whose
roster id is a spreadsheet formula and whose messages carry HTML. The rest are unit checks
that spawn nothing: ``collect``'s names, ids that share a file, a roster id given twice, the
gradebook's cells, the Markdown of the feedback.
"""
from __future__ import annotations

import csv
import os
import re
import zipfile
from pathlib import Path

import pytest
from conftest import fusion_key_source, fusion_student

from freereg_lib.teaching import assignments, export, gradebook, grader

MUTUAL_NN, FUSE = fusion_key_source("student_mutual_nn"), fusion_key_source("student_fuse")
HANGS = """
import time
def student_mutual_nn(fa, fb):
    while True:  # swallows the grader's time-out too
        try:
            time.sleep(0.1)
        except BaseException:
            pass
"""
PROBES = FUSE + """
import os
def _probe(path, mode="r"):
    try:
        with open(path, mode) as f:
            return f.write("x") if "w" in mode else f.read()[:40]
    except OSError as e:
        return type(e).__name__
_found = [_probe(p) for p in ({classmate!r}, "/etc/shadow", f"/proc/{{os.getppid()}}/environ")]
_found.append(_probe({gradebook!r}, "w"))
_found.append(next(line for line in open("/proc/self/status") if line.startswith("CapEff")))
def student_mutual_nn(fa, fb):
    raise ValueError(" | ".join(str(x) for x in _found))
"""
HTML = """
def student_mutual_nn(fa, fb):
    raise ValueError("<script>alert(1)</script> in /home/teacher/course/submissions/bob/03_fusion.ipynb")
"""
STUB = "def student_mutual_nn(fa, fb):\n    raise NotImplementedError('student_mutual_nn')\n" \
       "def student_fuse(f_d, f_g, w):\n    raise NotImplementedError('student_fuse')\n"
FORMULA, SCRIPT = "=cmd|' /C calc'!A0", "<img src=x onerror=alert(1)>"
LIMIT_S = 5


@pytest.fixture(scope="module")
def graded(tmp_path_factory, capsys_module=None):
    room = tmp_path_factory.mktemp("class")
    out = room.parent / f"{room.name}_grades"
    fusion_student(room / "hangs", HANGS, FUSE)
    classmate = fusion_student(room / "ann", MUTUAL_NN, FUSE)
    fusion_student(room / "probes", PROBES.format(classmate=str(classmate), gradebook=str(out / "grades.csv")))
    fusion_student(room / "html", HTML, FUSE)
    old = fusion_student(room / "dup", STUB)  # the unsolved copy, older...
    old.rename(room / "dup" / "03_fusion-Copy1.ipynb")  # ...sorts first
    os.utime(room / "dup" / "03_fusion-Copy1.ipynb", (1_700_000_000, 1_700_000_000))
    fusion_student(room / "dup", MUTUAL_NN, FUSE)
    roster = room.parent / f"{room.name}_roster.csv"
    with open(roster, "w", newline="") as f:
        csv.writer(f).writerows([["id", "name", "folder"], [FORMULA, "Formula Fan", "ann"],
                                 [SCRIPT, "Html Hal", "html"], ["s-absent", "Nobody Here", ""]])
    rows = gradebook.grade_all([room], out=out, roster=roster, timeout=1, limit=LIMIT_S, echo=True)
    return {r["id"]: r for r in rows}, out


def _by(result) -> dict:
    return {e["exercise"]: e for e in result["exercises"]}


def test_a_hang_costs_only_its_own_exercise(graded):
    by = _by(graded[0]["hangs"])
    assert by["student_mutual_nn"]["status"] == "stopped" and f"hard limit of {LIMIT_S} s" in by["student_mutual_nn"]["message"]
    assert by["student_fuse"]["score"] == 10 and graded[0]["hangs"]["score"] == 10


def test_probes_are_refused_and_listed_for_the_teacher(graded):
    rows, out = graded
    probe = rows["probes"]
    message = _by(probe)["student_mutual_nn"]["cases"][0]["message"]
    found = message.removeprefix("ValueError: ").split(" | ")
    assert found[:4] == ["PermissionError"] * 4, message  # classmate, /etc/shadow, the grader's environ, the gradebook
    if os.geteuid() == 0:  # as root: run as another user, or as uid 0 without a capability
        status = found[4]
        assert status.startswith("CapEff: 0000000000000000"), status
    assert any("read" in a and "ann/03_fusion.ipynb" in a for a in probe["attempts"]), probe["attempts"]
    assert any("write" in a and "grades.csv" in a for a in probe["attempts"]), probe["attempts"]
    table = {r["id"]: r for r in csv.DictReader(open(out / "grades.csv", newline=""))}
    assert "ann/03_fusion.ipynb" in table["probes"]["attempts"] and table["hangs"]["attempts"] == ""
    text = (out / "feedback" / "probes.md").read_text()
    assert str(out) not in text and str(Path(str(out)).parent) not in text and "tried to read or write" in text


def test_the_newest_of_two_copies_is_graded_and_said(graded):
    dup = graded[0]["dup"]
    assert dup["score"] == 20, dup
    assert any("graded the newest, 03_fusion.ipynb" in n for n in dup["chosen"]), dup["chosen"]
    assert "03_fusion-Copy1.ipynb" in (graded[1] / "feedback" / "dup.md").read_text()


def test_formula_ids_and_html_are_inert_in_every_file(graded):
    rows, out = graded
    raw = list(csv.reader(open(out / "grades.csv", newline="")))
    ids = [r[0] for r in raw[1:]]
    assert "'" + FORMULA in ids and not any(c and c[0] in "=+-@" for r in raw for c in r), raw
    canvas = list(csv.reader(open(out / "canvas.csv", newline="")))
    assert canvas[0] == [*export.CANVAS_COLUMNS, export.CANVAS_ASSIGNMENT]
    assert canvas[1][0] == "Points Possible" and canvas[1][-1] == "60"
    assert len(canvas) == 2 + len(rows) and ["Formula Fan", "", "'" + FORMULA, "", "", "20"] in canvas
    html = export.feedback_file(out, SCRIPT).read_text()
    assert "<script" not in html and "<img" not in html and "&lt;script&gt;" in html
    assert "/home/teacher" not in html and ".../03_fusion.ipynb" in html


def test_a_failed_case_shows_its_inputs(graded):
    text = export.feedback_file(graded[1], SCRIPT).read_text()
    assert "Its inputs" in text and re.search(r"arg0 = np\.array\(\[\[", text), text


def test_the_teachers_folders_are_kept_out_of_git(graded, tmp_path):
    assert (graded[1] / ".gitignore").read_text().splitlines()[-1] == "*"
    returned = tmp_path / "returned"
    (returned / "ann").mkdir(parents=True)
    gradebook.collect(returned, tmp_path / "submissions")
    assert (tmp_path / "submissions" / ".gitignore").is_file()


def test_collect_refuses_a_name_that_leaves_its_folder_before_writing(tmp_path, capsys):
    returned = tmp_path / "returned"
    returned.mkdir()
    for name in ("..zip", "ann.zip"):
        with zipfile.ZipFile(returned / name, "w") as z:
            z.writestr("03_fusion.ipynb", "{}")
    assert assignments.main(["collect", str(returned), "--out", str(tmp_path / "submissions")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{returned / '..zip'}: the id its name gives, '.'," in err, err
    assert not (tmp_path / "submissions").exists()


def test_collect_refuses_two_returns_of_one_student(tmp_path):
    returned = tmp_path / "returned"
    (returned / "ann").mkdir(parents=True)
    with zipfile.ZipFile(returned / "ann.zip", "w") as z:
        z.writestr("03_fusion.ipynb", "{}")
    with pytest.raises(export.IdError, match="both returns of student 'ann'"):
        gradebook.collect(returned, tmp_path / "submissions")


@pytest.mark.parametrize("folders, roster, says", [
    (["a b", "a\nb", "a_b"], None, r"ids 'a\\nb' \(from .*\) and 'a b' \(from .*\) share the feedback file feedback/a_b\.md"),
    (["Ann", "ann"], None, "share the feedback file"),
    (["x", "y"], "id,folder\ns1,x\ns1,y\n", "id 's1' is given to two folders, 'x' and 'y'"),
    (["x", "s1"], "id,folder\ns1,x\n", "both get the id 's1'"),
])
def test_ids_that_collide_stop_grading_before_it_starts(tmp_path, capsys, monkeypatch, folders, roster, says):
    for name in folders:
        (tmp_path / "class" / name).mkdir(parents=True)
        (tmp_path / "class" / name / "03_fusion.ipynb").write_text("{}")
    argv = ["grade", str(tmp_path / "class"), "--out", str(tmp_path / "grades")]
    if roster:
        (tmp_path / "roster.csv").write_text(roster)
        argv += ["--roster", str(tmp_path / "roster.csv")]
    monkeypatch.setattr(grader, "grade", lambda *a, **k: pytest.fail("grading started"))
    assert assignments.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("grade: ") and err.count("\n") == 1 and re.search(says, err), err


def test_two_copies_saved_at_the_same_time_are_named_not_guessed(tmp_path):
    for name in ("03_fusion.ipynb", "03_fusion_final.ipynb"):
        fusion_student(tmp_path / "s", STUB).rename(tmp_path / "s" / f"tmp_{name}")
    for name in ("03_fusion.ipynb", "03_fusion_final.ipynb"):
        (tmp_path / "s" / f"tmp_{name}").rename(tmp_path / "s" / name)
        os.utime(tmp_path / "s" / name, (1_700_000_000, 1_700_000_000))
    sources, wanted, missing, notes = grader.submission(tmp_path / "s")
    assert not sources and "03_fusion.ipynb, 03_fusion_final.ipynb are all notebook 03_fusion" in missing["student_fuse"]
    assert "saved at the same time" in missing["student_fuse"]


def test_cells_and_markdown_of_hostile_text():
    assert [export.cell(v) for v in ("=1+1", "+SUM(1+1)", "-2+3", "@x", "\tx", "10", "ann")] == [
        "'=1+1", "'+SUM(1+1)", "'-2+3", "'@x", "'\tx", "10", "ann"]
    assert export.md("a | b *c* [d](e) `f` <b>") == "a \\| b \\*c\\* \\[d\\](e) \\`f\\` &lt;b&gt;"
    assert export.md("student_fuse in /home/t/x/03_fusion.ipynb") == "student_fuse in .../03_fusion.ipynb"


def test_outputs_inside_what_is_read_are_refused(tmp_path, capsys, monkeypatch):
    (tmp_path / "returned" / "ann").mkdir(parents=True)
    assert assignments.main(["collect", str(tmp_path / "returned"), "--out", str(tmp_path / "returned" / "s")]) == 2
    assert "inside the returns' folder" in capsys.readouterr().err and not (tmp_path / "returned" / "s").exists()
    fusion_student(tmp_path / "class" / "ann", STUB)
    monkeypatch.setattr(grader, "grade", lambda *a, **k: pytest.fail("grading started"))
    out = tmp_path / "class" / "ann" / "grades"
    assert assignments.main(["grade", str(tmp_path / "class" / "ann"), "--out", str(out)]) == 2
    assert "inside the submission" in capsys.readouterr().err and not out.exists()
