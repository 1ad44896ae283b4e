"""Course assignments: student versions of the notebooks, the handout and the grader.

* ``make`` writes student notebooks that hold no solution code: every ``solution`` cell keeps
  its functions' signatures and docstrings and raises ``NotImplementedError`` with a hint; the
  ``check`` cells and everything else stay; outputs are stripped.
* The autograder (the solution cells run in a student process of their own, the
  score is computed in the grading process) gives the answer key (the notebooks themselves)
  full marks, the untouched student version zero, and partial, broken, looping or exiting work
  its due without crashing.
* ``dist`` hands out the student notebooks and the part of the library they import, never the
  answer key or the grader; an unfilled notebook runs from the handout alone.
* A student notebook filled from the key is the key's code (which the notebook tests run); left
  unfilled it runs with papermill to its last cell, each unsolved exercise's check saying so.
"""
from __future__ import annotations

import ast
import copy
import csv
import inspect
import json
import linecache
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import check_cells, fill

nbformat = pytest.importorskip("nbformat")
papermill = pytest.importorskip("papermill")

from freereg_lib.teaching import assignments, check, gradebook, grader, handout  # noqa: E402
from freereg_lib.teaching import notebooks as N  # noqa: E402
from freereg_lib.teaching.exercises import EXERCISES  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
WITH_EXERCISES = sorted({e.notebook for e in EXERCISES.values()})


def _solution_cells(nb):
    return [c for c in nb.cells if N._is_solution(c)]


def _body_lines(source: str) -> set[str]:
    """The solution's own lines: function bodies after the docstring, and other top-level code."""
    tree = ast.parse(source)
    lines = source.splitlines()
    body = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            stmts = node.body
            if ast.get_docstring(node) is not None:
                stmts = stmts[1:]
            if stmts:
                body |= {ln.strip() for ln in lines[stmts[0].lineno - 1 : node.end_lineno]}
        elif not isinstance(node, (ast.Import, ast.ImportFrom)):
            body |= {ln.strip() for ln in lines[node.lineno - 1 : node.end_lineno]}
    return {ln for ln in body if ln and not ln.startswith("# HINT")}


def _code_lines(cells) -> set[str]:
    return {ln.strip() for c in cells if c.cell_type == "code" for ln in c.source.splitlines() if ln.strip()}


@pytest.fixture(scope="module")
def student_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("student")
    N.make(out)
    return out


def _student(student_dir, stem):
    return nbformat.read(student_dir / f"{stem}.ipynb", as_version=4)


def _key(stem):
    return nbformat.read(NOTEBOOKS / f"{stem}.ipynb", as_version=4)


# --------------------------------------------------------------------------------------
# The registry and the notebooks agree.

def test_every_exercise_has_its_tagged_solution_andcheck_cells():
    for stem in WITH_EXERCISES:
        nb = _key(stem)
        defined = [n for c in _solution_cells(nb) for n in N._defined_functions(c.source)]
        registered = [n for n, e in EXERCISES.items() if e.notebook == stem]
        assert sorted(defined) == sorted(registered), f"{stem}: solution cells define {defined}, registry {registered}"
        checks = "\n".join(c.source for c in check_cells(nb))
        for name in defined:
            assert name in checks, f"{stem}: no check cell calls {name}"
    for e in EXERCISES.values():
        assert e.cases and e.max_points > 0 and e.teaches, e.function


# --------------------------------------------------------------------------------------
# Student versions.

def test_make_writes_every_notebook_and_they_validate(student_dir, unfilled_run):
    # (unfilled_run only starts the slow background papermill run early; see the end of the file.)
    assert sorted(p.name for p in student_dir.glob("*.ipynb")) == sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))
    for path in student_dir.glob("*.ipynb"):
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert "parameters" in code[0].metadata.get("tags", []), f"{path.name}: parameters cell no longer first"
        assert not any(c.outputs or c.execution_count is not None for c in code), f"{path.name} carries outputs"
        assert nb.metadata[N.METADATA_KEY]["notebook"] == path.stem
        # Outputs go into the student's own folder, and papermill still reads every parameter.
        assert f'out_dir: str = "runs/{path.stem}"' in code[0].source, code[0].source
        assert 'figures_dir: str = "figures"' in code[0].source
        key_params = papermill.inspect_notebook(str(NOTEBOOKS / path.name))
        assert papermill.inspect_notebook(str(path)).keys() == key_params.keys()


