"""The rendered companion (issue 17, items 1-3): the site built from a short run, opened in a browser.

A short run: notebook 00 executed with papermill (stub backend, one pair) into a run folder, and
the other notebooks copied there unexecuted (their headings are what the index links to; the test
stays under a minute). From it ``freereg_lib.commands.site.build_site`` writes the site, and:

* every link and image of the index resolves on disk, each ``#anchor`` to an id of its page;
* every page (the index, the notebooks, the docs pages, the API reference) has previous / next
  links in one chain, names its backend and has no dead link; each notebook page and each longer
  docs page has a table of contents whose links are ids of the page;
* every ``docs/*.md`` is a page, their links between each other resolve (GitHub's heading anchors
  to the renderer's ids), and every module of ``freereg_lib`` has an API page with its public
  functions and their signatures;
* headless Chromium (the Debian package; skipped with the reason when no binary is on PATH) opens
  the index, notebook 00's page, a docs page, a model card with its figure and an API page: no
  image is broken (``naturalWidth > 0``), which a page with a missing image shows the check can
  see; a screenshot of the index is saved in the run folder;
* the executed copy has text progress bars and no Open3D banner;
* the README's gallery: every figure it shows is in the repository, and small.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

nbformat = pytest.importorskip("nbformat")
papermill = pytest.importorskip("papermill")
pytest.importorskip("nbconvert")

from freereg_lib.commands import site as S  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
EXECUTED = "00_preliminaries"


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
            if a.get(key):
                self.refs.append((tag, a[key]))


def _parse(path: Path) -> _Links:
    key = (path.resolve(), path.stat().st_mtime_ns)
    if key not in _PARSED:
        p = _Links()
        p.feed(path.read_text(encoding="utf-8"))
        _PARSED[key] = p
    return _PARSED[key]


_PARSED: dict = {}


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("short") / "run"
    run.mkdir()
    papermill.execute_notebook(
        str(NOTEBOOKS / f"{EXECUTED}.ipynb"), str(run / f"{EXECUTED}.ipynb"),
        parameters={"backend": "stub", "n_pairs": 1, "out_dir": str(run / EXECUTED), "figures_dir": str(run / "figures")},
        kernel_name="python3", cwd=str(NOTEBOOKS), progress_bar=False,
    )
    for nb in sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb")):
        if nb.stem != EXECUTED:
            shutil.copy(nb, run / nb.name)
    return run


@pytest.fixture(scope="module")
def site(run) -> Path:
    index = S.build_site(run)
    assert index == run / "site" / "index.html"
    return index.parent


def _check_refs(page: Path, site: Path) -> list[str]:
    problems = []
    for tag, ref in _parse(page).refs:
        url = urlparse(ref)
        if url.scheme in ("http", "https", "data", "mailto"):
            continue
        target = page if not url.path else (page.parent / unquote(url.path)).resolve()
        if not target.is_file():
            problems.append(f"{page.name}: <{tag}> {ref} -> {target} does not exist")
        elif url.fragment and target.suffix == ".html" and not {url.fragment, unquote(url.fragment)} & _parse(target).ids:
            # (a browser tries the fragment as written, then percent-decoded: the HTML standard's rule)
            problems.append(f"{page.name}: <{tag}> {ref}: no id {unquote(url.fragment)!r} in {target.name}")
        elif target.is_file() and not target.resolve().is_relative_to(site.resolve()):
            problems.append(f"{page.name}: <{tag}> {ref} leaves the site folder")
    return problems


def test_the_index_maps_every_paper_float_and_no_link_is_dead(site):
    index = site / "index.html"
    text = index.read_text(encoding="utf-8")
    for f in S.PAPER_FLOATS:
        assert f"<td>{f.number}</td>" in text, f"{f.number} is not in the index's float table"
    for number in ("Fig. 4c", "Fig. 5 e-g", "Table 1", "Table 2", "Table 3", "Table 4", "Table 9"):
        assert f"<td>{number}</td>" in text
    assert "Table 8" not in text and "Fig. 3c" not in text
    refs = _parse(index).refs
    section_links = [r for t, r in refs if t == "a" and "#" in r and ".html" in r]
    assert len(section_links) >= len(S.PAPER_FLOATS), section_links
    assert any(r.startswith("03_fusion.html#3.") for r in section_links), "Fig. 5 e-g must link notebook 03's section 3"
    for f in S.PAPER_FLOATS:  # this short run drew none of them: each row names its figure instead
        assert all(f"{stem}.png" in text for stem in f.figures), f.number
    problems = _check_refs(index, site)
    assert not problems, "\n".join(problems)


def test_a_dead_link_or_anchor_is_caught(site, tmp_path):
    page = site / "zz_probe.html"
    page.write_text('<a href="nowhere.html">x</a> <a href="index.html#no-such-id">y</a> <a href="index.html">ok</a>')
    try:
        problems = _check_refs(page, site)
    finally:
        page.unlink()
    assert len(problems) == 2, problems


def _chain(site: Path) -> list[Path]:
    """The site's pages in the order of their "next" links, from the index."""
    pages = [site / "index.html"]
    while True:
        nxt = re.search(r'<a [^>]*rel="next"[^>]*>', pages[-1].read_text(encoding="utf-8"))
        if not nxt:
            return pages
        pages.append(site / re.search(r'href="([^"]+)"', nxt.group(0)).group(1))
        assert pages[-1] not in pages[:-1], f"the chain loops at {pages[-1].name}"


