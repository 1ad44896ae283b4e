"""Reading the notebooks, the student versions of them, and the student distribution.

* :func:`make` writes a student version of every notebook: each ``solution`` cell keeps its
  functions' signatures and docstrings and gets the body ``raise NotImplementedError("<hint>")``;
  ``check`` cells stay (students run them to test themselves); outputs are stripped.
* :func:`dist` builds what students receive (a folder or a zip): the library, the environment
  files and the student notebooks *as* ``notebooks/``, and nothing else: no answer key, no
  tests, no grader data. The project's own ``notebooks/`` are the answer key and never go out.
* The rest reads notebooks statically (tags, defined functions, imports) for the grader and
  for the student's process. Nothing here runs a notebook's code.
"""
from __future__ import annotations

import ast
import copy
import io
import json
import pkgutil
import re
import shutil
import tokenize
import zipfile
from pathlib import Path

from freereg_lib.teaching.exercises import EXERCISES

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
NOTEBOOKS = ROOT / "notebooks"
DEFAULT_OUT = ROOT / "assignments" / "student"
DEFAULT_DIST = ROOT / "assignments" / "handout"
SOLUTION_TAG = "solution"
CHECK_TAG = "check"
METADATA_KEY = "freereg_assignment"
BANNER_ID = "assignment-banner"

# --------------------------------------------------------------------------------------
# Reading notebooks.

def _read(path: str | Path):
    import nbformat

    return nbformat.read(str(path), as_version=4)


def _tags(cell) -> list[str]:
    return list(cell.get("metadata", {}).get("tags", []))


def _is_solution(cell) -> bool:
    return cell.cell_type == "code" and SOLUTION_TAG in _tags(cell)


def _python(source: str) -> str:
    """A cell's source as plain Python (IPython magics become calls) where IPython is around."""
    try:
        from IPython.core.inputtransformer2 import TransformerManager
    except ImportError:  # pragma: no cover - IPython comes with the notebook extras
        return source
    try:
        return TransformerManager().transform_cell(source)
    except Exception:
        return source