def test_student_notebooks_hold_no_solution_code(student_dir):
    for stem in WITH_EXERCISES:
        key, student = _key(stem), _student(student_dir, stem)
        elsewhere = _code_lines(c for c in key.cells if c not in _solution_cells(key))
        solution = set().union(*(_body_lines(c.source) for c in _solution_cells(key)))
        assert solution, f"{stem}: the key's solution cells have no body?"
        leaked = (solution - elsewhere) & _code_lines(student.cells)
        assert not leaked, f"{stem}: solution lines in the student version: {sorted(leaked)}"
        text = json.dumps(student)
        for line in solution - elsewhere:
            if len(line) > 12:
                assert json.dumps(line)[1:-1] not in text, f"{stem}: {line!r} is in the student notebook"


def test_stubs_keep_signatures_docstrings_and_checks_and_raise_a_hint(student_dir):
    for stem in WITH_EXERCISES:
        key, student = _key(stem), _student(student_dir, stem)
        assert [c.source for c in check_cells(student)] == [c.source for c in check_cells(key)]
        assert len(_solution_cells(student)) == len(_solution_cells(key))
        for mine, theirs in zip(_solution_cells(student), _solution_cells(key)):
            ns_s, ns_k = {"np": np}, {"np": np}
            exec(mine.source, ns_s)
            exec(theirs.source, ns_k)
            for name in N._defined_functions(theirs.source):
                assert inspect.signature(ns_s[name]) == inspect.signature(ns_k[name]), name
                assert inspect.getdoc(ns_s[name]) == inspect.getdoc(ns_k[name]), name
                n_args = len([p for p in inspect.signature(ns_s[name]).parameters.values()
                              if p.default is inspect.Parameter.empty])
                with pytest.raises(NotImplementedError, match=name):
                    ns_s[name](*([None] * n_args))
    # Hints: the exercise text's "Hint:" sentence, else the docstring's first line.
    src = _solution_cells(_student(student_dir, "00_preliminaries"))[0].source
    assert "np.minimum.at" in src
    src = _solution_cells(_student(student_dir, "03_fusion"))[1].source
    assert "Hint: [w * f_d / |f_d|" in src


