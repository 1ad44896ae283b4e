"""What students receive (``python -m freereg_lib.teaching.assignments dist``): what the notebooks need, and no more.

The handout holds the student version of every notebook *as* ``notebooks/``, the part of
``freereg_lib`` the notebooks import (followed through the library's own imports, with the
data files of those packages: the micro weights among them, which notebooks 01-04 run by
default), ``environment/``, ``pyproject.toml`` and a README for students. Of ``teaching`` it
holds only :mod:`.check` (the check cells' ``exercise_check``): no grader, no exercise
registry, no training code the notebooks do not import, no tests and no answer key (the
project's own ``notebooks/`` are the key and never go out).
"""
from __future__ import annotations

import ast
import json
import shutil
import zipfile
from pathlib import Path

from freereg_lib import SHORT_NAMES
from freereg_lib.teaching import notebooks as N

PACKAGE = Path(__file__).resolve().parents[1]
DEFAULT_DIST = N.ROOT / "assignments" / "handout"
_SKIP = ("__pycache__", ".ipynb_checkpoints", ".pytest_cache", "*.pyc")
_SHIM = '''"""The check cells' helper (the handout holds no grader)."""
from freereg_lib.teaching.check import exercise_check  # noqa: F401
'''
_STUDENT_README = """# FreeReg companion: student handout

The notebooks in `notebooks/` are the course's student versions: each exercise is a function
`student_<thing>` in a cell tagged `solution` that raises `NotImplementedError` with a hint.
Write it there, keep its name and signature, and run the cell tagged `check` below it.

Setup (once): `environment/setup_env.sh` (or `python -m venv .venv` and
`.venv/bin/python -m pip install -r environment/requirements.txt -e .`), then open the
notebooks with `.venv/bin/jupyter lab notebooks/`. Everything runs on a CPU.

Hand back your `notebooks/*.ipynb` as your teacher asks. Each function is graded on its own:
its solution cell runs alone, with NumPy and the standard library only (`numpy as np` is
there), on inputs drawn at grading time. `freereg_lib` and the notebook's variables are not
there, so a solution cell that imports the library scores 0 on its exercise.
"""


def _module_file(name: str) -> Path | None:
    path = PACKAGE.parent.joinpath(*name.split("."))
    for candidate in (path / "__init__.py", path.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


def _imported(tree: ast.AST, name: str, is_package: bool) -> set[str]:
    """The ``freereg_lib`` modules (and candidates: ``from a import b`` may import module a.b) a tree imports."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = name.split(".")[: len(name.split(".")) - node.level + is_package]
                module = ".".join(base + ([module] if module else []))
            found |= {module} | {f"{module}.{a.name}" for a in node.names}
    found = {m for m in found if m.split(".")[0] == PACKAGE.name}
    # ``from freereg_lib import cameras``: the package's short names for its modules (SHORT_NAMES)
    return {SHORT_NAMES.get(m.split(".", 1)[1], m) if m.count(".") == 1 else m for m in found}


def needed_modules(student_notebooks: list[Path]) -> set[Path]:
    """The library's files the notebooks import, directly or through the library (every import
    statement counts, those inside functions too); ``teaching`` is not followed."""
    todo = {PACKAGE.name}
    for path in student_notebooks:
        for cell in N._read(path).cells:
            if cell.cell_type == "code":
                try:
                    todo |= _imported(ast.parse(N._python(cell.source)), "__main__", False)
                except SyntaxError:
                    continue
    seen: set[str] = set()
    files: set[Path] = set()
    while todo:
        name = todo.pop()
        file = _module_file(name)
        if name in seen or file is None:
            continue
        seen.add(name)
        files.add(file)
        parts = name.split(".")
        todo |= {".".join(parts[:k]) for k in range(1, len(parts))}
        if parts[:2] != [PACKAGE.name, "teaching"]:
            todo |= _imported(ast.parse(file.read_text()), name, file.name == "__init__.py") - seen
    return {f for f in files if f.parent != PACKAGE / "teaching"}


def _data_files(package_dir: Path) -> list[Path]:
    """A package's files that are not Python, its non-package sub-folders' included."""
    out = []
    for entry in sorted(package_dir.iterdir()):
        if entry.is_file() and entry.suffix not in (".py", ".pyc"):
            out.append(entry)
        elif entry.is_dir() and entry.name not in _SKIP and not (entry / "__init__.py").exists():
            out += [f for f in entry.rglob("*") if f.is_file() and "__pycache__" not in f.parts]
    return out


def dist(out: str | Path = DEFAULT_DIST, notebooks: str | Path = N.NOTEBOOKS, zip_file: bool = False,
         root: Path = N.ROOT) -> Path:
    """Build the student handout in folder ``out`` (and ``out.zip`` with ``zip_file``).

    Raises if any notebook in it still holds a line of a solution (a last check). Returns the
    folder or the zip.
    """
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    written = N.make(out / "notebooks", notebooks)
    files = needed_modules(written)
    for package_dir in {f.parent for f in files if f.name == "__init__.py"}:
        files |= set(_data_files(package_dir))
    files |= {PACKAGE / "teaching" / "__init__.py", PACKAGE / "teaching" / "check.py"}
    for f in files:
        target = out / f.relative_to(PACKAGE.parent)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, target)
    (out / PACKAGE.name / "teaching" / "assignments.py").write_text(_SHIM)
    shutil.copytree(root / "environment", out / "environment", ignore=shutil.ignore_patterns(*_SKIP))
    shutil.copy2(root / "pyproject.toml", out / "pyproject.toml")
    (out / "README.md").write_text(_STUDENT_README)
    keys = {p.name: N._read(p) for p in Path(notebooks).glob("*.ipynb")}
    for path in written:
        assert_no_solution(keys[path.name], N._read(path), path.name)
    if not zip_file:
        return out
    archive = out.with_suffix(".zip")
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(out.rglob("*")):
            if f.is_file():
                z.write(f, Path(out.name) / f.relative_to(out))
    return archive


def assert_no_solution(key, student, name: str) -> None:
    """No line of the key's solution bodies (beyond imports and signatures) is in ``student``."""
    text = json.dumps(student)
    kept = {ln.strip() for c in key.cells if c.cell_type == "code" and not N._is_solution(c)
            for ln in c.source.splitlines()}
    for cell in key.cells:
        if not N._is_solution(cell):
            continue
        lines = cell.source.splitlines()
        for node in ast.parse(N._python(cell.source)).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for stmt in node.body[1:] if ast.get_docstring(node) is not None else node.body:
                    for ln in lines[stmt.lineno - 1: stmt.end_lineno]:
                        ln = ln.strip()
                        if len(ln) > 12 and not ln.startswith("#") and ln not in kept \
                                and json.dumps(ln)[1:-1] in text:
                            raise AssertionError(f"{name}: solution line {ln!r} in the student version")
