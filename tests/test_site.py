"""The book (``make book``): Sphinx + myst-nb + sphinx-book-theme, built offline from a small run and
opened in headless Chromium without a network.

The small run: the notebooks copied unexecuted into a run folder, notebook 00 given outputs made here
(a figure, a wide table, a progress bar on stderr, a verdict line far wider than the page, this
machine's paths as papermill's injected ``out_dir`` and printed file names) so the test needs no
kernel and stays under a minute. ``python -m freereg_lib.commands.book`` builds it, and:

* the index maps every paper float, in the paper's order, to a notebook section whose heading names
  the float (a link to an id of that page) and names its figure; no link or image of any page leads
  nowhere, none leaves the site, none needs a network;
* every notebook page names its backend; stderr is not on the page; no page shows an absolute path
  of this machine (the run folder, the repository, the home folder);
* a cross-reference of a docstring is a link to the object's entry; a broken one fails the build;
* in Chromium (the Debian package; skipped when there is none): the math of notebook 00 and of the
  float index is typeset by the site's own MathJax (no raw ``$`` or ``\\hat`` in the text), the
  search box finds "Kabsch" and, opened from ``file://`` as a reader opens it, shows excerpts, a
  sidebar links the pages, no image is broken, wide tables scroll, on every notebook page no printed
  line is wider than its box, and the docstring's cross-reference is a link whose target is on the
  page it opens (``FREEREG_BOOK_RUN=runs/reproduce`` runs these checks on a real run's book too);
* the README's gallery: every figure it shows is in the repository, and small.
"""
from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

pytest.importorskip("sphinx")
pytest.importorskip("myst_nb")

from freereg_lib.commands import book as B  # noqa: E402
from freereg_lib.commands.gallery import GALLERY  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
STDERR_MARK = "progress-on-stderr 50%|#####"
LONG_LINE = ("Table 5, RGBD-Scenes-v2, 0.10 m: Kabsch RR 15.0 % [9.1, 23.6] vs PnP 8.5 % [4.1, 15.9], n = 120 pairs, "
             "p = 0.037, paired sign test; " * 4 + "verdict: VERDICT_AT_THE_END")


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs: list[tuple[str, str]] = []  # (tag, href or src)
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(a["id"])
        for key in ("href", "src"):
            if a.get(key) and not (tag == "link" and a.get("rel") in ("canonical",)):
                self.refs.append((tag, a[key]))


_PARSED: dict = {}


def _parse(path: Path) -> _Links:
    if path not in _PARSED:
        p = _Links()
        p.feed(path.read_text(encoding="utf-8"))
        _PARSED[path] = p
    return _PARSED[path]


def _png() -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1, 2], [0, 1, 4])
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("small") / "run"
    run.mkdir()
    for nb in sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb")):
        shutil.copy(nb, run / nb.name)
    nb = json.loads((run / "00_preliminaries.ipynb").read_text(encoding="utf-8"))
    nb.setdefault("metadata", {})["papermill"] = {"parameters": {"backend": "stub", "n_pairs": 1}}
    wide = "<table><tr>" + "".join(f"<th>column_{k}_with_a_long_name</th>" for k in range(40)) + "</tr><tr>" + \
        "".join(f"<td>{k}.000</td>" for k in range(40)) + "</tr></table>"
    code = next(c for c in nb["cells"] if c["cell_type"] == "code" and "parameters" not in c["metadata"].get("tags", []))
    code["outputs"] = [
        {"output_type": "stream", "name": "stderr", "text": STDERR_MARK + "\n"},
        {"output_type": "display_data", "metadata": {}, "data": {"image/png": _png(), "text/plain": "<Figure>"}},
        {"output_type": "display_data", "metadata": {}, "data": {"text/html": wide, "text/plain": "table"}},
        # A verdict line far wider than the page, with its verdict word at the end; a long unbroken token;
        # the machine's paths as a notebook prints them (papermill's out_dir, a figure, a cache).
        {"output_type": "stream", "name": "stdout", "text": LONG_LINE + "\n" + "f" * 400 + "\n"
         + f"wrote {run}/00_preliminaries/table.csv, {ROOT}/figures/00_probe.png, cache {Path.home()}/.cache/x\n"},
        {"output_type": "execute_result", "execution_count": 1, "metadata": {},
         "data": {"text/plain": "    " + "   ".join(f"column_{k}" for k in range(60))}},
    ]
    params = next(k for k, c in enumerate(nb["cells"]) if "parameters" in c["metadata"].get("tags", []))
    nb["cells"].insert(params + 1, {  # as papermill injects it
        "cell_type": "code", "execution_count": None, "id": "injected", "outputs": [],
        "metadata": {"tags": ["injected-parameters"]},
        "source": f'# Parameters\nbackend = "stub"\nout_dir = "{run}/00_preliminaries"\n'})
    (run / "00_preliminaries.ipynb").write_text(json.dumps(nb), encoding="utf-8")
    return run


