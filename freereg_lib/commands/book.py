"""The companion as a book: one run's executed notebooks, the pages of ``docs/`` and the API reference.

``python -m freereg_lib.commands.book runs/reproduce`` (``make book``; ``make reproduce`` calls
:func:`build_book` at its end) builds ``<run>/site/index.html`` with Sphinx, myst-nb and
sphinx-book-theme (the Jupyter Book 1 stack; ``book/conf.py`` holds the configuration). The build
needs no network: the notebooks are rendered from their stored outputs (nothing is executed), the
math by the MathJax the pinned package ``django-static-mathjax`` ships, copied into the site, and
the search index is Sphinx's own, with every page's text beside it so that its excerpts work from
``file://`` too (``book/conf.py``). It runs in nitpicky mode with warnings as errors, so a
cross-reference of a docstring that leads nowhere, a link between pages to a missing heading or a
notebook whose section a paper float names is gone fails the build, naming it.

The sources are laid out in ``<run>/book_src`` (the repository's paths, so the pages' relative links
work as on GitHub): ``index.md`` (the notebooks with their backends and :data:`PAPER_FLOATS`, every
paper float the companion re-draws mapped to its notebook section and figure), the executed
notebooks under ``notebooks/`` (each with a first line naming its backend, and this machine's absolute
paths, such as papermill's injected ``out_dir``, shown relative: :func:`machine_paths`), ``docs/``, the
benchmarks' results, the teacher's guide, the model cards, and ``api/``: one page per topic of the
method layers (:data:`API_TOPICS`), made by autodoc from the docstrings.

The site folder is emptied before Sphinx writes it, so the book writes only into a new or empty folder
or one it built (:func:`~freereg_lib.commands.book_inputs.output_fault` refuses the rest, and ``--out``
equal to or above an input, with exit status 2 before anything is staged).
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from freereg_lib.commands.book_inputs import clear_site, exit_on_bad_sources, output_fault
from freereg_lib.data import paper
from freereg_lib.report import prose
from freereg_lib.report.plots import compact_png

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
BOOK_CONF = ROOT / "book"


@dataclass(frozen=True)
class PaperFloat:
    """A float of the paper the companion re-draws: where, and in which figure files."""

    number: str               # "Fig. 4c", "Table 1"
    shows: str                # what it shows, as the paper names it
    notebook: str             # notebook stem
    section: str              # the start of the section's heading text (without the #s)
    figures: tuple[str, ...]  # figure file stems (figures/<stem>.png)
    reason: str = ""          # for a float with no re-run: why, and what would draw it (no notebook then)


def _not_rerun(number: str, shows: str, reason: str) -> PaperFloat:
    return PaperFloat(number, shows, "", "", (), reason)


# Every float of the paper, in the paper's order (its list of floats, freereg_lib/data/paper_floats.csv:
# Figs. 1-10, then Tables 1-13, the appendix's numbered after the main text's): the section that re-draws it,
# or why none does. :func:`unmapped_floats` checks it against the paper's list, :func:`out_of_order` its order.
PAPER_FLOATS: tuple[PaperFloat, ...] = (
    _not_rerun("Fig. 1", "teaser", "a drawing of the idea, no measurement; notebook 00, section 1 states the task"),
    PaperFloat("Fig. 2-I", "images generated from one depth map (the idea, panel I)", "01_diffusion_features",
               "8. A depth map admits many images", ("01_generated_from_depth",)),
    PaperFloat("Fig. 3", "the FreeReg pipeline, drawn from one pair's intermediate outputs", "07_paper_figures",
               "1. The pipeline on one pair", ("07_pipeline_one_pair",)),
    PaperFloat("Fig. 4c", "PCA of decoder features (diffusion feature extraction)", "01_diffusion_features",
               "3. What the layers see", ("01_pca_layers", "01_pca_layers_committed")),
    PaperFloat("Fig. 5 b-d", "fused features: D / G / fused feature maps", "03_fusion", "2. The fusion",
               ("03_features_diffusion", "03_features_geometric", "03_features_fused")),
    PaperFloat("Fig. 5 e-g", "fused features: D / G / fused matches", "03_fusion",
               "3. Correspondences from D, G and fused features", ("03_matches_d_g_fused", "03_matches_d_g_fused_committed")),
    PaperFloat("Fig. 6", "qualitative correspondences on real frames (ICL-NUIM)", "07_paper_figures",
               "4. Successes and failures on real frames", ("07_icl_outcomes",)),
    PaperFloat("Fig. 7", "rotation and translation error curves (appendix)", "04_benchmark",
               "5. Rotation and translation error curves", ("04_rotation_error_curves", "04_translation_error_curves")),
    PaperFloat("Fig. 8", "semantic properties of the features on the cloud (appendix)", "07_paper_figures",
               "2. Features on the cloud", ("07_cloud_features",)),
    PaperFloat("Fig. 9", "additional qualitative results: feature maps and matches (appendix)", "07_paper_figures",
               "4. Successes and failures on real frames", ("07_icl_outcomes",)),
    PaperFloat("Fig. 10", "patch warping: image patches moved by the matches (appendix)", "07_paper_figures",
               "3. Patches warped by the matches", ("07_patch_warp",)),
    PaperFloat("Table 1", "main results, beside the re-run", "04_benchmark", "3. Table 1 beside the paper's",
               ("04_table1_committed", "04_table1_side_by_side")),
    PaperFloat("Table 2", "layer selection", "01_diffusion_features", "5. Which layers?",
               ("01_table2_committed", "01_table2_ir", "01_table2_in")),
    PaperFloat("Table 3", r"diffusion step $\hat t$", "01_diffusion_features", "6. Which diffusion step",
               ("01_table3_t_hat",)),
    PaperFloat("Table 4", "fusion weight w", "03_fusion", "4. The fusion weight", ("03_table4_committed", "03_table4_fusion_weight")),
    PaperFloat("Table 5", "RGBD-Scenes-v2 under 2D3D-MATR's protocol, coarse-to-fine matches (appendix)",
               "06_appendix", "6. The RGBD-Scenes-v2 protocol", ()),
    PaperFloat("Table 6", "other vision backbones (appendix)", "06_appendix",
               "8. Other vision backbones (Table 6)", ("06_table6_other_backbones",)),
    PaperFloat("Table 7", "SD vs ControlNet depth features (appendix)", "01_diffusion_features",
               "7. Does the depth side need ControlNet?", ("01_sd_vs_controlnet",)),
    PaperFloat("Table 8", "layer combinations on the validation scene (appendix)", "06_appendix",
               "4. Layer combinations", ("06_layer_combinations",)),
    PaperFloat("Table 9", "PnP vs Kabsch: RR threshold ladders (appendix), under depth error", "02_geometric_features",
               "Beside the paper's Table 9", ("02_depth_error_sweep",)),
    PaperFloat("Table 9", "PnP vs Kabsch: RR threshold ladders (appendix)", "04_benchmark",
               "4. Registration recall over threshold ladders", ("04_rr_ladder_committed", "04_rr_ladder")),
    PaperFloat("Table 10", "mono-modality registration (appendix)", "06_appendix",
               "5. Mono-modality registration", ("06_table10_mono",)),
    PaperFloat("Table 11", "fine-tuning the ControlNet on sensor-like depth (appendix)", "06_appendix",
               "7. Fine-tuning the ControlNet", ()),
    _not_rerun("Table 12", "2D3D-MATR against fine-tuned FreeReg (appendix)",
               "2D3D-MATR's numbers are its paper's; FreeReg-Ft under Table 5's protocol would need the "
               "fine-tuned micro ControlNet (not committed) run through that protocol, where the micro models "
               "score zero"),
    PaperFloat("Table 13", "DDIM iterations: faster features (appendix)", "06_appendix", "3. The verdict",
               ("06_table13_ddim",)),
)


def float_number(label: str) -> str:
    """The paper's float a row label names, without the panels that follow its number."""
    m = re.match(r"(Fig\.|Table) (\d+)", label)
    if m is None:
        raise ValueError(f"{label!r} names no paper float (expected 'Fig. N...' or 'Table N...')")
    return f"{m.group(1)} {m.group(2)}"


