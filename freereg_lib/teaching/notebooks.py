"""Reading the notebooks, the student versions of them, and the student distribution.

* :func:`make` writes a student version of every notebook: each ``solution`` cell keeps its
  functions' signatures and docstrings and gets the body ``raise NotImplementedError("<hint>")``;
  ``check`` cells stay (students run them to test themselves); outputs are stripped.
* The rest reads notebooks statically (tags, defined functions, the solution code of each
  exercise) for the grader. Nothing here runs a notebook's code.
"""
from __future__ import annotations

import ast
import copy
import io
import json
import re
import tokenize
from pathlib import Path

from freereg_lib.teaching.exercises import EXERCISES

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
NOTEBOOKS = ROOT / "notebooks"
DEFAULT_OUT = ROOT / "assignments" / "student"
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
    message = (f"{node.name} is your exercise (NumPy and the standard library only). Hint: {hint}" if hint else
               f"{node.name} is your exercise (NumPy and the standard library only): write it as the text above "
               "asks, then run the check cell below.")
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
                "are graded on their own, with only their arguments, NumPy and the standard library: the solution "
                "cell runs alone (with `numpy as np`), so it must not use `freereg_lib` or the notebook's "
                "variables (`pair`, `cfg`, ...); import anything else it needs in the cell itself.")
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
            if not (Path(key) / ".gitignore").exists():  # a `git add -A` must not commit the answer key
                (Path(key) / ".gitignore").write_text("# The answer key: never commit it.\n*\n", encoding="utf-8")
            answer = copy.deepcopy(nb)
            _strip(answer)
            nbformat.write(answer, str(Path(key) / path.name))
    return written


# --------------------------------------------------------------------------------------
# What the grader sends to the student's process.

def solution_sources(nb) -> dict[str, str]:
    """Each exercise function the notebook defines, and the code that defines it: its tagged
    solution cell (the whole cell, as plain Python), or failing that its last ``def`` in any
    other code cell. A tagged cell that does not parse still goes (its error is the result)."""
    found: dict[str, str] = {}
    for cell in nb.cells:
        if _is_solution(cell):
            source = _python(cell.source)
            names = _defined_functions(cell.source) or re.findall(r"^def\s+(\w+)", cell.source, re.MULTILINE)
            found.update({n: source for n in names if n in EXERCISES})
    for cell in nb.cells:
        if cell.cell_type != "code" or _is_solution(cell):
            continue
        try:
            tree = ast.parse(source := _python(cell.source))
        except SyntaxError:
            continue
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name in EXERCISES and node.name not in found:
                found[node.name] = ast.get_source_segment(source, node, padded=True)
    return found


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