@pytest.fixture(scope="module")
def site(run) -> Path:
    proc = subprocess.run([sys.executable, "-m", "freereg_lib.commands.book", str(run), "--out", str(run / "site")],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert f"Site: {run / 'site' / 'index.html'}" in proc.stdout
    return run / "site"


def _check_refs(page: Path, site: Path) -> list[str]:
    problems = []
    for tag, ref in _parse(page).refs:
        url = urlparse(ref)
        if url.scheme in ("http", "https") or ref.startswith("//"):
            if tag in ("script", "link", "img", "iframe"):
                problems.append(f"{page.name}: <{tag}> {ref} needs a network")
            continue
        if url.scheme in ("data", "mailto", "javascript"):
            continue
        target = page if not url.path else (page.parent / unquote(url.path)).resolve()
        if target.is_dir():
            target = target / "index.html"
        if not target.is_file():
            problems.append(f"{page.relative_to(site)}: <{tag}> {ref} -> {target} does not exist")
        elif not target.resolve().is_relative_to(site.resolve()):
            problems.append(f"{page.relative_to(site)}: <{tag}> {ref} leaves the site folder")
        elif url.fragment and target.suffix == ".html" and not {url.fragment, unquote(url.fragment)} & _parse(target).ids:
            problems.append(f"{page.relative_to(site)}: <{tag}> {ref}: no id {unquote(url.fragment)!r} in {target.name}")
    return problems


def test_the_index_maps_every_paper_float_to_its_section(site):
    text = (site / "index.html").read_text(encoding="utf-8")
    for f in B.PAPER_FLOATS:
        assert f"<td><p>{f.number}</p></td>" in text, f"{f.number} is not in the index's float table"
        assert all(f"{stem}.png" in text for stem in f.figures), f.number  # named: this small run drew none
    links = [r for t, r in _parse(site / "index.html").refs if t == "a" and "notebooks/" in r and "#" in r]
    assert len(links) >= sum(not f.reason for f in B.PAPER_FLOATS), links
    assert "not re-run: " in text and "of its 23 floats are re-drawn" in text
    assert any(r.startswith("notebooks/03_fusion.html#") and "correspondences" in r for r in links), links
    assert not _check_refs(site / "index.html", site)


def test_no_page_has_a_dead_link_or_needs_a_network(site):
    pages = sorted(p for p in site.rglob("*.html") if "_static" not in p.relative_to(site).parts)  # (theme macros)
    assert len(pages) >= 25, len(pages)
    problems = [p for page in pages for p in _check_refs(page, site)]
    assert not problems, "\n".join(problems[:30])
    probe = site / "zz_probe.html"  # the check sees a dead link, a missing id and a CDN script
    probe.write_text('<a href="nowhere.html">x</a><a href="index.html#no-such-id">y</a>'
                     '<script src="https://cdn.example.org/mathjax.js"></script><a href="index.html">ok</a>')
    try:
        assert len(_check_refs(probe, site)) == 3
    finally:
        probe.unlink()
    assert (site / "_static" / "mathjax" / "tex-mml-chtml.js").is_file()


def test_every_notebook_page_names_its_backend_and_hides_stderr(site, run):
    for nb in sorted(run.glob("[0-9][0-9]_*.ipynb")):
        text = (site / "notebooks" / f"{nb.stem}.html").read_text(encoding="utf-8")
        assert re.search(r"<strong>Backend: \w+\.</strong>", text), f"{nb.stem}: no backend named"
    zero = (site / "notebooks" / "00_preliminaries.html").read_text(encoding="utf-8")
    assert "<strong>Backend: stub.</strong>" in zero
    assert "<strong>Backend: micro.</strong>" in (site / "notebooks" / "01_diffusion_features.html").read_text("utf-8")
    assert STDERR_MARK.split("|")[0] not in zero and "column_39_with_a_long_name" in zero


def test_no_page_shows_a_path_of_this_machine(site, run):
    """papermill injects ``out_dir`` as an absolute path, and notebooks print file names: the book shows them
    relative (the run folder by its name here, as this run lies outside the repository)."""
    paths = _machine_paths(run)
    files = [p for p in site.rglob("*.html") if "_static" not in p.relative_to(site).parts]
    files.append(site / "_static" / "freereg_page_texts.js")  # the search excerpts' text
    hits = [f"{f.relative_to(site)}: {p}" for f in files for p in paths
            if re.search(re.escape(p) + ("" if p.endswith("/") else r"(?![\w.-])"), f.read_text(encoding="utf-8"))]
    assert not hits, "\n".join(hits[:20])
    import html

    zero = html.unescape(re.sub(r"<[^>]+>", "", (site / "notebooks" / "00_preliminaries.html").read_text("utf-8")))
    assert f'out_dir = "{run.name}/00_preliminaries"' in zero, "papermill's out_dir, relative"
    assert "figures/00_probe.png" in zero and "~/.cache/x" in zero and "Parameters injected by papermill" in zero


def test_the_api_reference_is_the_method_by_topic_with_linked_cross_references(site):
    api = site / "api"
    assert {f"{slug}.html" for slug, *_ in B.API_TOPICS} <= {p.name for p in api.glob("*.html")}
    pose = (api / "pose.html").read_text(encoding="utf-8")
    assert 'id="freereg_lib.geometry.pose.kabsch_ransac"' in pose
    assert "(N, 3)" in re.sub(r"<[^>]+>", "", pose), "the docstrings' shapes"
    # The module docstring's :class:`PoseResult` is a link to the class's entry.
    assert re.search(r'<a class="reference internal" href="#freereg_lib\.geometry\.pose\.PoseResult"[^>]*>'
                     r'<code class="xref py py-class', pose), "the docstring's :class: is not a link"
    every = " ".join(p.read_text(encoding="utf-8") for p in api.glob("*.html"))
    for tool in ("freereg_lib.teaching", "freereg_lib.training", "freereg_lib.commands.book", "freereg_lib.report.plots"):
        assert f'id="{tool}' not in every, f"{tool} is in the API reference"


def test_a_broken_cross_reference_fails_the_build(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    (tmp_path / "probe_mod.py").write_text('"""A probe: :func:`official_projection` names no function."""\n')
    (src / "index.md").write_text("# Probe\n\n```{eval-rst}\n.. automodule:: probe_mod\n```\n")
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-b", "html", "-q", "-n", "-W", "-c", str(ROOT / "book"),
                           str(src), str(tmp_path / "out")], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode != 0 and "official_projection" in proc.stderr, proc.stderr[-2000:]


def test_a_float_whose_section_is_gone_fails_naming_it(tmp_path):
    nb = json.loads((NOTEBOOKS / "03_fusion.ipynb").read_text(encoding="utf-8"))
    for cell in nb["cells"]:
        src = "".join(cell["source"])
        if cell["cell_type"] == "markdown" and src.startswith("## 3. Correspondences"):
            cell["source"] = src.replace("## 3. Correspondences", "## 3. Matches", 1)
    (tmp_path / "03_fusion.ipynb").write_text(json.dumps(nb), encoding="utf-8")
    src = tmp_path / "src"
    pages = B.stage_notebooks(tmp_path, src)
    with pytest.raises(B.BookError, match=r"Fig\. 5 e-g .*no heading starting '3\. Correspondences"):
        B.write_index(src, pages, tmp_path, [], tmp_path)


def test_the_command_on_a_folder_without_notebooks_says_so(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "freereg_lib.commands.book", str(tmp_path)], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 1 and "no executed notebook" in proc.stderr and "Traceback" not in proc.stderr


# --------------------------------------------------------------------------------------
# In Chromium, offline.

_PROBE = """<!DOCTYPE html><html><body><pre id="result">pending</pre><script>
const pages = %s; const machinePaths = %s; const out = {}; let left = pages.length;
function report(page, r) { out[page] = r; if (--left === 0) document.getElementById("result").textContent = JSON.stringify(out); }
function look(f, page, tries) {
  const d = f.contentDocument, w = f.contentWindow;
  const mathPending = d.querySelector(".math") && !d.querySelector("mjx-container");
  const found = d.querySelectorAll("#search-results li, ul.search li").length;
  const finished = /finished/i.test((d.querySelector(".search-summary") || {}).textContent || "");
  const excerpted = d.querySelectorAll("#search-results li p.context, ul.search li p.context").length;
  const searchPending = page.includes("search.html") && !(finished && excerpted >= Math.min(3, found));
  if ((mathPending || searchPending) && tries > 0) { setTimeout(() => look(f, page, tries - 1), 250); return; }
  const imgs = Array.from(d.images);
  const tables = Array.from(d.querySelectorAll("article table"));
  const scrolls = el => { for (let e = el, k = 0; e && k < 4; e = e.parentElement, k++) {
      if (["auto", "scroll"].includes(w.getComputedStyle(e).overflowX)) return true; } return false; };
  // Every printed line whole: an output's text wraps inside its box (no scroll bar, nothing past the article).
  const article = d.querySelector("article") || d.body, right = article.getBoundingClientRect().right + 1;
  const pres = Array.from(d.querySelectorAll("div.cell_output pre"));
  const cut = pres.filter(p => p.scrollWidth > p.clientWidth + 1 || p.getBoundingClientRect().right > right);
  const outputs = Array.from(d.querySelectorAll("div.cell_output"));
  const past = outputs.filter(o => o.scrollWidth > o.clientWidth + 1 || o.getBoundingClientRect().right > right);
  const text = d.body.innerText;
  const xref = d.querySelector("a.reference.internal code.xref");
  const a = xref ? xref.closest("a") : null;
  report(page, {
    images: imgs.length, broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.getAttribute("src")),
    text_dollars: (d.querySelector("article") || d.body).innerText.split("$").length - 1,
    mjx: d.querySelectorAll("mjx-container").length,
    sidebar_links: d.querySelectorAll("nav.bd-docs-nav a, .bd-sidebar-primary nav a").length,
    search_box: !!d.querySelector("form[action*='search'] input[name='q'], input[name='q']"),
    results: Array.from(d.querySelectorAll("#search-results li a, ul.search li a")).map(x => x.textContent).slice(0, 40),
    excerpts: Array.from(d.querySelectorAll("#search-results li p.context, ul.search li p.context")).map(x => x.textContent).slice(0, 40),
    printed_lines: pres.reduce((n, p) => n + p.textContent.split("\\n").filter(l => l.trim()).length, 0),
    cut_lines: cut.map(p => p.textContent.slice(0, 80)), outputs: outputs.length, outputs_past: past.length,
    machine_paths: machinePaths.filter(m => text.split(m).slice(1).some(rest => m.endsWith("/") || !/^[A-Za-z0-9_.-]/.test(rest))),
    raw_tex: ["hat", "mathbf", "frac"].reduce((n, word) => n + text.split(String.fromCharCode(92) + word).length - 1, 0),
    tables: tables.length, unscrolled: tables.filter(t => !scrolls(t)).length,
    xref_target: a ? (a.hash && d.getElementById(decodeURIComponent(a.hash.slice(1))) ? "found" : a.href) : null,
  });
}
for (const page of pages) {
  const f = document.createElement("iframe"); f.style.width = "1200px"; f.style.height = "900px";
  f.onload = () => { try { look(f, page, 120); } catch (e) { report(page, {error: String(e)}); } };
  f.src = page; document.body.appendChild(f);
}
</script></body></html>"""


def _search_excerpts(site: Path, query: str) -> list[str]:
    """The excerpts of the search page for ``query``, opened from disk as a reader opens it: without
    ``--allow-file-access-from-files`` (with it Chromium lets fetch() read file:// URLs, which a reader's
    browser refuses: the probe above needs it to look into its frames)."""
    url = (site / "search.html").as_uri() + f"?q={query}"
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--proxy-server=127.0.0.1:9",
                           "--virtual-time-budget=20000", "--dump-dom", url], capture_output=True, text=True, timeout=120)
    assert "Search finished" in proc.stdout, f"the search did not finish (rc {proc.returncode}): {proc.stderr[-1500:]}"
    import html

    return [html.unescape(re.sub(r"<[^>]+>", "", x)) for x in re.findall(r'<p class="context">(.*?)</p>', proc.stdout, re.S)]