def unmapped_floats(rows: Iterable[PaperFloat] = PAPER_FLOATS) -> list[str]:
    """The paper's floats (``freereg_lib/data/paper_floats.csv``) with neither a section nor a reason
    among ``rows``, and rows naming a float the paper does not have."""
    listed = list(paper.floats()["number"])
    covered = {float_number(f.number) for f in rows if (f.notebook and f.section) or f.reason}
    named = {float_number(f.number) for f in rows}
    return ([f"{n}: no section and no reason" for n in listed if n not in covered]
            + [f"{n}: not a float of the paper" for n in sorted(named - set(listed))])


def out_of_order(rows: Iterable[PaperFloat] = PAPER_FLOATS) -> list[str]:
    """The rows of ``rows`` that come before a float the paper lists earlier (its list:
    ``freereg_lib/data/paper_floats.csv``), as ``"Fig. 7 before Fig. 6"``; [] when in the paper's order."""
    rank = {n: k for k, n in enumerate(paper.floats()["number"])}
    seen: list[str] = []
    out = []
    for f in rows:
        n = float_number(f.number)
        later = [m for m in seen if rank.get(m, -1) > rank.get(n, -1)]
        if later:
            out.append(f"{later[0]} before {n}")
        seen.append(n)
    return out


BACKEND_NOTES = {
    "micro": "Miniature SD-layout models trained in this repository on synthetic rooms: a learned miniature of "
             "the paper's diffusion branch. Its numbers are not the paper's.",
    "stub": "No model: designed features on synthetic scenes. Checks the wiring and the paper's qualitative "
            "effects; its numbers are not the paper's.",
    "tiny": "The real code path with random weights: its numbers mean nothing.",
    "real": "Stable Diffusion v1.5 + ControlNet v1.1 depth + ZoeDepth: the paper's experiment.",
}

