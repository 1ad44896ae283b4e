"""The companion as a static site, and the README's gallery, from one run's executed notebooks.

``python -m freereg_lib.commands.site runs/reproduce`` (``make book``; ``make reproduce`` calls it at the
end) renders every executed notebook ``NN_*.ipynb`` of a run folder with nbconvert's HTML exporter
into ``<run>/site/``, with the small template ``site_templates/freereg`` (nbconvert's "lab"
template plus navigation): previous / next links on every page, a table of contents at the top of
each notebook page built from its headings, and the backend named on every page. The index page
is itself a notebook made here and rendered the same way: the notebooks with their backends, and a
table mapping every paper float the companion re-draws (:data:`PAPER_FLOATS`) to its notebook
section and figure (a thumbnail under ``site/figures/``), and links to the reference pages. After the
notebooks come the pages of ``docs/`` and an API reference made from the docstrings, one page per
module (:mod:`freereg_lib.commands.site_docs`); previous / next run through all of them in that order.

:func:`write_gallery` writes the README's gallery: compact copies (at most ``max_width`` pixels
wide and ``max_bytes`` each) of the key figures of the run (:data:`GALLERY`) into
``figures/gallery/``, which is committed.

This module owns the site's layout, the float table and the gallery's list; the notebooks own
their content, headings and figure names (a float whose heading or figure is missing fails the
build with a message naming it).
"""
from __future__ import annotations

import argparse
import ast
import html
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from freereg_lib.report.plots import compact_png

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
TEMPLATES = Path(__file__).resolve().parent / "site_templates"
TEMPLATE = "freereg"
GALLERY_DIR = ROOT / "figures" / "gallery"


@dataclass(frozen=True)
class PaperFloat:
    """A float of the paper the companion re-draws: where, and in which figure files."""

    number: str               # "Fig. 4c", "Table 1"
    shows: str                # what it shows, as the paper names it
    notebook: str             # notebook stem
    section: str              # the start of the section's heading text (without the #s)
    figures: tuple[str, ...]  # figure file stems (figures/<stem>.png)


# Every float re-drawn, in the paper's order (numbers: ../shared/paper/FACTS.md, "Figure and table numbers").
PAPER_FLOATS: tuple[PaperFloat, ...] = (
    PaperFloat("Fig. 4c", "PCA of decoder features (diffusion feature extraction)", "01_diffusion_features",
               "3. What the layers see", ("01_pca_layers",)),
    PaperFloat("Fig. 5 b-d", "fused features: D / G / fused feature maps", "03_fusion", "2. The fusion",
               ("03_features_diffusion", "03_features_geometric", "03_features_fused")),
    PaperFloat("Fig. 5 e-g", "fused features: D / G / fused matches", "03_fusion",
               "3. Correspondences from D, G and fused features", ("03_matches_d_g_fused",)),
    PaperFloat("Fig. 7", "rotation and translation error curves (appendix)", "04_benchmark",
               "5. Rotation and translation error curves", ("04_rotation_error_curves", "04_translation_error_curves")),
    PaperFloat("Table 1", "main results, beside the re-run", "04_benchmark", "3. Table 1 beside the paper's",
               ("04_table1_side_by_side",)),
    PaperFloat("Table 2", "layer selection", "01_diffusion_features", "5. Which layers?",
               ("01_table2_ir", "01_table2_in")),
    PaperFloat("Table 3", "diffusion step t_hat", "01_diffusion_features", "6. Which diffusion step",
               ("01_table3_t_hat",)),
    PaperFloat("Table 4", "fusion weight w", "03_fusion", "4. The fusion weight", ("03_table4_fusion_weight",)),
    PaperFloat("Table 7", "SD vs ControlNet depth features (appendix)", "01_diffusion_features",
               "7. Does the depth side need ControlNet?", ("01_sd_vs_controlnet",)),
    PaperFloat("Table 9", "PnP vs Kabsch: RR threshold ladders (appendix), under depth error", "02_geometric_features",
               "Beside the paper's Table 9", ("02_depth_error_sweep",)),
    PaperFloat("Table 9", "PnP vs Kabsch: RR threshold ladders (appendix)", "04_benchmark",
               "4. Registration recall over threshold ladders", ("04_rr_ladder",)),
)

