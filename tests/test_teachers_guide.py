"""The teacher's guide, run as written, end to end on a class of fake students.

The commands of "The term in five commands" in ``assignments/README.md`` run in a course folder
(the project's notebooks and environment linked in). Between them, the students work from
the handout zip: Alice fills every solution (from the key), Bob hands back the untouched
notebooks, Carol gets Kabsch's reflection wrong and calls the library in ``student_fuse``, Dave's
``student_fuse`` hangs (catching the time-out), Eve returns an unsolved ``03_fusion.ipynb``
beside her solved, newer ``03_fusion_final.ipynb`` under the id ``@eve``, and the returns
``frank lee`` and ``frank_lee`` would share a feedback file. Their returns come back as an LMS
would give them (zips and folders). Grading first stops on the colliding ids (the guide's roster
without its last two rows), then runs. The result: ``grades.csv`` opens as a spreadsheet with
one row per student, under the roster's ids, ``canvas.csv`` has its ``Points Possible`` row,
and each student has a feedback file that says what each check found.
"""
from __future__ import annotations

import csv
import os
import re
import shlex
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest
from conftest import HANGING_FUSE, fill, key_source, student_notebook

nbformat = pytest.importorskip("nbformat")

from freereg_lib.teaching import gradebook  # noqa: E402
from freereg_lib.teaching import notebooks as N  # noqa: E402
from freereg_lib.teaching.exercises import EXERCISES  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
GUIDE = ROOT / "assignments" / "README.md"
PROGRAM = ".venv/bin/python -m freereg_lib.teaching.assignments"