# Markdown files of the repository that become pages, beside docs/ (their paths are kept).
EXTRA_PAGES = ("benchmarks/README.md", "assignments/README.md", "freereg_lib/models/micro/weights/MODEL_CARD.md",
               "freereg_lib/models/micro/weights/depth/MODEL_CARD.md")
# The reading order of docs/; a page not named here follows, by name.
DOC_ORDER = ("backends", "micro_models", "world", "reproducibility", "real_data", "your_data", "real_frames", "fidelity", "performance",
             "troubleshooting", "teaching", "contributing", "changelog")

# The API reference: the method layers by topic (tools beside the method are not in it).
API_TOPICS: tuple[tuple[str, str, str, tuple[str, ...]], ...] = (
    ("config", "Configuration", "The paper's settings as one object.", ("freereg_lib.config",)),
    ("cameras", "Cameras, projection and depth maps",
     "Intrinsics and SE(3), a point cloud rendered into a depth map, densification, keypoint grids.",
     ("freereg_lib.geometry", "freereg_lib.geometry.cameras", "freereg_lib.geometry.projection",
      "freereg_lib.geometry.densify", "freereg_lib.geometry.keypoints")),
    ("pose", "Pose solvers and metrics", "Kabsch-RANSAC and PnP-RANSAC; FMR, IR, IN, RR, RE, TE.",
     ("freereg_lib.geometry.pose", "freereg_lib.geometry.metrics")),
    ("data", "Pairs and data sources",
     "What a pair is, the synthetic scenes, the dataset loaders, the paper's tables.",
     ("freereg_lib.data", "freereg_lib.data.pair", "freereg_lib.data.sources", "freereg_lib.data.paper",
      "freereg_lib.data.shards", "freereg_lib.data.synthetic", "freereg_lib.data.synthetic.pairs",
      "freereg_lib.data.synthetic.indoor", "freereg_lib.data.synthetic.rooms", "freereg_lib.data.synthetic.outdoor",
      "freereg_lib.data.synthetic.render",
      "freereg_lib.data.synthetic.seeds", "freereg_lib.data.datasets", "freereg_lib.data.datasets.registry",
      "freereg_lib.data.datasets.common", "freereg_lib.data.datasets.demo", "freereg_lib.data.datasets.icl",
      "freereg_lib.data.datasets.threedmatch", "freereg_lib.data.datasets.scannet", "freereg_lib.data.datasets.kitti",
      "freereg_lib.data.datasets.rgbd_scenes_v2", "freereg_lib.data.datasets.pairlists")),
    ("models", "Backends and models",
     "The backend interface and its four kinds; the diffusion, depth and FCGF models; weights.",
     ("freereg_lib.models", "freereg_lib.models.base", "freereg_lib.models.stub", "freereg_lib.models.torch_backends",
      "freereg_lib.models.diffusion", "freereg_lib.models.zoedepth", "freereg_lib.models.fcgf",
      "freereg_lib.models.micro", "freereg_lib.models.micro.diffusion", "freereg_lib.models.micro.depth",
      "freereg_lib.models.micro.fcgf", "freereg_lib.models.weights", "freereg_lib.models.weightcheck")),
    ("features", "Features and matching",
     "Diffusion descriptors (PCA, sampling, fusion), geometric descriptors, mutual nearest neighbours.",
     ("freereg_lib.features", "freereg_lib.features.descriptors", "freereg_lib.features.geometric",
      "freereg_lib.features.matching", "freereg_lib.features.baseline")),
    ("pipeline", "The pipeline", "FreeReg on one pair and on many; a cloud without its sensor pose registered.",
     ("freereg_lib.pipeline", "freereg_lib.pipeline.steps", "freereg_lib.pipeline.register",
      "freereg_lib.pipeline.verdict")),
)