def _machine_paths(run: Path) -> list[str]:
    """The absolute paths of this machine no page may show: the run folder and the repository (as a whole
    name: not "/work/mainline"), and any path inside the home folder (with its "/": a page may say "a Python
    under /root" where the home folder is /root)."""
    paths = {str(p) for q in (run, ROOT) for p in (q, q.resolve())}
    paths |= {f"{h}/" for h in {str(Path.home()), str(Path.home().resolve())}}
    return sorted(p for p in paths if len(Path(p).parts) > 1)


def _browser(pages: list[str], site: Path, machine_paths: list[str] = ()) -> dict:
    probe = site / "browser_probe.html"
    probe.write_text(_PROBE % (json.dumps(pages), json.dumps(list(machine_paths))))
    try:
        proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
                               "--proxy-server=127.0.0.1:9", "--virtual-time-budget=60000", "--dump-dom", probe.as_uri()],
                              capture_output=True, text=True, timeout=240)
    finally:
        probe.unlink()
    m = re.search(r'<pre id="result">(.*?)</pre>', proc.stdout, re.S)
    assert m and m.group(1) != "pending", f"Chromium gave no result (rc {proc.returncode}): {proc.stderr[-1500:]}"
    import html

    return json.loads(html.unescape(m.group(1)))


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary on PATH (Debian: apt-get install chromium; "
                                             "environment/setup_env.sh --browser installs it when run as root)")