def _defined_functions(source: str) -> list[str]:
    try:
        tree = ast.parse(_python(source))
    except SyntaxError:
        return []
    return [n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _notebook_stem(nb, path: Path | None) -> str | None:
    """Which project notebook ``nb`` is: its assignment metadata, else its file name."""
    meta = nb.get("metadata", {}).get(METADATA_KEY, {})
    if meta.get("notebook"):
        return meta["notebook"]
    if path is None:
        return None
    stems = sorted({e.notebook for e in EXERCISES.values()} | {p.stem for p in NOTEBOOKS.glob("*.ipynb")})
    for stem in stems:
        if path.stem.startswith(stem):
            return stem
    prefix = re.match(r"(\d\d)_", path.stem)
    matches = [s for s in stems if prefix and s.startswith(prefix.group(0))]
    return matches[0] if len(matches) == 1 else None


# --------------------------------------------------------------------------------------
# Student versions.

_HINT_COMMENT = re.compile(r"#\s*HINT\s*:?\s*(.*)", re.IGNORECASE)
_MARKDOWN_HINT = re.compile(r"\bHint:\s*(.+?)(?:\)\s*)?(?:\n\s*\n|$)", re.DOTALL)


def _clean(text: str) -> str:
    return " ".join(text.split())


def markdown_hint(nb, index: int) -> str | None:
    """The "Hint: ..." sentence of the markdown cell(s) just above cell ``index``, if any."""
    for cell in reversed(nb.cells[:index]):
        if cell.cell_type != "markdown":
            break
        m = _MARKDOWN_HINT.search(cell.source)
        if m:
            return _clean(m.group(1))
    return None


def _signature_end(lines: list[str], start: int, stop: int) -> tuple[int, int]:
    """(0-based line, column) of the colon that ends the ``def`` line(s) in ``lines[start:stop]``."""
    text = "\n".join(lines[start:stop]) + "\n"
    depth, seen_def = 0, False
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.NAME and tok.string == "def":
            seen_def = True
        elif tok.type == tokenize.OP:
            if tok.string in "([{":
                depth += 1
            elif tok.string in ")]}":
                depth -= 1
            elif tok.string == ":" and seen_def and depth == 0:
                return start + tok.start[0] - 1, tok.start[1]
    raise ValueError("could not find the end of the def line")


def _hint_comments(lines: list[str], start: int, stop: int) -> list[str]:
    text = "\n".join(lines[start:stop]) + "\n"
    found = []
    try:
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            if tok.type == tokenize.COMMENT:
                m = _HINT_COMMENT.match(tok.string)
                if m and m.group(1).strip():
                    found.append(m.group(1).strip())
    except (tokenize.TokenError, IndentationError):
        pass
    return found


def _function_stub(node: ast.FunctionDef, lines: list[str], chunk_start: int, md_hint: str | None) -> list[str]:
    first = min([node.lineno, *(d.lineno for d in node.decorator_list)]) - 1
    end = node.end_lineno
    colon_line, colon_col = _signature_end(lines, first, end)
    body0 = node.body[0]
    one_liner = body0.lineno - 1 == colon_line
    if one_liner:
        head = lines[first:colon_line] + [lines[colon_line][: colon_col + 1]]
        indent = " " * (node.col_offset + 4)
    else:
        head = lines[first : colon_line + 1]
        indent = " " * body0.col_offset
    out = list(head)
    doc = ast.get_docstring(node, clean=True)
    has_doc = isinstance(body0, ast.Expr) and isinstance(body0.value, ast.Constant) and isinstance(body0.value.value, str)
    if has_doc and not one_liner:
        out += lines[body0.lineno - 1 : body0.end_lineno]
    elif has_doc:
        out.append(f'{indent}"""{doc}"""')
    hints = _hint_comments(lines, chunk_start, end)
    if hints:
        hint = " ".join(hints)
    elif md_hint:
        hint = md_hint
    elif doc:
        hint = doc.strip().splitlines()[0]
    else:
        hint = None
    message = (f"{node.name} is your exercise. Hint: {hint}" if hint else
               f"{node.name} is your exercise: write it as the text above asks, then run the check cell below.")
    out.append(f"{indent}# Your code here: replace the line below with your implementation.")
    out.append(f"{indent}raise NotImplementedError({json.dumps(message, ensure_ascii=False)})")
    return out


def stub_source(source: str, md_hint: str | None = None) -> str:
    """A solution cell with every top-level function reduced to signature, docstring and a stub.

    Imports are kept; every other statement, comment and nested function is solution code and
    goes. The stub raises ``NotImplementedError`` with a hint: a ``# HINT: ...`` comment of the
    function (or just above it) if there is one, else the exercise text's "Hint: ..." sentence
    (``md_hint``), else the docstring's first line, else a generic pointer to the text and the
    check cell. (The docstring comes after the exercise's hint because the stub keeps it anyway.)
    """
    tree = ast.parse(source)
    lines = source.splitlines()
    out: list[list[str]] = []
    chunk_start = 0
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out.append(_function_stub(node, lines, chunk_start, md_hint))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(lines[node.lineno - 1 : node.end_lineno])
        chunk_start = node.end_lineno
    return "\n\n\n".join("\n".join(chunk) for chunk in out)


def _banner(stem: str, functions: list[str]):
    import nbformat

    if functions:
        todo = "\n".join(f"- `{name}`" for name in functions)
        text = (f"**Student version** of `{stem}`.\n\n"
                f"Your exercises in this notebook (code cells tagged `{SOLUTION_TAG}`):\n\n{todo}\n\n"
                "Replace each `raise NotImplementedError(...)` with your code, keep the function names and "
                f"signatures, and run the cell tagged `{CHECK_TAG}` just below to test yourself. Your functions "
                "are graded on their own, with only their arguments, `numpy as np`, this notebook's imports and "
                "the `freereg_lib` modules to hand; do not use the notebook's variables (`pair`, `cfg`, ...) "
                "inside them.")
    else:
        text = f"**Student version** of `{stem}`. This notebook has no exercise: read and run it."
    cell = nbformat.v4.new_markdown_cell(text)
    cell["id"] = BANNER_ID
    return cell


def _relocate_outputs(source: str, stem: str) -> str:
    """Point ``out_dir`` / ``figures_dir`` of a parameters cell (annotated or not) into the student folder."""
    targets = {"out_dir": f"runs/{stem}", "figures_dir": "figures"}
    return re.sub(r'^(\s*)(out_dir|figures_dir)(\s*(?::[^=\n]*)?=\s*)(?:"[^"\n]*"|\'[^\'\n]*\')(.*)$',
                  lambda m: f'{m.group(1)}{m.group(2)}{m.group(3)}"{targets[m.group(2)]}"{m.group(4)}',
                  source, flags=re.MULTILINE)


def _strip(nb) -> None:
    for cell in nb.cells:
        cell.get("metadata", {}).pop("papermill", None)
        cell.get("metadata", {}).pop("execution", None)
        if cell.cell_type == "code":
            cell["outputs"] = []
            cell["execution_count"] = None
    nb.metadata.pop("papermill", None)


def student_notebook(nb, stem: str):
    """The student version of notebook ``nb`` (a copy; ``nb`` is left alone)."""
    out = copy.deepcopy(nb)
    _strip(out)
    functions = []
    for i, cell in enumerate(out.cells):
        if _is_solution(cell):
            functions += _defined_functions(cell.source)
            try:
                cell.source = stub_source(cell.source, markdown_hint(out, i))
            except SyntaxError as e:
                raise ValueError(f"{stem}: solution cell {i} is not valid Python ({e})") from e
        elif cell.cell_type == "code" and "parameters" in _tags(cell):
            cell.source = _relocate_outputs(cell.source, stem)
    banner = _banner(stem, functions)
    if out.nbformat_minor < 5:
        banner.pop("id", None)
    out.cells.insert(0, banner)
    out.metadata[METADATA_KEY] = {"notebook": stem, "exercises": functions,
                                  "generated_by": "python -m freereg_lib.teaching.assignments make"}
    return out


def make(out: str | Path = DEFAULT_OUT, notebooks: str | Path = NOTEBOOKS,
         key: str | Path | None = None) -> list[Path]:
    """Write the student version of every notebook of ``notebooks`` into ``out``.

    With ``key``, a copy of the originals (outputs stripped) goes there as the answer key.
    Returns the student notebooks written.
    """
    import nbformat

    out, notebooks = Path(out), Path(notebooks)
    sources = sorted(notebooks.glob("*.ipynb"))
    if not sources:
        raise FileNotFoundError(f"no notebook in {notebooks}")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for path in sources:
        nb = _read(path)
        student = student_notebook(nb, path.stem)
        nbformat.validate(student)
        nbformat.write(student, str(out / path.name))
        written.append(out / path.name)
        if key is not None:
            Path(key).mkdir(parents=True, exist_ok=True)
            answer = copy.deepcopy(nb)
            _strip(answer)
            nbformat.write(answer, str(Path(key) / path.name))
    return written


def fill(student, key):
    """The student notebook with the key's solution cells put back (a copy).

    Cells are matched by the functions they define, else by their order.
    """
    out = copy.deepcopy(student)
    key_cells = [c for c in key.cells if _is_solution(c)]
    by_names = {tuple(_defined_functions(c.source)): c.source for c in key_cells}
    mine = [c for c in out.cells if _is_solution(c)]
    for k, cell in enumerate(mine):
        names = tuple(_defined_functions(cell.source))
        if names in by_names:
            cell.source = by_names[names]
        elif k < len(key_cells):
            cell.source = key_cells[k].source
    return out




# --------------------------------------------------------------------------------------
# What the student's process needs to load the solution cells.

def _parsed_cells(nb):
    """The syntax tree of every code cell outside the solution cells that parses."""
    for cell in nb.cells:
        if cell.cell_type != "code" or _is_solution(cell):
            continue
        try:
            yield ast.parse(_python(cell.source))
        except SyntaxError:
            continue


def _import_statements(nb) -> dict[str, str]:
    """Every name the notebook's import statements bind (outside solution cells), and the statement."""
    lazy: dict[str, str] = {}
    import freereg_lib

    for mod in pkgutil.iter_modules(freereg_lib.__path__):
        if mod.name not in ("assignments", "teaching"):
            lazy[mod.name] = f"from freereg_lib import {mod.name}"
    for tree in _parsed_cells(nb):
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    name = a.asname or a.name.split(".")[0]
                    lazy[name] = f"import {a.name}" + (f" as {a.asname}" if a.asname else "")
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                for a in node.names:
                    if a.name != "*":
                        lazy[a.asname or a.name] = (f"from {node.module} import {a.name}"
                                                    + (f" as {a.asname}" if a.asname else ""))
    return lazy




def notebooks_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.ipynb")
                  if ".ipynb_checkpoints" not in p.parts and not p.name.endswith(".executed.ipynb"))