class BookError(RuntimeError):
    """The run cannot be rendered as the book promises (no notebook, a float without its section, a warning)."""


class BookOutputError(BookError):
    """The book may not write where it was asked to (a folder it did not build, an input, a read-only folder)."""


_MD_IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s#]+)\)")


def _headings(nb: dict) -> list[tuple[int, str]]:
    out = []
    for cell in nb["cells"]:
        if cell["cell_type"] != "markdown":
            continue
        src = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
        for line in src.splitlines():
            m = re.match(r"(#{1,6})\s+(.*?)\s*#*\s*$", line)
            if m:
                out.append((len(m.group(1)), m.group(2)))
    return out


def _parameter(nb: dict, name: str) -> str:
    """``name``'s value in an executed notebook: papermill's injected one, else the parameters cell's."""
    injected = nb.get("metadata", {}).get("papermill", {}).get("parameters", {})
    if name in injected:
        return str(injected[name])
    for cell in nb["cells"]:
        if cell["cell_type"] == "code" and "parameters" in cell.get("metadata", {}).get("tags", []):
            src = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
            m = re.search(rf"^{name}\s*(?::[^=]+)?=\s*['\"]([^'\"]+)['\"]", src, re.M)
            if m:
                return m.group(1)
    return "unknown"


@dataclass
class NotebookPage:
    stem: str
    title: str
    backend: str
    failed: bool
    headings: list[tuple[int, str]]


def _fill_missing_glue(nb: dict, why: str) -> set[str]:
    """Replace, in ``nb``'s Markdown, each glue reference whose name the run did not glue by a visible note
    (a notebook that failed, or was not run, glued nothing after that point; myst-nb would stop the
    build on it). Returns the names replaced."""
    glued = prose.glued_names(nb)
    missing: set[str] = set()

    def note(m: re.Match) -> str:
        name = prose.glue_references(m.group(0))[0]
        if name in glued:
            return m.group(0)
        missing.add(name)
        return f"*(not computed: this run {why})*"

    for cell in nb["cells"]:
        if cell["cell_type"] == "markdown":
            text = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
            cell["source"] = prose.GLUE_ROLE.sub(note, text)
    return missing


def machine_paths(run_dir: Path) -> list[tuple[re.Pattern, str]]:
    """The absolute paths of this machine a page must not show, each with what it shows instead: the run
    folder as the path a reader types in the project folder (``runs/reproduce``; its name when it lies
    elsewhere), the project folder as a relative path, the home folder as ``~``. Longest first, so that
    the run folder inside the project folder is rewritten as a whole."""
    root, run = ROOT.resolve(), Path(run_dir).resolve()
    shown_run = run.relative_to(root).as_posix() if run.is_relative_to(root) else run.name
    places = [(run, shown_run), (Path(run_dir).absolute(), shown_run), (root, "."), (ROOT.absolute(), ".")]
    home = Path.home()
    if len(home.parts) > 1:  # a home of "/" would be every path
        places += [(home.resolve(), "~"), (home.absolute(), "~")]
    out, seen = [], set()
    for path, shown in sorted(places, key=lambda p: -len(str(p[0]))):
        if str(path) not in seen and len(path.parts) > 1:
            seen.add(str(path))
            # "/work/main/runs" -> "runs", "/work/main" -> "."; never a longer name ("/work/mainline")
            out.append((re.compile(re.escape(str(path)) + r"(/|(?![\w.-]))"), shown))
    return out