def test_in_chromium_offline_math_search_sidebar_images_tables_and_a_linked_reference(site, run):
    notebooks = [f"notebooks/{p.stem}.html" for p in sorted(run.glob("[0-9][0-9]_*.ipynb"))]
    pages = ["notebooks/00_preliminaries.html", "search.html?q=Kabsch", "api/pose.html", "docs/troubleshooting.html",
             "freereg_lib/models/micro/weights/MODEL_CARD.html", "index.html", *notebooks[1:]]
    r = _browser(pages, site, _machine_paths(run))
    zero, search, pose, index = r[pages[0]], r[pages[1]], r[pages[2]], r["index.html"]
    assert "error" not in zero, zero
    assert zero["mjx"] >= 20 and zero["text_dollars"] == 0, f"math not typeset in notebook 00: {zero}"
    assert zero["images"] >= 1 and not zero["broken"], zero
    assert search["results"] and any("Kabsch" in t or "pose" in t.lower() for t in search["results"]), search
    assert search["search_box"], search
    # The float index: its math typeset (Table 3's t-hat), none of it raw.
    assert index["raw_tex"] == 0 and index["mjx"] >= 1, index
    for page in pages:
        assert "error" not in r[page], (page, r[page])
        assert r[page]["sidebar_links"] >= 10, f"{page}: no sidebar ({r[page]})"
        assert not r[page]["broken"], f"{page}: broken images {r[page]['broken']}"
        assert r[page]["unscrolled"] == 0, f"{page}: {r[page]['unscrolled']} of {r[page]['tables']} tables do not scroll"
        assert not r[page]["machine_paths"], f"{page} shows this machine's paths {r[page]['machine_paths']}"
    # Every printed line whole on every notebook page: no output wider than its box.
    assert len(notebooks) == 8 and zero["printed_lines"] >= 4, zero
    for page in notebooks:
        assert not r[page]["cut_lines"] and r[page]["outputs_past"] == 0, \
            f"{page}: printed lines wider than their box: {r[page]['cut_lines']} ({r[page]['outputs_past']} outputs)"
    assert r["docs/troubleshooting.html"]["tables"] >= 1 and zero["tables"] >= 1
    assert r["freereg_lib/models/micro/weights/MODEL_CARD.html"]["images"] >= 1  # the loss curves
    assert pose["xref_target"] == "found", pose


