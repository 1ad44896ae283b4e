"""The book's sources checked before Sphinx starts (``python -m freereg_lib.commands.book RUN``).

A notebook cut off while it was written (a full disk, a killed run), an empty or ``{}`` file, a
notebook path that is a folder, or a docs page saved in another encoding than UTF-8 made the
book command stop with a Python traceback from the staging code, or with pages of Sphinx
warnings a minute later. :func:`source_fault` names the first such file and what was expected;
:func:`exit_on_bad_sources` prints it as one line and exits with status 2 (bad input, as the
other commands), before anything is staged or built. :func:`output_fault` does the same for where the
book writes: its site folder, the run folder it stages in, and the figures its index shrinks.
"""
from __future__ import annotations

import json
import shutil
import sys
from collections.abc import Iterable
from pathlib import Path

from freereg_lib.commands import process_io
from freereg_lib.commands.process_io import write_fault

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


# --- where the book writes -------------------------------------------------------------------------------
# The book empties its site folder before Sphinx writes it. It empties only a folder it built itself (one
# holding SITE_MARK, written before Sphinx starts, so a build that failed half way is still the book's),
# or the default ``<run>/site`` of an older build (Sphinx's ``.buildinfo`` there): a user's folder given as
# ``--out`` is never emptied, and ``--out`` naming the run folder or another input is refused.
SITE_MARK = ".freereg-book-site"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CHOOSE = "choose a new or empty folder, e.g. <run>/site (the default)"


def _writable_fault(folder: Path, what: str) -> str:
    """``folder`` (or, when it does not exist yet, its nearest existing parent) refusing a file, as one line."""
    why = write_fault(folder)
    return f"{what} {folder}: {why}; {CHOOSE}" if why else ""


def _figure_fault(path: Path) -> str:
    """What is wrong with the run's figure ``path`` for the book's index ("" when it is a readable PNG)."""
    from PIL import Image

    try:
        with path.open("rb") as f:
            head = f.read(8)
        if head != PNG_MAGIC:
            return (f"{path}: not a PNG image (it starts with {head[:4]!r}); expected the PNG a notebook drew: "
                    "re-run the notebook, or remove the file (the index then says the figure was not drawn)")
        with Image.open(path) as im:
            im.verify()
    except OSError as exc:  # PIL's errors on a cut file are OSErrors (or SyntaxError on a bad chunk)
        return f"{path}: a damaged PNG ({exc}); re-run the notebook that draws it, or remove the file"
    except SyntaxError as exc:
        return f"{path}: a damaged PNG ({exc}); re-run the notebook that draws it, or remove the file"
    return ""


def output_fault(run_dir: Path, site: Path, figures_dir: Path, inputs: Iterable[Path],
                 figure_stems: Iterable[str]) -> str:
    """Why the book must not write the site ``site`` of ``run_dir`` ("" when it may), as one line.

    Refused: ``site`` equal to, or a folder above, the run folder or any of ``inputs`` (docs, the
    configuration, the project); ``site`` inside the book's staging folders; a file; a folder holding
    files the book did not write; a run folder or site that cannot be written; a figure of
    ``figures_dir`` named in ``figure_stems`` that is not a readable PNG."""
    run_dir, site = Path(run_dir).resolve(), Path(site).resolve()
    for folder, name in [(run_dir, "the run folder")] + [(Path(p).resolve(), "an input of the book") for p in inputs]:
        if site == folder or folder.is_relative_to(site):
            return (f"--out {site}: {'is' if site == folder else 'holds'} {name} ({folder}); the book replaces its "
                    f"site folder, so it would delete it: {CHOOSE}")
    for staging in ("book_src", "book_doctrees"):
        if site.is_relative_to(run_dir / staging):
            return f"--out {site}: inside {run_dir / staging}, which the book rewrites each build; {CHOOSE}"
    if site.exists() and not site.is_dir():
        return f"--out {site}: a file, not a folder; {CHOOSE}"
    if site.is_dir() and not (site / SITE_MARK).is_file():
        legacy = site == run_dir / "site" and (site / ".buildinfo").is_file()  # built before the mark existed
        foreign = sorted(p.name for p in site.iterdir())
        if foreign and not legacy:
            return (f"--out {site}: holds files the book did not write ({', '.join(foreign[:3])}"
                    f"{', ...' if len(foreign) > 3 else ''}); the book empties its site folder before it writes, "
                    f"so it writes only into a new or empty folder or a site it built: {CHOOSE}")
    try:
        process_io.probe_write(run_dir)
    except OSError as exc:
        return (f"{run_dir}: cannot write in the run folder ({exc.strerror or exc}); the book stages its sources in "
                "<run>/book_src: copy the run folder somewhere writable (`cp -r RUN /tmp/run`) and build from there")
    fault = _writable_fault(site, "--out")
    if fault:
        return fault
    for stem in figure_stems:
        path = Path(figures_dir) / f"{stem}.png"
        if path.is_file():
            fault = _figure_fault(path)
            if fault:
                return fault
    return ""


def clear_site(site: Path) -> None:
    """Make ``site`` an empty folder holding :data:`SITE_MARK` (after :func:`output_fault` let it through):
    a site the book built is emptied, a new folder created."""
    if site.is_dir() and any(site.iterdir()):
        shutil.rmtree(site)
    site.mkdir(parents=True, exist_ok=True)
    (site / SITE_MARK).write_text("Written by `python -m freereg_lib.commands.book`: the book may empty this "
                                  "folder when it rebuilds the site.\n", encoding="utf-8")