def _relative_paths(nb: dict, places: list[tuple[re.Pattern, str]]) -> None:
    """Rewrite, in ``nb``'s sources and printed outputs, the machine's absolute paths (:func:`machine_paths`):
    papermill injects ``out_dir`` as an absolute path, and tracebacks and printed file names carry them."""

    def fix(text):
        if isinstance(text, list):
            return [fix(t) for t in text]
        if not isinstance(text, str):
            return text
        for pattern, shown in places:  # "<root>/x" -> "x", "<root>" -> ".", "<run>/x" -> "runs/reproduce/x"
            text = pattern.sub(lambda m: "" if shown == "." and m.group(1) else shown + m.group(1), text)
        return text

    for cell in nb["cells"]:
        cell["source"] = fix(cell["source"])
        if "injected-parameters" in cell.get("metadata", {}).get("tags", []):
            cell["source"] = re.sub(r"^# Parameters\n", "# Parameters injected by papermill (paths shown relative, "
                                    "not as on the machine that ran it)\n", "".join(cell["source"]))
        for out in cell.get("outputs", []):
            for key in ("text", "traceback", "evalue"):
                if key in out:
                    out[key] = fix(out[key])
            for mime, value in out.get("data", {}).items():
                if mime.startswith("text/") or mime in ("application/json", "image/svg+xml"):
                    out["data"][mime] = fix(value)


def stage_notebooks(run_dir: Path, src: Path) -> list[NotebookPage]:
    """Copy the run's executed notebooks into ``src/notebooks``, each with a line naming its backend."""

    paths = sorted(Path(run_dir).glob("[0-9][0-9]_*.ipynb"))
    if not paths:
        raise BookError(f"{run_dir}: no executed notebook (NN_*.ipynb); run `make reproduce` first")
    (src / "notebooks").mkdir(parents=True, exist_ok=True)
    pages, places = [], machine_paths(run_dir)
    for path in paths:
        nb = json.loads(path.read_text(encoding="utf-8"))
        heads = _headings(nb)
        backend = _parameter(nb, "backend")
        failed = bool(nb.get("metadata", {}).get("papermill", {}).get("exception"))
        line = (f"**Backend: {backend}.** {BACKEND_NOTES.get(backend, 'See the README, Backends.')}"
                + (" **This run of the notebook failed**: the page shows the error." if failed else ""))
        missing = _fill_missing_glue(nb, "failed before it" if failed else "did not reach it")
        _relative_paths(nb, places)
        if missing and not failed:
            print(f"{path.name}: no value glued for {', '.join(sorted(missing))}; the page says so", file=sys.stderr)
        cell = {"cell_type": "markdown", "metadata": {"tags": ["freereg-backend"]}, "source": line, "id": "freereg-backend"}
        first = next((k for k, c in enumerate(nb["cells"]) if c["cell_type"] == "markdown"), -1)
        nb["cells"].insert(first + 1, cell)
        (src / "notebooks" / path.name).write_text(json.dumps(nb), encoding="utf-8")
        title = next((t for level, t in heads if level == 1), path.stem)
        pages.append(NotebookPage(path.stem, title, backend, failed, heads))
    return pages


def _float_rows(pages: list[NotebookPage], figures_dir: Path, src: Path) -> list[str]:
    from myst_parser.slugs import github_slugify

    by_stem = {p.stem: p for p in pages}
    rows = []
    for f in PAPER_FLOATS:
        if f.reason:
            rows.append(f"| {f.number} | {f.shows} | not re-run: {f.reason} | |")
            continue
        page = by_stem.get(f.notebook)
        if page is None:
            where = f"`{f.notebook}` (not in this run)"
        else:
            head = next((t for _, t in page.headings if t.startswith(f.section)), None)
            if head is None:
                raise BookError(f"{f.number} ({f.shows}): no heading starting {f.section!r} in "
                                f"{f.notebook}.ipynb; its headings: {[t for _, t in page.headings]}")
            label = head.replace("|", "\\|").replace("[", "").replace("]", "")  # its math stays math: typeset
            slug = github_slugify(re.sub(r"\$[^$]*\$", "", head))  # myst leaves math out of the anchor
            where = f"[{f.notebook[:2]} · {label}](notebooks/{f.notebook}.ipynb#{slug})"
        thumbs = []
        for stem in f.figures:
            fig = figures_dir / f"{stem}.png"
            if page is not None and fig.is_file():
                compact_png(fig, src / "figures" / f"{stem}.png", max_width=480, max_bytes=150_000)
                thumbs.append(f'<img src="figures/{stem}.png" alt="{stem}" width="240">')
            else:
                thumbs.append(f"`{stem}.png` (not drawn in this run)")
        rows.append(f"| {f.number} | {f.shows} | {where} | {' '.join(thumbs)} |")
    return rows