BUILT_RUN = os.environ.get("FREEREG_BOOK_RUN")  # a run folder whose book is built, e.g. runs/reproduce


@pytest.mark.skipif(CHROMIUM is None or not BUILT_RUN, reason="set FREEREG_BOOK_RUN=<run folder> (e.g. runs/reproduce, "
                                                             "after `make reproduce`) to check that run's book")
def test_in_chromium_the_book_of_a_built_run_shows_every_line_and_no_machine_path():
    """The checks above on the book of a real run (opt-in: it needs `make reproduce` first)."""
    run = (ROOT / BUILT_RUN).resolve()
    site = run / "site"
    notebooks = [f"notebooks/{p.stem}.html" for p in sorted(run.glob("[0-9][0-9]_*.ipynb"))]
    assert notebooks and (site / "index.html").is_file(), f"{run}: no executed notebooks or no site/index.html"
    r = _browser([*notebooks, "index.html"], site, _machine_paths(run))
    for page in notebooks:
        assert not r[page]["cut_lines"] and r[page]["outputs_past"] == 0, (page, r[page]["cut_lines"])
        assert not r[page]["machine_paths"] and r[page]["unscrolled"] == 0, (page, r[page])
    assert r["index.html"]["raw_tex"] == 0 and not r["index.html"]["machine_paths"], r["index.html"]
    assert sum("kabsch" in t.lower() for t in _search_excerpts(site, "Kabsch")) >= 3


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary on PATH")
def test_in_chromium_search_results_have_excerpts_from_file(site):
    excerpts = _search_excerpts(site, "Kabsch")
    assert sum("kabsch" in t.lower() for t in excerpts) >= 3, f"no search excerpts offline: {excerpts[:5]}"