def guide_commands() -> list[str]:
    """The commands of the walkthrough, in order, from the guide's code blocks."""
    text = GUIDE.read_text().split("## The term in five commands", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"^```\w*\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip().startswith(PROGRAM)]


def guide_roster() -> str:
    return re.search(r"```csv\n(.*?)```", GUIDE.read_text(), flags=re.DOTALL).group(1)


# The commands run between two steps of the students share a process of their own: each runs as
# ``python -m`` runs it (runpy as __main__, the guide's argv, the course folder; the guide's
# commands hand each other only files). A fresh interpreter for each cost ~1.1 s of CPU in imports.
_COMMANDS = textwrap.dedent("""
    import runpy, shlex, sys
    for command in sys.argv[1:]:
        _, flag, module, *args = shlex.split(command)
        assert flag == "-m", command
        sys.argv = [module, *args]
        try:
            runpy.run_module(module, run_name="__main__", alter_sys=True)
        except SystemExit as end:
            if end.code not in (None, 0):
                raise
        print("\\0", flush=True)
""")


def _run(commands: list[str], cwd: Path) -> list[str]:
    """Each command's output."""
    proc = subprocess.run([sys.executable, "-c", _COMMANDS, *commands], cwd=cwd, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, (commands, proc.stdout[-2000:], proc.stderr[-2000:])
    printed = proc.stdout.split("\0\n")
    assert len(printed) == len(commands) + 1 and printed[-1] == "", printed
    return printed[:-1]


def _student_work(handout_zip: Path, desk: Path, name: str) -> Path:
    """A student unpacks the handout and works in its notebooks; their notebooks folder."""
    with zipfile.ZipFile(handout_zip) as z:
        z.extractall(desk / name)
    books = desk / name / "handout" / "notebooks"
    for path in books.glob("*.ipynb"):
        student, key = nbformat.read(path, as_version=4), nbformat.read(ROOT / "notebooks" / path.name, as_version=4)
        if name in ("bob", "frank"):
            continue
        filled = fill(student, key)
        if name == "dave":
            for cell in filled.cells:
                if N._is_solution(cell) and "def student_fuse" in cell.source:
                    cell.source = HANGING_FUSE
        if name == "carol":
            for cell in filled.cells:
                if N._is_solution(cell) and "def student_kabsch" in cell.source:
                    cell.source = cell.source.replace("np.sign(np.linalg.det(V @ U.T))", "1.0")
                if N._is_solution(cell) and "def student_fuse" in cell.source:
                    cell.source = ("from freereg_lib import features\n\n"
                                   "def student_fuse(f_d, f_g, w):\n    return features.fuse(f_d, f_g, w)\n")
        nbformat.write(filled, str(path))
    return books


def test_the_guide_walks_a_class_through_release_collection_grading_and_export(tmp_path):
    commands = guide_commands()
    assert [c.split()[3] for c in commands] == ["list", "make", "dist", "collect", "grade"], commands
    course = tmp_path / "course"
    course.mkdir()
    for name in ("notebooks", "environment", "pyproject.toml"):
        (course / name).symlink_to(ROOT / name)

    # 1. Release.
    printed = _run(commands[:3], course)[0]
    assert all(name in printed for name in EXERCISES)
    handout_zip = course / "assignments" / "handout.zip"
    assert handout_zip.is_file() and (course / "answer_key" / "03_fusion.ipynb").is_file()
    assert not any("answer_key" in n or "teaching/grader" in n for n in zipfile.ZipFile(handout_zip).namelist())

    # The students work, and hand back: two zips and a folder, as an LMS download gives them.
    desk, returned = tmp_path / "students", course / "returned"
    returned.mkdir()
    for name in ("alice", "carol", "dave"):
        books = _student_work(handout_zip, desk, name)
        with zipfile.ZipFile(returned / f"{name}.zip", "w") as z:
            for path in books.glob("*.ipynb"):
                z.write(path, f"{name}_work/notebooks/{path.stem}_{name}.ipynb")
    books = _student_work(handout_zip, desk, "bob")
    for folder in ("bob", "frank lee", "frank_lee"):
        (returned / folder).mkdir()
        for path in books.glob("*.ipynb") if folder == "bob" else [books / "03_fusion.ipynb"]:
            (returned / folder / path.name).write_bytes(path.read_bytes())
    solved = _student_work(handout_zip, desk, "eve") / "03_fusion.ipynb"
    (returned / "eve").mkdir()
    (returned / "eve" / "03_fusion.ipynb").write_bytes((books / "03_fusion.ipynb").read_bytes())  # unsolved, older
    os.utime(returned / "eve" / "03_fusion.ipynb", (1_764_000_000, 1_764_000_000))
    (returned / "eve" / "03_fusion_final.ipynb").write_bytes(solved.read_bytes())
    roster = guide_roster()
    assert roster.splitlines()[-2:] == ["s006,Frank Lee,frank lee", "s007,Frank Lee Jr,frank_lee"], roster
    (course / "roster.csv").write_text("\n".join(roster.splitlines()[:-2]) + "\n")

    # 2. Collect; 3. grade: first with a roster that leaves the two Franks to their folders' names.
    printed = _run(commands[3:4], course)[0]
    assert {"alice", "bob", "carol", "dave", "eve"} <= set(re.findall(r"^(\w+): \d+ notebook", printed, flags=re.M))
    assert "graded the newest, 03_fusion_final.ipynb" in printed
    stopped = subprocess.run([sys.executable, *shlex.split(commands[4])[1:]], cwd=course, capture_output=True,
                             text=True, timeout=600)
    assert stopped.returncode == 2 and stopped.stderr.count("\n") == 1, stopped.stderr
    assert "ids 'frank lee' (from " in stopped.stderr and "share the feedback file feedback/frank_lee.md" in stopped.stderr
    assert not (course / "grades" / "grades.csv").exists()  # stopped before anyone was graded
    (course / "roster.csv").write_text(roster)
    printed = _run(commands[4:], course)[0]
    assert "ATTEMPTS" not in printed and "s004: 50/60 stopped" in printed, printed

    # 4. Export: a spreadsheet with one row per student, and a feedback file each.
    pd = pytest.importorskip("pandas")
    table = pd.read_csv(course / "grades" / "grades.csv", dtype={"id": str}).set_index("id")
    ids = ["s001", "s002", "s003", "s004", "'@eve", "s006", "s007"]
    assert sorted(table.index) == sorted(ids)
    assert list(table.columns) == ["name", *EXERCISES, "total", "attempts"]
    assert table.loc["s001", "total"] == 60 and table.loc["s002", "total"] == 0
    assert table.loc["s003", "student_fuse"] == 0 and table.loc["s003", "student_kabsch"] == 7
    assert table.loc["s003", "total"] == 47
    assert table.loc["s004", "student_fuse"] == 0 and table.loc["s004", "total"] == 50  # the hang cost one exercise
    assert table.loc["'@eve", "total"] == 20 and table.loc["s006", "total"] == table.loc["s007", "total"] == 0
    with open(course / "grades" / "grades.csv", newline="") as f:
        assert len(list(csv.reader(f))) == 1 + len(ids)
    with open(course / "grades" / "canvas.csv", newline="") as f:
        canvas = list(csv.reader(f))
    assert canvas[1][0] == "Points Possible" and canvas[1][-1] == "60" and len(canvas) == 2 + len(ids)
    assert ["Eve Adams", "", "'@eve", "", "", "20"] in canvas
    assert (course / "grades" / ".gitignore").is_file() and (course / "submissions" / ".gitignore").is_file()
    assert (course / "answer_key" / ".gitignore").is_file()
    feedback = {sid: (course / "grades" / "feedback" / (sid.lstrip("'") + ".md")).read_text() for sid in table.index}
    assert "60 / 60 points" in feedback["s001"]
    assert feedback["s002"].count("not done") >= len(EXERCISES)
    carol = feedback["s003"]
    assert "refused" in carol and "imports freereg_lib" in carol and "FAILED (0 / 3) planar point sets" in carol
    assert "Its inputs" in carol and "arg0 = np.array(" in carol
    assert "hard limit of 10 s" in feedback["s004"] and "graded the newest" in feedback["'@eve"]
    assert not any(str(tmp_path) in text for text in feedback.values())


def test_collect_keeps_only_notebooks_inside_its_folder_and_the_roster_gets_a_row_each(tmp_path):
    returned = tmp_path / "returned"
    returned.mkdir()
    with zipfile.ZipFile(returned / "dan.zip", "w") as z:
        z.writestr("../../escaped.ipynb", "{}")
        z.writestr("deep/notebooks/03_fusion.ipynb", "{}")
        z.writestr("notes.txt", "not a notebook")
    (returned / "eve").mkdir()
    (returned / "eve" / "03_fusion.ipynb").symlink_to(ROOT / "notebooks" / "03_fusion.ipynb")  # the key, by a link
    found = gradebook.collect(returned, tmp_path / "submissions")
    assert found == {"dan": ["03_fusion.ipynb", "escaped.ipynb"], "eve": []}
    assert not (tmp_path / "escaped.ipynb").exists() and not list(tmp_path.glob("*/escaped.ipynb"))

    folder = tmp_path / "class"
    student_notebook(folder / "fay", "03_fusion", key_source("student_mutual_nn"))
    (tmp_path / "roster.csv").write_text("id,folder\nS-1,fay\nS-2,gus\n")
    rows = gradebook.grade_all([folder], out=tmp_path / "grades", roster=tmp_path / "roster.csv", limit=60, echo=False)
    assert [(r["id"], r["score"]) for r in rows] == [("S-1", 10.0), ("S-2", 0.0)]
    table = list(csv.DictReader(open(tmp_path / "grades" / "grades.csv")))
    assert [(r["id"], r["student_mutual_nn"], r["total"]) for r in table] == [("S-1", "10", "10"), ("S-2", "0", "0")]
    assert "no submission" in (tmp_path / "grades" / "feedback" / "S-2.md").read_text()
    with pytest.raises(ValueError, match="column 'id'"):
        (tmp_path / "bad.csv").write_text("name\nAnn\n")
        gradebook.read_roster(tmp_path / "bad.csv")