def _doc_paths(docs_dir: Path) -> list[Path]:
    found = {p.stem: p for p in sorted(docs_dir.glob("*.md"))}
    return [found[s] for s in DOC_ORDER if s in found] + [found[s] for s in sorted(found) if s not in DOC_ORDER]


def stage_docs(src: Path, docs_dir: Path) -> list[str]:
    """Copy ``docs/*.md`` and :data:`EXTRA_PAGES` (with the images they show) into ``src``; their documents."""
    docs = []
    for path in _doc_paths(docs_dir) + [ROOT / rel for rel in EXTRA_PAGES if (ROOT / rel).is_file()]:
        rel = path.resolve().relative_to(ROOT.resolve()) if path.resolve().is_relative_to(ROOT.resolve()) else \
            Path("docs") / path.name
        target = src / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        text = path.read_text(encoding="utf-8")
        target.write_text(text, encoding="utf-8")
        for image in _MD_IMAGE.findall(text):
            if "://" not in image and (path.parent / image).is_file():
                (target.parent / image).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(path.parent / image, target.parent / image)
        docs.append(rel.with_suffix("").as_posix())
    return docs


def stage_api(src: Path) -> list[str]:
    """One page per topic of :data:`API_TOPICS` under ``src/api``, each module by ``automodule``."""
    api = src / "api"
    api.mkdir(parents=True, exist_ok=True)
    rows = ["| topic | what it holds | modules |", "|---|---|---|"]
    for slug, title, what, modules in API_TOPICS:
        body = [f"# {title}", "", what, ""]
        for mod in modules:
            package = (ROOT / "freereg_lib").joinpath(*mod.split(".")[1:], "__init__.py").is_file()
            body += [f"## `{mod}`", "", "```{eval-rst}", f".. automodule:: {mod}", "   :members:",
                     *(["   :ignore-module-all:"] if package else []),
                     "   :show-inheritance:", "```", ""]
        (api / f"{slug}.md").write_text("\n".join(body), encoding="utf-8")
        rows.append(f"| [{title}]({slug}.md) | {what} | {', '.join(f'`{m}`' for m in modules if m.count('.') >= 1)} |")
    toc = "\n".join(f"{slug}" for slug, *_ in API_TOPICS)
    (api / "index.md").write_text(
        "# API reference\n\nThe method, layer by layer from the bottom (`config` -> `geometry` -> `data` -> "
        "`models` -> `features` -> `pipeline`), grouped by topic; made from the docstrings, which state the "
        "arrays' shapes. The tools beside the method (`report`, `commands`, `training`, `teaching`) are not "
        "part of it.\n\n" + "\n".join(rows) + f"\n\n```{{toctree}}\n:hidden:\n\n{toc}\n```\n", encoding="utf-8")
    return ["api/index"]