def relevant(nb, path: Path) -> list[str]:
    """The exercises a notebook is graded on: those of the project notebook it is a version
    of (its metadata or file name), then any other exercise function it defines."""
    stem = _notebook_stem(nb, path)
    own = [n for n, ex in EXERCISES.items() if ex.notebook == stem]
    defined = {n for c in nb.cells if c.cell_type == "code" for n in _defined_functions(c.source)}
    return own + [n for n in EXERCISES if n in defined and n not in own]


# --------------------------------------------------------------------------------------
# What students receive.

_DIST_SKIP = {"__pycache__", ".ipynb_checkpoints", ".pytest_cache"}
_STUDENT_README = """# FreeReg companion: student handout

The notebooks in `notebooks/` are the course's student versions: each exercise is a function
`student_<thing>` in a cell tagged `solution` that raises `NotImplementedError` with a hint.
Write it there, keep its name and signature, and run the cell tagged `check` below it.

Setup (once): `environment/setup_env.sh` (or `python -m venv .venv` and
`.venv/bin/python -m pip install -r environment/requirements.txt -e .`), then open the
notebooks with `.venv/bin/jupyter lab notebooks/`. Everything runs on a CPU.

Hand back your `notebooks/*.ipynb` as your teacher asks. They are graded by calling your
functions on inputs drawn at grading time; only the functions count, and they must not just
call the library's own implementation of the exercise.
"""