# --------------------------------------------------------------------------------------
# The README's gallery and front door.

README_IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)|<img [^>]*src=\"([^\"]+)\"")


def test_every_figure_the_readme_shows_is_in_the_repository_and_small():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    shown = [a or b for a, b in README_IMAGE.findall(text)]
    local = [s for s in shown if not s.startswith(("http://", "https://"))]
    assert len(local) >= 4, f"the README's gallery shows {local}"
    tracked = set(subprocess.run(["git", "ls-files", "figures"], cwd=ROOT, capture_output=True, text=True).stdout.split())
    total = 0
    for src in local:
        path = ROOT / src
        assert path.is_file(), f"README shows {src}, which does not exist"
        if tracked:  # in a git checkout the figure must be committed, not a leftover of a local run
            assert src in tracked, f"README shows {src}, which is not committed"
        size = path.stat().st_size
        assert size <= 420_000, f"{src} is {size // 1024} KB (the gallery keeps each under ~400 KB)"
        total += size
    assert total <= 3_000_000, f"the gallery is {total / 1e6:.1f} MB (at most 3 MB)"
    for name in GALLERY:
        assert f"figures/gallery/{name}.png" in local, f"the README does not show the gallery's {name}"


def test_the_readme_is_a_front_door_whose_links_lead_somewhere():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300, "the README is a front door: move reference material to docs/"
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    local = [unquote(urlparse(l).path) for l in links if not urlparse(l).scheme and urlparse(l).path]
    assert any(l.startswith("docs/") for l in local), local
    missing = [l for l in local if not (ROOT / l).exists()]
    assert not missing, f"README links to {missing}, which do not exist"
    for md in (ROOT / "docs").glob("*.md"):
        assert f"docs/{md.name}" in text, f"the README does not link docs/{md.name}"