# The README's gallery: the key figures of the default run.
GALLERY: tuple[str, ...] = ("01_pca_layers", "03_matches_d_g_fused", "04_table1_side_by_side", "04_rr_ladder",
                            "03_table4_fusion_weight", "01_table2_ir")

BACKEND_NOTES = {
    "micro": "Miniature SD-layout models trained in this repository on synthetic rooms: a learned miniature of "
             "the paper's diffusion branch. Its numbers are not the paper's.",
    "stub": "No model: designed features on synthetic scenes. Checks the wiring and the paper's qualitative "
            "effects; its numbers are not the paper's.",
    "tiny": "The real code path with random weights: its numbers mean nothing.",
    "real": "Stable Diffusion v1.5 + ControlNet v1.1 depth + ZoeDepth: the paper's experiment.",
}


@dataclass(frozen=True)
class Heading:
    level: int
    anchor: str   # the id nbconvert gives the heading
    text: str


@dataclass
class Page:
    source: Path            # the executed notebook
    stem: str
    title: str              # its first heading
    backend: str
    failed: bool
    headings: list[Heading]

    @property
    def href(self) -> str:
        return f"{self.stem}.html"


class SiteError(RuntimeError):
    """The run cannot be rendered as the site promises (no notebook, a float without its section)."""


_HEADING = re.compile(r'<h([1-6]) id="([^"]+)"[^>]*>(.*?)<a class="anchor-link"', re.S)


def headings(nb: Any) -> list[Heading]:
    """The headings of a notebook's markdown cells with the ids nbconvert's HTML gives them."""
    from nbconvert.filters import markdown2html_mistune

    found = []
    for cell in nb.cells:
        if cell.cell_type != "markdown" or "#" not in cell.source:
            continue
        for level, anchor, inner in _HEADING.findall(markdown2html_mistune(cell.source)):
            text = html.unescape(re.sub(r"<[^>]+>", "", inner)).strip()
            found.append(Heading(int(level), anchor, text))
    return found


def _parameter_value(nb: Any, name: str) -> Any:
    """``name``'s value in an executed notebook: papermill's injected one, else the parameters cell's."""
    injected = nb.metadata.get("papermill", {}).get("parameters", {})
    if name in injected:
        return injected[name]
    for cell in nb.cells:
        if cell.cell_type == "code" and "parameters" in cell.metadata.get("tags", []):
            for node in ast.parse(cell.source).body:
                target = node.target if isinstance(node, ast.AnnAssign) else (
                    node.targets[0] if isinstance(node, ast.Assign) else None)
                if isinstance(target, ast.Name) and target.id == name and node.value is not None:
                    return ast.literal_eval(node.value)
    return None


def read_pages(run_dir: Path) -> list[Page]:
    """The executed notebooks ``NN_*.ipynb`` of ``run_dir``, in order."""
    import nbformat

    paths = sorted(Path(run_dir).glob("[0-9][0-9]_*.ipynb"))
    if not paths:
        raise SiteError(f"{run_dir}: no executed notebook (NN_*.ipynb); run `make reproduce` first")
    pages = []
    for path in paths:
        nb = nbformat.read(path, as_version=4)
        heads = headings(nb)
        title = next((h.text for h in heads if h.level == 1), path.stem)
        failed = bool(nb.metadata.get("papermill", {}).get("exception"))
        pages.append(Page(path, path.stem, title, str(_parameter_value(nb, "backend")), failed, heads))
    return pages


def write_gallery(figures_dir: Path, out: Path = GALLERY_DIR, names: Sequence[str] = GALLERY,
                  max_width: int = 1000, max_bytes: int = 400_000) -> list[Path]:
    """Compact copies of the gallery's figures of ``figures_dir`` in ``out`` (missing ones are skipped,
    and named on stderr). Returns the files written."""
    written = []
    for name in names:
        src = Path(figures_dir) / f"{name}.png"
        if not src.is_file():
            print(f"gallery: {src} is missing (not drawn in this run); kept the old copy if any", file=sys.stderr)
            continue
        written.append(compact_png(src, Path(out) / f"{name}.png", max_width, max_bytes))
    return written