def test_dist_hands_out_what_the_notebooks_import_and_no_answer_key_or_grader(handout_dir):
    out, archive = handout_dir
    assert archive == out.with_suffix(".zip") and archive.is_file()
    assert sorted(p.name for p in (out / "notebooks").glob("*.ipynb")) == sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))
    lib = out / "freereg_lib"
    assert (lib / "features" / "descriptors.py").is_file() and (out / "environment").is_dir()
    assert (lib / "models" / "micro" / "weights" / "unet").is_dir()  # notebooks 01-04 run the micro models
    assert (lib / "training" / "verdicts.py").is_file()  # notebooks 01, 03 and 04 import it
    assert not (lib / "training" / "train_diffusion.py").exists() and not (lib / "commands" / "site.py").exists()
    assert sorted(p.name for p in (lib / "teaching").iterdir()) == ["__init__.py", "assignments.py", "check.py"]
    assert not (out / "tests").exists() and not (out / "assignments").exists()
    assert not list(out.rglob("__pycache__"))
    for stem in WITH_EXERCISES:  # the notebooks are the student versions: stubs, not solutions
        student = nbformat.read(out / "notebooks" / f"{stem}.ipynb", as_version=4)
        assert student.metadata[N.METADATA_KEY]["notebook"] == stem
        for cell in _solution_cells(student):
            assert "raise NotImplementedError" in cell.source
        solution = set().union(*(_body_lines(c.source) for c in _solution_cells(_key(stem))))
        elsewhere = _code_lines(c for c in _key(stem).cells if c not in _solution_cells(_key(stem)))
        assert not (solution - elsewhere) & _code_lines(student.cells), stem
    import zipfile

    names = zipfile.ZipFile(archive).namelist()
    assert "handout/notebooks/03_fusion.ipynb" in names and not any("/tests/" in n for n in names)
    # Every import of every notebook resolves inside the handout, without the project.
    imports = sorted({i for p in (out / "notebooks").glob("*.ipynb") for c in _read_cells(p) for i in _imports(c.source)})
    code = "import freereg_lib, sys\n" + "\n".join(imports) + "\nprint(freereg_lib.__file__)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=out / "notebooks",
                          env={**os.environ, "PYTHONPATH": str(out)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().startswith(str(out)), proc.stdout
    # The last check of dist refuses a student version that still holds a solution line.
    key = _key("03_fusion")
    with pytest.raises(AssertionError, match="solution line"):
        handout.assert_no_solution(key, key, "03_fusion.ipynb")


def _read_cells(path):
    return [c for c in nbformat.read(path, as_version=4).cells if c.cell_type == "code"]


def _imports(source: str) -> set[str]:
    """The imports of freereg_lib in a cell, one statement each (a parenthesised one spans lines)."""
    try:
        tree = ast.parse(N._python(source))
    except SyntaxError:
        return set()
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "freereg_lib":
            found.add(f"from {node.module} import {', '.join(a.name for a in node.names)}")
        elif isinstance(node, ast.Import):
            found |= {f"import {a.name}" for a in node.names if a.name.split(".")[0] == "freereg_lib"}
    return found


def test_stub_source_handles_hint_comments_decorators_and_one_liners():
    source = (
        "import math\n"
        "CONST = 3\n\n"
        "# HINT: start from the mean\n"
        "@staticmethod\n"
        "def student_a(x: 'list[int]',\n"
        "              y=(1, 2)) -> float:\n"
        "    '''Multi-line\n    docstring.'''\n"
        "    def helper(z):\n"
        "        return z * 2\n"
        "    return helper(x) + CONST\n\n"
        "def student_b(x): return x + 41\n"
    )
    stub = N.stub_source(source, md_hint="from the text")
    assert "import math" in stub and "CONST" not in stub and "helper" not in stub and "41" not in stub
    assert "@staticmethod" in stub and "y=(1, 2)) -> float:" in stub and "docstring.'''" in stub
    ns: dict = {}
    exec(stub, ns)
    with pytest.raises(NotImplementedError, match="start from the mean"):
        ns["student_a"].__func__([1], 2)
    with pytest.raises(NotImplementedError, match="from the text"):
        ns["student_b"](1)


# --------------------------------------------------------------------------------------
# The autograder.

def test_grading_the_answer_key_gives_full_marks():
    result = grader.grade(NOTEBOOKS)
    assert [e["exercise"] for e in result["exercises"]] == list(EXERCISES)
    bad = {e["exercise"]: e.get("message") for e in result["exercises"] if e["status"] != "ok"}
    assert not bad, bad
    assert result["score"] == result["max"] == sum(e.max_points for e in EXERCISES.values())
    one = grader.grade(NOTEBOOKS / "03_fusion.ipynb")
    assert [e["exercise"] for e in one["exercises"]] == ["student_mutual_nn", "student_fuse"]
    assert one["score"] == one["max"] == 20


def test_grading_the_untouched_student_version_gives_zero_not_done(student_dir, tmp_path, capsys):
    assert assignments.main(["grade", str(student_dir), "--out", str(tmp_path / "grades")]) == 0
    out = capsys.readouterr().out
    rows = list(csv.DictReader(open(tmp_path / "grades" / "grades.csv")))
    assert [r["id"] for r in rows] == [student_dir.name] and rows[0]["total"] == "0"
    assert [k for k in rows[0] if k.startswith("student_")] == list(EXERCISES)
    text = (tmp_path / "grades" / "feedback" / f"{student_dir.name}.md").read_text()
    assert text.count("not done: student_") == len(EXERCISES) and "0 / 60" in text
    assert "0/60" in out


def _variant(student_dir, tmp_path, stem, sources: dict[str, str], extra_cell: str | None = None) -> Path:
    nb = copy.deepcopy(_student(student_dir, stem))
    for cell in _solution_cells(nb):
        names = N._defined_functions(cell.source)
        cell.source = "\n\n".join(sources.get(n, cell.source) for n in names) if names else cell.source
    if extra_cell is not None:
        nb.cells.append(nbformat.v4.new_code_cell(extra_cell))
    path = tmp_path / "alice" / f"{stem}.ipynb"
    path.parent.mkdir(exist_ok=True)
    nbformat.write(nb, str(path))
    return path


def _key_function(stem, name):
    for cell in _solution_cells(_key(stem)):
        if name in N._defined_functions(cell.source):
            return cell.source
    raise KeyError(name)


def test_grader_scores_partial_and_broken_work_without_crashing(student_dir, tmp_path, capsys):
    no_reflection_fix = _key_function("02_geometric_features", "student_kabsch").replace(
        "np.sign(np.linalg.det(V @ U.T))", "1.0")
    assert no_reflection_fix != _key_function("02_geometric_features", "student_kabsch")
    # 00: project_to_depth written in an untagged cell (its tagged cell emptied), inlier ratio
    # with the pose used the wrong way round, and a print at top level.
    _variant(student_dir, tmp_path, "00_preliminaries", {
        "student_project_to_depth": "print('working on it')",
        "student_inlier_ratio": _key_function("00_preliminaries", "student_inlier_ratio").replace(
            "p_pc = (p_cam - t) @ R", "p_pc = p_cam @ R.T + t"),
    }, extra_cell=_key_function("00_preliminaries", "student_project_to_depth"))
    _variant(student_dir, tmp_path, "02_geometric_features", {"student_kabsch": no_reflection_fix})
    _variant(student_dir, tmp_path, "03_fusion", {
        "student_mutual_nn": "def student_mutual_nn(fa, fb)\n    return fa",  # a syntax error
        "student_fuse": _key_function("03_fusion", "student_fuse").replace(  # loops forever at w = 0
            "    def unit_rows(x):", "    while w == 0:\n        pass\n\n    def unit_rows(x):"),
    })
    _variant(student_dir, tmp_path, "04_benchmark", {
        "student_registration_recall": "import sys\ndef student_registration_recall(re, te, ladder):\n    sys.exit(3)",
    })
    result = grader.grade(tmp_path / "alice", grader.prepare(seed=7), timeout=1.0)  # a fixed draw: the same every run
    by = {e["exercise"]: e for e in result["exercises"]}
    assert by["student_project_to_depth"]["score"] == 10, by["student_project_to_depth"]
    assert by["student_inlier_ratio"]["status"] in ("failed", "partial")
    assert by["student_inlier_ratio"]["score"] < 10
    assert by["student_kabsch"]["status"] == "partial" and by["student_kabsch"]["score"] == 7
    assert [c["ok"] for c in by["student_kabsch"]["cases"]] == [True, False, True, True]
    assert by["student_mutual_nn"]["status"] == "missing" and "SyntaxError" in by["student_mutual_nn"]["message"]
    fuse = by["student_fuse"]
    assert fuse["score"] == 8 and "TimeoutError" in " ".join(c["message"] for c in fuse["cases"])
    assert by["student_registration_recall"]["score"] == 0
    assert "SystemExit" in by["student_registration_recall"]["message"]
    assert "working on it" not in capsys.readouterr().out
    text = gradebook.feedback({**result, "id": "alice"})
    assert "FAILED (0 / 3) planar point sets" in text and "SyntaxError" in text


def test_grader_reports_a_missing_notebook_and_a_missing_path(student_dir, tmp_path, capsys):
    folder = tmp_path / "bob"
    folder.mkdir()
    (folder / "04_benchmark.ipynb").write_bytes((student_dir / "04_benchmark.ipynb").read_bytes())
    (folder / "notes.ipynb").write_text("not a notebook")
    result = grader.grade(folder)
    assert result["score"] == 0 and result["max"] == 60
    assert {e["status"] for e in result["exercises"]} == {"missing", "not done"}
    (tmp_path / "cat").mkdir()
    (tmp_path / "cat" / "03_fusion_cat.ipynb").write_text("garbage")  # one unreadable notebook, graded alone
    one = grader.grade(tmp_path / "cat" / "03_fusion_cat.ipynb")
    assert [e["exercise"] for e in one["exercises"]] == ["student_mutual_nn", "student_fuse"] and one["score"] == 0
    assert all("not a readable notebook" in e["message"] for e in one["exercises"])
    assert assignments.main(["grade", str(tmp_path / "nobody")]) == 0
    assert "no such notebook or folder" in capsys.readouterr().out


@pytest.mark.filterwarnings("ignore:'freereg_lib.teaching.assignments' found in sys.modules:RuntimeWarning")
def test_module_runs_as_a_command(monkeypatch, capsys):
    # As ``python -m freereg_lib.teaching.assignments list`` runs it (its ``__main__`` block, the
    # module's code run afresh), in this process: a new interpreter would only import the library again.
    import runpy

    monkeypatch.setattr(sys, "argv", ["assignments", "list"])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_module("freereg_lib.teaching.assignments", run_name="__main__", alter_sys=True)
    out = capsys.readouterr()
    assert exit_.value.code == 0, out.err
    for name in EXERCISES:
        assert name in out.out


# --------------------------------------------------------------------------------------
# Papermill: filled from the key it runs; unfilled it runs too, each check reporting the stub.
# The unfilled run goes in a background process, started by the first test that makes the
# student versions, so it overlaps the other tests and the filled run (each kernel mostly
# waits on imports): the file takes ~45 s, not ~65 s. Both write the executed notebook once, at
# the end, not after every cell (papermill's default re-validates and re-writes it each time).

PAPERMILL_STEM = "00_preliminaries"


def _params(tmp: Path) -> dict:
    # Two noise levels for the forward-noising figure instead of six: a smaller figure, the same cells.
    return {"n_pairs": 1, "out_dir": str(tmp / "out"), "figures_dir": str(tmp / "figures"), "noise_steps": [0, 999]}


@pytest.fixture(scope="module")
def handout_dir(tmp_path_factory):
    """The student handout, as ``dist --zip`` builds it: (folder, zip)."""
    out = tmp_path_factory.mktemp("dist") / "handout"
    return out, handout.dist(out, zip_file=True)


@pytest.fixture(scope="module")
def unfilled_run(handout_dir, tmp_path_factory):
    """papermill on the untouched student notebook, from the handout alone (its own freereg_lib
    first on the path), in the background: (process, executed notebook)."""
    tmp = tmp_path_factory.mktemp("unfilled")
    executed = tmp / f"{PAPERMILL_STEM}.executed.ipynb"
    books = handout_dir[0] / "notebooks"
    cmd = [sys.executable, "-m", "papermill", str(books / f"{PAPERMILL_STEM}.ipynb"), str(executed),
           "-k", "python3", "--cwd", str(books), "--no-progress-bar", "--no-request-save-on-cell-execute",
           "-y", json.dumps(_params(tmp))]  # JSON is YAML: the list stays a list
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONPATH": str(handout_dir[0])})
    yield proc, executed
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_student_notebook_filled_from_the_key_is_the_key_but_for_its_folders(student_dir, tmp_path):
    """Filled from the key, a student notebook runs the key's code: every code cell is the key's but the
    parameters cell, whose defaults differ only in the handout's folders. So the key's own runs (nbmake's,
    and test_notebooks.py's with other parameters, which also require each check cell to pass
    unskipped) are the filled notebook's runs, top to bottom."""
    for stem in WITH_EXERCISES:
        key = _key(stem)
        filled = fill(_student(student_dir, stem), key)
        code = [c.source for c in filled.cells if c.cell_type == "code"]
        key_code = [c.source for c in key.cells if c.cell_type == "code"]
        assert len(code) == len(key_code) and code[1:] == key_code[1:], stem
        path = tmp_path / f"{stem}.ipynb"
        nbformat.write(filled, str(path))
        mine = {k: v["default"] for k, v in papermill.inspect_notebook(str(path)).items()}
        theirs = {k: v["default"] for k, v in papermill.inspect_notebook(str(NOTEBOOKS / f"{stem}.ipynb")).items()}
        assert mine.keys() == theirs.keys(), stem
        differ = {k for k in mine if mine[k] != theirs[k]}
        assert differ <= {"out_dir", "figures_dir"}, f"{stem}: the parameters cell differs in {sorted(differ)}"


def test_unfilled_student_notebook_runs_to_its_last_cell(unfilled_run):
    """Run All on the untouched student version reaches the end: each unsolved exercise's check
    cell says so in one printed line and the notebook goes on."""
    proc, executed = unfilled_run
    log, _ = proc.communicate(timeout=600)
    assert proc.returncode == 0, log[-3000:]
    nb = nbformat.read(executed, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert not [k for k, c in enumerate(code) if any(o.output_type == "error" for o in c.outputs)]
    assert all(c.execution_count is not None for c in code), "a code cell did not run"
    checks = check_cells(nb)
    assert len(checks) == len(check_cells(_key(PAPERMILL_STEM))) == 2
    for cell in checks:
        printed = "".join(o.get("text", "") for o in cell.outputs)
        name = next(n for n in EXERCISES if n in cell.source)
        assert f"EXERCISE NOT DONE: {name}" in printed and "reference" in printed, printed
    # The notebook's last cells (after both exercises) ran and printed their usual output.
    assert any(o.get("text") or o.get("data") for c in code[-4:] for o in c.outputs)


def test_exercise_check_skips_only_an_unsolved_stub(capsys):
    with check.exercise_check("student_fuse") as done:
        raise NotImplementedError("student_fuse is your exercise. Hint: normalise the rows")
    assert done.skipped == "student_fuse"
    assert "EXERCISE NOT DONE: student_fuse" in capsys.readouterr().out
    with pytest.raises(AssertionError):  # a wrong answer still stops the notebook
        with check.exercise_check("student_fuse"):
            assert False, "differs from features.fuse"
    with pytest.raises(NotImplementedError):  # someone else's NotImplementedError is not swallowed
        with check.exercise_check("student_fuse"):
            raise NotImplementedError("student_kabsch is your exercise")
    with pytest.raises(ValueError, match="unknown exercise"):
        check.exercise_check("fuse")


def _cell(source: str, name: str) -> dict:
    """Run ``source`` as IPython runs a cell (its text kept in linecache); its namespace."""
    filename = f"<cell {abs(hash(source))}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    env = {"np": np, "__name__": "__main__"}
    exec(compile(source, filename, "exec"), env)
    return env


def test_the_check_cell_says_when_a_solution_would_not_be_graded_alone():
    """The check cell stops a function that the grader could not run alone: its cell uses
    freereg_lib, or it reads a notebook variable; a solution in plain NumPy passes."""
    from freereg_lib.geometry import cameras

    ok = _cell(_key_function("03_fusion", "student_fuse"), "student_fuse")
    assert check.graded_alone(ok["student_fuse"], ok) is None
    lib = _cell("from freereg_lib.geometry import cameras\ndef student_kabsch(src, dst):\n"
                "    return cameras.invert(np.eye(4))\n", "student_kabsch")
    assert "line 1 imports freereg_lib.geometry" in check.graded_alone(lib["student_kabsch"], lib)
    env = _cell("def student_kabsch(src, dst):\n    return cameras.invert(pair_pose)\n", "student_kabsch")
    env["cameras"], env["pair_pose"] = cameras, np.eye(4)
    assert "uses cameras from freereg_lib" in check.graded_alone(env["student_kabsch"], env)
    del env["cameras"]
    assert "uses the notebook's pair_pose" in check.graded_alone(env["student_kabsch"], env)
    assert check.library_use("x = 'freereg' + '_lib'") is None  # what the source cannot show, the process stops
    assert check.library_use('def f():\n    """Like freereg_lib.features.fuse."""\n') is None  # prose may name it
    assert check.library_use("import importlib\nm = importlib.import_module('freereg_lib.features')") == \
        "line 2 names freereg_lib ('freereg_lib.features')"


def test_exercises_sit_at_the_end_of_their_section():
    """After an exercise's check cell comes the end of the notebook, a new section (## ...) or the
    next exercise; never more of the section's own material."""
    for stem in WITH_EXERCISES:
        cells = _key(stem).cells
        for k, cell in enumerate(cells):
            if "check" not in cell.metadata.get("tags", []):
                continue
            nxt = cells[k + 1] if k + 1 < len(cells) else None
            ok = nxt is None or (nxt.cell_type == "markdown" and (
                nxt.source.startswith("## ") or (nxt.source.startswith("#") and "exercise" in nxt.source.lower()
                                                 .splitlines()[0])))
            assert ok, f"{stem}: after the check cell {k} comes {nxt.source[:80]!r}, not a new section"