def write_index(src: Path, pages: list[NotebookPage], figures_dir: Path, docs: list[str], run_dir: Path) -> None:
    backends: dict[str, list[str]] = {}
    for p in pages:
        backends.setdefault(p.backend, []).append(p.stem[:2])
    nb_rows = ["| notebook | backend |", "|---|---|"]
    for p in pages:
        status = " (**failed**: the page shows the error)" if p.failed else ""
        nb_rows.append(f"| [{p.title.replace('|', '/')}](notebooks/{p.stem}.ipynb){status} | {p.backend} |")
    unmapped = unmapped_floats()
    if unmapped:
        raise BookError("the index of the paper's floats is incomplete: " + "; ".join(unmapped))
    if out_of_order():
        raise BookError("the index of the paper's floats is not in the paper's order: " + "; ".join(out_of_order()))
    float_rows = ["| paper | what it shows | notebook section | figure of this run |", "|---|---|---|---|"]
    float_rows += _float_rows(pages, figures_dir, src)
    redrawn = sorted({float_number(f.number) for f in PAPER_FLOATS if not f.reason})
    text = "\n".join([
        "# FreeReg companion", "",
        f"The notebooks of the run `{run_dir.name}`, executed top to bottom with papermill, the reference pages "
        "and the API reference of the method. Backends of this run: "
        + "; ".join(f"**{b}** (notebooks {', '.join(s)})" for b, s in backends.items()) + ".", "",
        *[f"- **{b}**: {BACKEND_NOTES.get(b, 'see the README, Backends.')}" for b in backends], "",
        "## The paper's figures and tables", "",
        f"Numbers as in the paper (FreeReg, ICLR 2024, with its appendix). {len(redrawn)} of its "
        f"{len(paper.floats())} floats are re-drawn: each such row links to the notebook section that re-draws "
        "it, with the figure this run drew (the notebook page has it at full size); the other rows say why "
        "there is no re-run and what would draw it.", "",
        *float_rows, "",
        "## The notebooks", "", *nb_rows, "",
        "```{toctree}", ":caption: Notebooks", ":maxdepth: 1", "", *[f"notebooks/{p.stem}" for p in pages], "```", "",
        "```{toctree}", ":caption: Reference", ":maxdepth: 1", "", *docs, "```", "",
        "```{toctree}", ":caption: API", ":maxdepth: 2", "", "api/index", "```", ""])
    (src / "index.md").write_text(text, encoding="utf-8")


def build_book(run_dir: str | Path, out: str | Path | None = None, figures_dir: str | Path | None = None,
               docs_dir: str | Path | None = None, conf_dir: str | Path | None = None) -> Path:
    """Build the book of ``run_dir`` into ``out`` (default ``<run>/site``); returns its index page.

    ``figures_dir``: where the run's notebooks wrote their figures (default ``<run>/figures`` when it
    exists, else the repository's ``figures/``). Raises :class:`BookError` with Sphinx's warnings
    when the build has any (a broken cross-reference among them).
    """
    run_dir = Path(run_dir).resolve()
    conf = Path(conf_dir) if conf_dir is not None else BOOK_CONF
    if not (conf / "conf.py").is_file():
        raise BookError(f"{conf / 'conf.py'} is missing: run the command in the project folder (where book/ is)")
    site = Path(out).resolve() if out is not None else run_dir / "site"
    figures_dir = Path(figures_dir) if figures_dir is not None else (
        run_dir / "figures" if (run_dir / "figures").is_dir() else ROOT / "figures")
    inputs = [conf, Path(docs_dir) if docs_dir is not None else ROOT / "docs", ROOT]
    fault = output_fault(run_dir, site, figures_dir, inputs, [stem for f in PAPER_FLOATS for stem in f.figures])
    if fault:  # before anything is staged: the book never deletes a folder it did not build
        raise BookOutputError(fault)
    src = run_dir / "book_src"
    if src.exists():
        shutil.rmtree(src)
    src.mkdir(parents=True)
    pages = stage_notebooks(run_dir, src)
    docs = stage_docs(src, Path(docs_dir) if docs_dir is not None else ROOT / "docs")
    stage_api(src)
    write_index(src, pages, figures_dir, docs, run_dir)
    clear_site(site)
    cmd = [sys.executable, "-m", "sphinx", "-b", "html", "-q", "-n", "-W", "--keep-going", "-c", str(conf),
           "-d", str(run_dir / "book_doctrees"), str(src), str(site)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise BookError("the book's build failed (warnings are errors):\n" + (proc.stderr or proc.stdout)[-6000:])
    return site / "index.html"


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", nargs="?", default="runs/reproduce", help="run folder with the executed notebooks")
    ap.add_argument("--out", default=None, help="site folder (default <run>/site)")
    ap.add_argument("--figures", default=None, help="the run's figures folder (default <run>/figures or figures/)")
    args = ap.parse_args(list(argv) if argv is not None else None)
    exit_on_bad_sources(args.run, ROOT / "docs", [ROOT / rel for rel in EXTRA_PAGES])  # one line, exit 2
    try:
        index = build_book(args.run, args.out, args.figures)
    except BookError as exc:
        print(f"book: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, BookOutputError) else 1
    print(f"Site: {index}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