def test_every_page_has_navigation_a_contents_and_its_backend(site, run):
    notebooks = [site / f"{p.stem}.html" for p in sorted(run.glob("[0-9][0-9]_*.ipynb"))]
    pages = _chain(site)
    assert pages[:len(notebooks) + 1] == [site / "index.html"] + notebooks, [p.name for p in pages]
    rest = {p.name for p in pages[len(notebooks) + 1:]}
    assert {f"{d.stem}.html" for d in (ROOT / "docs").glob("*.md")} <= rest, rest
    assert {"api.html", "api_freereg_lib_geometry_pose.html", "benchmarks.html"} <= rest, rest
    assert set(pages) == set(site.glob("*.html")), "a page outside the previous / next chain"
    for k, page in enumerate(pages):
        text = page.read_text(encoding="utf-8")
        assert text.count('class="freereg-nav"') == 2, f"{page.name}: navigation at the top and the bottom"
        assert ('rel="prev"' in text) == (k > 0), page.name
        assert ('rel="next"' in text) == (k < len(pages) - 1), page.name
        if k + 1 < len(pages):
            assert f'href="{pages[k + 1].name}"' in text and 'rel="next"' in text
        assert re.search(r'class="freereg-backend">Backend: <strong>\w', text), f"{page.name}: no backend named"
        assert not _check_refs(page, site), _check_refs(page, site)
        if 0 < k <= len(notebooks) or page.name in ("micro_models.html", "real_data.html", "fidelity.html", "api_freereg_lib_geometry_pose.html"):
            toc = re.search(r'<nav aria-label="contents of this page" class="freereg-toc">(.*?)</nav>', text, re.S)
            assert toc, f"{page.name}: no table of contents"
            anchors = re.findall(r'href="#([^"]+)"', toc.group(1))
            assert len(anchors) >= 3, anchors
            ids = _parse(page).ids
            missing = [a for a in anchors if not {html_unescape(a), unquote(html_unescape(a))} & ids]
            assert not missing, f"{page.name}: contents entries without their heading: {missing}"
    assert 'Backend: <strong>stub</strong>' in (site / f"{EXECUTED}.html").read_text(encoding="utf-8")
    assert 'Backend: <strong>micro</strong>' in (site / "01_diffusion_features.html").read_text(encoding="utf-8")