def test_compact_png_fits_the_limits(tmp_path):
    import numpy as np
    from PIL import Image

    from freereg_lib.report.plots import compact_png

    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (900, 2400, 3), dtype=np.uint8)).save(tmp_path / "noise.png")
    out = compact_png(tmp_path / "noise.png", tmp_path / "small.png", max_width=1000, max_bytes=400_000)
    with Image.open(out) as im:
        assert im.width <= 1000
    assert out.stat().st_size <= 400_000


def test_every_float_of_the_paper_has_a_section_or_a_reason():
    from freereg_lib.data import paper

    listed = paper.floats()
    assert len(listed) == 23 and listed["kind"].value_counts().to_dict() == {"table": 13, "figure": 10}
    assert B.unmapped_floats() == []
    without_fig10 = [f for f in B.PAPER_FLOATS if B.float_number(f.number) != "Fig. 10"]
    assert B.unmapped_floats(without_fig10) == ["Fig. 10: no section and no reason"]
    no_reason = B.PaperFloat("Table 5", "RGBD-Scenes-v2", "", "", ())
    rows = [f for f in B.PAPER_FLOATS if B.float_number(f.number) != "Table 5"] + [no_reason]
    assert B.unmapped_floats(rows) == ["Table 5: no section and no reason"]
    extra = B.PaperFloat("Table 14", "a table the paper lacks", "06_appendix", "1.", ())
    assert B.unmapped_floats([*B.PAPER_FLOATS, extra]) == ["Table 14: not a float of the paper"]
    assert B.float_number("Fig. 5 b-d") == "Fig. 5" and B.float_number("Fig. 2-I") == "Fig. 2"


def _names_float(heading: str, number: str) -> bool:
    """Whether a heading names the paper's float ``number`` ("Table 13", "Fig. 7"; "Figs. 6 and 9" names both)."""
    kind, n = B.float_number(number).split(" ")
    return re.search(rf"\b{kind.rstrip('.')}s?\.? [^()]*?\b{n}(?!\d)", heading) is not None


def test_the_float_index_is_in_the_papers_order_and_lands_on_headings_that_name_the_float():
    assert B.out_of_order() == []
    fig7 = next(f for f in B.PAPER_FLOATS if f.number == "Fig. 7")
    rows = [f for f in B.PAPER_FLOATS if f is not fig7]
    rows.insert(next(k for k, f in enumerate(rows) if f.number == "Fig. 5 e-g"), fig7)  # where it was
    assert B.out_of_order(rows) == ["Fig. 7 before Fig. 5", "Fig. 7 before Fig. 6"]
    assert _names_float("4. Successes and failures on real frames (Figs. 6 and 9)", "Fig. 9")
    assert not _names_float("3. The verdict, from the committed test split", "Table 13")
    assert not _names_float("3. Table 1 beside the paper's", "Table 13") and not _names_float("Table 13", "Table 1")
    unnamed = []
    for f in B.PAPER_FLOATS:
        if f.reason:
            continue
        heads = B._headings(json.loads((NOTEBOOKS / f"{f.notebook}.ipynb").read_text(encoding="utf-8")))
        head = next(t for _, t in heads if t.startswith(f.section))
        if not _names_float(head, f.number):
            unnamed.append(f"{f.number}: {f.notebook} '{head}'")
    assert not unnamed, f"the float index links to headings that do not name the float: {unnamed}"


def test_every_module_of_the_method_layers_is_in_the_api_reference():
    """A new module of the method (config, geometry, data, models, features, pipeline) gets a topic of
    ``API_TOPICS``: else its page is missing, and a docstring's ``:mod:`` naming it fails the book's build."""
    listed = {m for *_, modules in B.API_TOPICS for m in modules}
    found = {"freereg_lib.config"}
    for layer in ("geometry", "data", "models", "features", "pipeline"):
        for path in (ROOT / "freereg_lib" / layer).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    assert not found - listed, f"modules missing from book.API_TOPICS: {sorted(found - listed)}"
    assert not listed - found, f"API_TOPICS names modules that do not exist: {sorted(listed - found)}"