def _float_rows(pages: list[Page], figures_dir: Path, site: Path) -> list[str]:
    by_stem = {p.stem: p for p in pages}
    rows = []
    for f in PAPER_FLOATS:
        page = by_stem.get(f.notebook)
        if page is None:
            where = f"`{f.notebook}` (not in this run)"
        else:
            head = next((h for h in page.headings if h.text.startswith(f.section)), None)
            if head is None:
                raise SiteError(f"{f.number} ({f.shows}): no heading starting {f.section!r} in {page.source}; "
                                f"its headings: {[h.text for h in page.headings]}")
            where = f"[{f.notebook[:2]} · {head.text}]({page.href}#{head.anchor})"
        thumbs = []
        for stem in f.figures:
            src = figures_dir / f"{stem}.png"
            if page is not None and src.is_file():
                compact_png(src, site / "figures" / f"{stem}.png", max_width=480, max_bytes=150_000)
                thumbs.append(f'<a href="figures/{stem}.png"><img src="figures/{stem}.png" alt="{stem}" width="240"></a>')
            else:
                thumbs.append(f"`{stem}.png` (not drawn in this run)")
        rows.append(f"| {f.number} | {f.shows} | {where} | {' '.join(thumbs)} |")
    return rows


def _index_notebook(pages: list[Page], figures_dir: Path, site: Path, run_dir: Path, refs: Sequence = ()) -> Any:
    import nbformat

    backends = {}
    for p in pages:
        backends.setdefault(p.backend, []).append(p.stem[:2])
    intro = ("# FreeReg companion: the executed notebooks\n\n"
             f"The notebooks of the run `{run_dir.name}`, executed top to bottom with papermill and rendered "
             "with nbconvert (`make book`). Backends of this run: "
             + "; ".join(f"**{b}** (notebooks {', '.join(s)})" for b, s in backends.items()) + ".\n\n"
             + "\n".join(f"- **{b}**: {BACKEND_NOTES.get(b, 'see the README, Backends.')}" for b in backends))
    nb_rows = ["| notebook | backend | sections |", "|---|---|---|"]
    for p in pages:
        secs = ", ".join(f"[{h.text}]({p.href}#{h.anchor})" for h in p.headings if h.level == 2)
        status = " (**failed**: the page shows the error)" if p.failed else ""
        nb_rows.append(f"| [{p.title}]({p.href}){status} | {p.backend} | {secs} |")
    float_rows = ["| paper | what it shows | notebook section | figure of this run |", "|---|---|---|---|"]
    float_rows += _float_rows(pages, figures_dir, site)
    cells = [nbformat.v4.new_markdown_cell(intro),
             nbformat.v4.new_markdown_cell("## The notebooks\n\n" + "\n".join(nb_rows)),
             nbformat.v4.new_markdown_cell(
                 "## The paper's figures and tables re-drawn here\n\n"
                 "Numbers as in the paper (FreeReg, ICLR 2024); each row links to the notebook section that "
                 "re-draws the float, with the figure this run drew (click for a larger copy; the notebook page "
                 "has it at full size).\n\n" + "\n".join(float_rows))]
    docs = [r for r in refs if not r.stem.startswith("api")]
    api = next((r for r in refs if r.stem == "api"), None)
    if docs or api:
        lines = [f"- [{r.title}]({r.href}) (`{r.source}`)" for r in docs]
        if api is not None:
            lines.append(f"- [API reference]({api.href}): one page per module of `freereg_lib`, from its docstrings")
        cells.append(nbformat.v4.new_markdown_cell(
            "## Reference pages\n\nThe pages of `docs/` (the README links them), the benchmarks' results, the "
            "teacher's guide and the model cards, then the API reference.\n\n" + "\n".join(lines)))
    nb = nbformat.v4.new_notebook(cells=cells)
    nb.metadata["title"] = "FreeReg companion"
    return nb