def test_the_docs_pages_and_the_api_reference(site):
    from freereg_lib.commands import site_docs as D

    assert not D.WARNINGS, "docs links that lead nowhere:\n" + "\n".join(D.WARNINGS)
    index = (site / "index.html").read_text(encoding="utf-8")
    for md in (ROOT / "docs").glob("*.md"):
        assert f'href="{md.stem}.html"' in index, f"the index does not link docs/{md.name}"
    assert 'href="api.html"' in index
    # A link between docs pages, written with GitHub's anchor, lands on the renderer's id.
    perf = (site / "performance.html").read_text(encoding="utf-8")
    assert "Kabsch-RANSAC scoring, measured" in perf and "<table>" in perf
    troubles = (site / "troubleshooting.html").read_text(encoding="utf-8")
    assert "When something goes wrong" in troubles and troubles.count("<tr>") > 50
    # The model card's figure is copied with the page; a repository file without a page is text.
    card = (site / "model_card_diffusion.html").read_text(encoding="utf-8")
    assert 'src="assets/freereg_lib/models/micro/weights/loss_curves.png"' in card
    assert (site / "assets/freereg_lib/models/micro/weights/loss_curves.png").is_file()
    # The API reference: every module, its public functions with their signatures.
    api = (site / "api.html").read_text(encoding="utf-8")
    for name, _ in D._modules(ROOT / "freereg_lib"):
        assert f'href="api_{name.replace(".", "_")}.html"' in api, name
    pose = (site / "api_freereg_lib_geometry_pose.html").read_text(encoding="utf-8")
    assert 'Backend: <strong>any</strong>' in pose
    assert re.search(r'<h2 id="kabsch_ransac"', pose) and "def kabsch_ransac(" in html_unescape(re.sub(r"<[^>]+>", "", pose))
    assert "Kabsch" in pose  # its docstring


def test_a_docs_link_to_a_missing_heading_is_reported(tmp_path):
    from freereg_lib.commands import site_docs as D

    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "a.md").write_text("# A\n\n## Part one\n\nSee [b](b.md#part-two), [gone](b.md#nowhere) and [one](#part-one).\n")
    (docs / "b.md").write_text("# B\n\n## Part two\n\nBack to [a](a.md).\n")
    D.WARNINGS.clear()
    pages = [p for p in D.doc_pages(docs) if p.stem in ("a", "b")]
    D.link_pages(pages, tmp_path / "site")
    a = pages[0].body
    assert 'href="b.html#Part-two"' in a and 'href="#Part-one"' in a and 'href="b.html"' in a
    assert D.WARNINGS == [f"{(docs / 'a.md')}: no heading for #nowhere in {docs / 'b.md'}"], D.WARNINGS
    D.WARNINGS.clear()


def html_unescape(s: str) -> str:
    import html

    return html.unescape(s)


def test_the_executed_copy_has_text_progress_bars_and_no_open3d_banner(run):
    nb = nbformat.read(run / f"{EXECUTED}.ipynb", as_version=4)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not any("WebVisualizer" in o.get("text", "") for o in outputs), "Open3D's banner is back"
    assert not any("application/vnd.jupyter.widget-view+json" in o.get("data", {}) for o in outputs), "widget bars"
    assert not any(o.output_type == "error" for o in outputs)


def _browser_check(pages: list[Path], where: Path) -> dict:
    """Open ``pages`` in headless Chromium (each in an iframe of one probe page) and report their images."""
    probe = where / "browser_probe.html"
    probe.write_text("""<!DOCTYPE html><html><body><pre id="result">pending</pre><script>
const pages = %s; const out = {}; let left = pages.length;
for (const page of pages) {
  const f = document.createElement("iframe"); f.style.width = "1200px"; f.style.height = "900px";
  f.onload = () => {
    let r;
    try {
      const imgs = Array.from(f.contentDocument.images);
      r = {images: imgs.length,
           broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => (i.getAttribute("src") || "").slice(0, 80))};
    } catch (e) { r = {error: String(e)}; }
    out[page] = r;
    if (--left === 0) document.getElementById("result").textContent = JSON.stringify(out);
  };
  f.src = page; document.body.appendChild(f);
}
</script></body></html>""" % json.dumps([p.resolve().as_uri() for p in pages]))
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
                           "--virtual-time-budget=60000", "--dump-dom", probe.as_uri()],
                          capture_output=True, text=True, timeout=180)
    m = re.search(r'<pre id="result">(.*?)</pre>', proc.stdout, re.S)
    assert m and m.group(1) != "pending", f"Chromium gave no result (rc {proc.returncode}): {proc.stderr[-1500:]}"
    return {Path(urlparse(k).path).name: v for k, v in json.loads(html_unescape(m.group(1))).items()}


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary on PATH (Debian: apt-get install chromium; "
                                             "environment/setup_env.sh installs it when run as root)")