def dist(out: str | Path = DEFAULT_DIST, notebooks: str | Path = NOTEBOOKS, zip_file: bool = False,
         root: Path = ROOT) -> Path:
    """Build the student distribution in folder ``out`` (and ``out.zip`` with ``zip_file``).

    It holds ``freereg_lib/`` (the library the notebooks import), ``environment/``,
    ``pyproject.toml``, a README for students and the student version of every notebook in
    ``notebooks/`` (as :func:`make` writes them). Not the project's notebooks (they are the
    answer key), its tests, its ``assignments/`` folder or anything else. Raises if any
    notebook in it still holds a solution cell's code (a last check). Returns the folder or zip.
    """
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    (out / "notebooks").mkdir(parents=True)
    ignore = shutil.ignore_patterns(*_DIST_SKIP, "*.pyc")
    shutil.copytree(Path(__file__).resolve().parents[1], out / "freereg_lib", ignore=ignore)
    shutil.copytree(root / "environment", out / "environment", ignore=ignore)
    for name in ("pyproject.toml",):
        shutil.copy2(root / name, out / name)
    (out / "README.md").write_text(_STUDENT_README)
    written = make(out / "notebooks", notebooks)
    keys = {p.name: _read(p) for p in Path(notebooks).glob("*.ipynb")}
    for path in written:
        _assert_no_solution(keys[path.name], _read(path), path.name)
    if not zip_file:
        return out
    archive = out.with_suffix(".zip")
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(out.rglob("*")):
            if f.is_file():
                z.write(f, Path(out.name) / f.relative_to(out))
    return archive


def _assert_no_solution(key, student, name: str) -> None:
    """No line of the key's solution bodies (beyond imports and signatures) is in ``student``."""
    text = json.dumps(student)
    kept = {ln.strip() for c in key.cells if c.cell_type == "code" and not _is_solution(c)
            for ln in c.source.splitlines()}
    for cell in key.cells:
        if not _is_solution(cell):
            continue
        tree = ast.parse(_python(cell.source))
        lines = cell.source.splitlines()
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                body = node.body[1:] if ast.get_docstring(node) is not None else node.body
                for stmt in body:
                    for ln in lines[stmt.lineno - 1: stmt.end_lineno]:
                        ln = ln.strip()
                        if len(ln) > 12 and not ln.startswith("#") and ln not in kept \
                                and json.dumps(ln)[1:-1] in text:
                            raise AssertionError(f"{name}: solution line {ln!r} in the student version")