def _export(nb: Any, resources: dict) -> str:
    from nbconvert import HTMLExporter
    from nbconvert.preprocessors import CoalesceStreamsPreprocessor

    exporter = HTMLExporter(template_name=TEMPLATE, extra_template_basedirs=[str(TEMPLATES)])
    # One stream output per cell, a text progress bar's redraws (\r) reduced to its last state.
    exporter.register_preprocessor(CoalesceStreamsPreprocessor, enabled=True)
    body, _ = exporter.from_notebook_node(nb, resources=resources)
    return body


def build_site(run_dir: str | Path, out: str | Path | None = None, figures_dir: str | Path | None = None,
               docs_dir: str | Path | None = None, api: bool = True) -> Path:
    """Render the run's executed notebooks, an index, the docs pages and the API reference into ``out``
    (default ``<run>/site``).

    ``figures_dir``: where the run's notebooks wrote their figures (default ``<run>/figures`` when it
    exists, else the repository's ``figures/``). ``docs_dir``: the markdown pages (default ``docs/``);
    ``api=False`` leaves the API reference out. Returns the index page.
    """
    import nbformat

    run_dir = Path(run_dir).resolve()
    site = Path(out).resolve() if out is not None else run_dir / "site"
    if figures_dir is None:
        figures_dir = run_dir / "figures" if (run_dir / "figures").is_dir() else ROOT / "figures"
    figures_dir = Path(figures_dir)
    pages = read_pages(run_dir)
    if site.exists():
        shutil.rmtree(site)
    site.mkdir(parents=True)
    from freereg_lib.commands import site_docs

    site_docs.WARNINGS.clear()
    docs = site_docs.doc_pages() if docs_dir is None else site_docs.doc_pages(Path(docs_dir))
    site_docs.link_pages(docs, site)
    refs = docs + (site_docs.api_pages() if api else [])
    for warning in site_docs.WARNINGS:
        print(f"site: {warning}", file=sys.stderr)

    def link(page: Page | None) -> dict | None:
        return None if page is None else {"href": page.href, "title": page.title}

    index_nb = _index_notebook(pages, figures_dir, site, run_dir, refs)
    index_site = {"prev": None, "next": link(pages[0]), "toc": [],
                  "backend": ", ".join(dict.fromkeys(p.backend for p in pages)),
                  "backend_note": "Each notebook page names its own; see the list below."}
    (site / "index.html").write_text(_export(index_nb, {"freereg": index_site, "metadata": {"name": "index"}}),
                                     encoding="utf-8")
    for k, page in enumerate(pages):
        nb = nbformat.read(page.source, as_version=4)
        info = {"prev": link(pages[k - 1]) if k > 0 else {"href": "index.html", "title": "Contents"},
                "next": link(pages[k + 1]) if k + 1 < len(pages) else (
                    {"href": refs[0].href, "title": refs[0].title} if refs else None),
                "toc": [h for h in page.headings if h.level in (2, 3)],
                "backend": page.backend, "backend_note": BACKEND_NOTES.get(page.backend, "")}
        body = _export(nb, {"freereg": info, "metadata": {"name": page.title}})
        (site / page.href).write_text(body, encoding="utf-8")
    site_docs.write_pages(refs, site, link(pages[-1]), None)
    return site / "index.html"


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", nargs="?", default="runs/reproduce", help="run folder with the executed notebooks")
    ap.add_argument("--out", default=None, help="site folder (default <run>/site)")
    ap.add_argument("--figures", default=None, help="the run's figures folder (default <run>/figures or figures/)")
    ap.add_argument("--no-api", action="store_true", help="leave the API reference out")
    ap.add_argument("--gallery", action="store_true", help="also rewrite the README's gallery in figures/gallery/")
    args = ap.parse_args(list(argv) if argv is not None else None)
    try:
        index = build_site(args.run, args.out, args.figures, api=not args.no_api)
    except SiteError as exc:
        print(f"site: {exc}", file=sys.stderr)
        return 1
    print(f"Site: {index}")
    if args.gallery:
        figures = Path(args.figures) if args.figures else (Path(args.run) / "figures" if (Path(args.run) / "figures").is_dir()
                                                          else ROOT / "figures")
        for path in write_gallery(figures):
            print(f"Gallery: {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path} "
                  f"({path.stat().st_size // 1024} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