def test_in_chromium_no_image_is_broken_and_a_screenshot_is_saved(site, run):
    broken_page = run / "broken_probe.html"
    broken_page.write_text('<html><body><img src="no_such_figure.png"></body></html>')
    opened = ["index.html", f"{EXECUTED}.html", "micro_models.html", "model_card_diffusion.html",
              "api_freereg_lib_geometry_pose.html"]
    result = _browser_check([site / name for name in opened] + [broken_page], run)
    assert result["broken_probe.html"] == {"images": 1, "broken": ["no_such_figure.png"]}, result  # the check sees
    for name in opened:
        assert "error" not in result[name], result[name]
        assert not result[name]["broken"], f"{name}: broken images {result[name]['broken']}"
        assert not _check_refs(site / name, site), _check_refs(site / name, site)
    assert result[f"{EXECUTED}.html"]["images"] >= 5, result  # notebook 00 draws its figures inline
    assert result["model_card_diffusion.html"]["images"] >= 1, result  # the loss curves
    shot = run / "site_index.png"
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                           "--window-size=1280,1600", "--virtual-time-budget=20000", f"--screenshot={shot}",
                           (site / "index.html").as_uri()], capture_output=True, text=True, timeout=180)
    assert shot.is_file() and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", proc.stderr[-1500:]
    assert shot.stat().st_size > 20_000, "the screenshot is blank"


def test_make_book_command_writes_the_site(tmp_path):
    small = tmp_path / "run"  # one (unexecuted) notebook keeps the command's test short
    small.mkdir()
    shutil.copy(NOTEBOOKS / "05_your_data.ipynb", small)
    proc = subprocess.run([sys.executable, "-m", "freereg_lib.commands.site", str(small), "--out", str(tmp_path / "book")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "book" / "index.html").is_file() and (tmp_path / "book" / "05_your_data.html").is_file()
    assert (tmp_path / "book" / "troubleshooting.html").is_file() and (tmp_path / "book" / "api.html").is_file()
    assert "Site:" in proc.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run([sys.executable, "-m", "freereg_lib.commands.site", str(empty)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 1 and "no executed notebook" in proc.stderr and "Traceback" not in proc.stderr


# --------------------------------------------------------------------------------------
# The README's gallery.

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
    for name in S.GALLERY:
        assert f"figures/gallery/{name}.png" in local, f"the README does not show the gallery's {name}"


def test_the_readme_is_a_front_door_whose_links_lead_somewhere():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300, "the README is a front door (issue 42): move reference material to docs/"
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

    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (900, 2400, 3), dtype=np.uint8)).save(tmp_path / "noise.png")
    out = S.compact_png(tmp_path / "noise.png", tmp_path / "small.png", max_width=1000, max_bytes=400_000)
    with Image.open(out) as im:
        assert im.width <= 1000
    assert out.stat().st_size <= 400_000


def test_a_float_whose_section_is_gone_fails_the_build_naming_it(tmp_path):
    nb = nbformat.read(NOTEBOOKS / "03_fusion.ipynb", as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "markdown" and cell.source.startswith("## 3. Correspondences"):
            cell.source = cell.source.replace("## 3. Correspondences", "## 3. Matches", 1)
    nbformat.write(nb, str(tmp_path / "03_fusion.ipynb"))
    with pytest.raises(S.SiteError, match=r"Fig\. 5 e-g .*no heading starting '3\. Correspondences"):
        S.build_site(tmp_path)
