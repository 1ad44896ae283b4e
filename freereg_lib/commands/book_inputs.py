"""The book's sources checked before Sphinx starts (``python -m freereg_lib.commands.book RUN``).

A notebook cut off while it was written (a full disk, a killed run), an empty or ``{}`` file, a
notebook path that is a folder, or a docs page saved in another encoding than UTF-8 made the
book command stop with a Python traceback from the staging code, or with pages of Sphinx
warnings a minute later. :func:`source_fault` names the first such file and what was expected;
:func:`exit_on_bad_sources` prints it as one line and exits with status 2 (bad input, as the
other commands), before anything is staged or built.
"""
from __future__ import annotations

import json
import sys
from collections.abc import Iterable
from pathlib import Path

NOTEBOOK_GLOB = "[0-9][0-9]_*.ipynb"  # the run's executed notebooks, as book.stage_notebooks reads them
CELL_TYPES = ("markdown", "code", "raw")
EXPECTED_NB = "expected an executed notebook (nbformat 4 JSON: an object with 'cells' and 'nbformat': 4)"


def _is_text(source) -> bool:
    """A cell's source as nbformat stores it: one string or a list of strings."""
    return isinstance(source, str) or (isinstance(source, list) and all(isinstance(s, str) for s in source))


def notebook_fault(path: Path) -> str:
    """What is wrong with the notebook file ``path`` for the book ("" when nothing)."""
    if path.is_dir():
        return f"{path}: a folder; expected a notebook file (.ipynb: nbformat 4 JSON)"
    try:
        raw = path.read_bytes()
    except OSError as exc:
        return f"{path}: cannot read it ({exc.strerror or exc}); {EXPECTED_NB}"
    if not raw.strip():
        return f"{path}: an empty file; {EXPECTED_NB} (re-run the notebook)"
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        return f"{path}: not UTF-8 (byte 0x{raw[exc.start]:02x} at offset {exc.start}); {EXPECTED_NB}"
    try:
        nb = json.loads(text)
    except json.JSONDecodeError as exc:
        # A notebook ends with its closing brace; without it the writer stopped part way (a killed run, a full disk).
        cut = "" if text.rstrip().endswith("}") else " (it ends before its closing '}': cut off; re-run the notebook)"
        return f"{path}: not JSON at line {exc.lineno}, column {exc.colno} ({exc.msg}){cut}; {EXPECTED_NB}"
    if not isinstance(nb, dict):
        return f"{path}: a JSON {type(nb).__name__}, not an object; {EXPECTED_NB}"
    missing = [k for k in ("cells", "nbformat") if k not in nb]
    if missing:
        return f"{path}: no {' and no '.join(repr(k) for k in missing)}; {EXPECTED_NB}"
    if nb["nbformat"] != 4:
        return f"{path}: nbformat {nb['nbformat']!r}; {EXPECTED_NB} (upgrade it with `jupyter nbconvert --to notebook`)"
    if not isinstance(nb["cells"], list):
        return f"{path}: 'cells' is a {type(nb['cells']).__name__}, not a list; {EXPECTED_NB}"
    if "metadata" in nb and not isinstance(nb["metadata"], dict):
        return f"{path}: 'metadata' is a {type(nb['metadata']).__name__}, not an object; {EXPECTED_NB}"
    for k, cell in enumerate(nb["cells"]):
        if not isinstance(cell, dict) or cell.get("cell_type") not in CELL_TYPES or not _is_text(cell.get("source")):
            return (f"{path}: cell {k} is not a notebook cell; expected an object with 'cell_type' "
                    f"({', '.join(CELL_TYPES)}) and 'source' (text)")
        if not isinstance(cell.get("metadata", {}), dict):
            return f"{path}: cell {k}'s 'metadata' is not an object; {EXPECTED_NB}"
    return ""


def page_fault(path: Path) -> str:
    """What is wrong with the Markdown page ``path`` for the book ("" when nothing)."""
    if path.is_dir():
        return f"{path}: a folder; expected a Markdown page (a UTF-8 text file)"
    try:
        raw = path.read_bytes()
    except OSError as exc:
        return f"{path}: cannot read it ({exc.strerror or exc}); expected a Markdown page (a UTF-8 text file)"
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        return (f"{path}: not UTF-8 (byte 0x{raw[exc.start]:02x} on line {line}); expected a Markdown page in UTF-8: "
                "re-save it as UTF-8 (e.g. `iconv -f latin1 -t utf-8`)")
    return ""


def source_fault(run_dir: str | Path, docs_dir: str | Path, extra_pages: Iterable[str | Path] = ()) -> str:
    """The first bad source of the book of ``run_dir`` as one line ("" when all are readable):
    the run folder itself, its notebooks (:data:`NOTEBOOK_GLOB`), then ``docs_dir/*.md`` and the
    ``extra_pages`` that exist (the book leaves a missing extra page out)."""
    run = Path(run_dir)
    if not run.is_dir():
        return (f"{run}: {'not a folder' if run.exists() else 'no such folder'}; expected the run folder of "
                "executed notebooks (NN_*.ipynb), e.g. runs/reproduce")
    for path in sorted(run.glob(NOTEBOOK_GLOB)):
        fault = notebook_fault(path)
        if fault:
            return fault
    docs = Path(docs_dir)
    pages = sorted(docs.glob("*.md")) if docs.is_dir() else []
    for path in pages + [Path(p) for p in extra_pages if Path(p).exists()]:
        fault = page_fault(path)
        if fault:
            return fault
    return ""


def exit_on_bad_sources(run_dir: str | Path, docs_dir: str | Path, extra_pages: Iterable[str | Path] = ()) -> None:
    """Print :func:`source_fault` as ``book: <file>: <what was expected>`` and exit with status 2
    when there is one; return quietly otherwise."""
    fault = source_fault(run_dir, docs_dir, extra_pages)
    if fault:
        print(f"book: {fault}", file=sys.stderr)
        raise SystemExit(2)
