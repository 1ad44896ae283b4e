"""The site's reference pages: the pages of ``docs/`` and an API reference made from the docstrings.

:func:`doc_pages` renders every ``docs/*.md`` (in :data:`DOC_ORDER`, then the rest by name) and the
other markdown files those pages lead to (:data:`EXTRA_PAGES`: the benchmarks' results, the
teacher's guide, the model cards) with nbconvert's markdown renderer (mistune), the one that renders
the notebooks' markdown cells, so headings get the same ids. Links between them become links between
the HTML pages (GitHub's heading anchors mapped to the renderer's ids); an image of the repository is
copied under ``site/assets/``; a link to any other file of the repository becomes its path as text,
since the site holds no copy of it. A link that cannot be resolved is reported in :data:`WARNINGS`
(the tests require none) and rendered without its anchor.

:func:`api_pages` writes one page per module of ``freereg_lib`` from its source (``ast``: nothing is
imported, so the reference builds without torch or Open3D): the module's docstring, then each public
function and class with its signature and docstring, a class's public methods under it.

The pages are plain HTML with the site's navigation, the backend line and a table of contents, in
:func:`page_html`; ``freereg_lib.commands.site`` chains them after the notebooks.
"""
from __future__ import annotations

import ast
import html
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable
from urllib.parse import unquote, urlparse

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
DOCS = ROOT / "docs"
LIBRARY = Path(__file__).resolve().parents[1]  # the freereg_lib package

# The reading order of docs/; a page not named here follows, by name.
DOC_ORDER = ("backends", "micro_models", "real_data", "your_data", "real_frames", "fidelity", "performance",
             "troubleshooting", "teaching", "contributing")
# Other markdown files of the repository rendered as pages (repository path -> page stem).
EXTRA_PAGES = {
    "benchmarks/README.md": "benchmarks",
    "assignments/README.md": "assignments",
    "freereg_lib/models/micro/weights/MODEL_CARD.md": "model_card_diffusion",
    "freereg_lib/models/micro/weights/depth/MODEL_CARD.md": "model_card_depth",
}
# The backend each page is about (the backend line every page of the site carries).
DOC_BACKENDS = {
    "backends": ("all four", "This page says what each backend's numbers mean."),
    "micro_models": ("micro", "Miniature models trained here: their numbers are not the paper's."),
    "model_card_diffusion": ("micro", "Miniature models trained here: their numbers are not the paper's."),
    "model_card_depth": ("micro", "Miniature models trained here: their numbers are not the paper's."),
    "real_data": ("real", "The paper's models and data, on a GPU: nothing of it runs in this repository's CI."),
    "your_data": ("real", "The default of freereg register; the page says what the stub and tiny backends do there."),
    "real_frames": ("stub", "FreeReg-G (FPFH) with the true depth or the stub's monocular depth: not the paper's numbers."),
}
DEFAULT_BACKEND = ("any", "Each number on this page names the backend that measured it.")
API_BACKEND = ("any", "The library: the backend is an argument (freereg_lib.models.get_backend).")

WARNINGS: list[str] = []

_HEADING = re.compile(r'<h([1-6]) id="([^"]+)"[^>]*>(.*?)<a class="anchor-link"', re.S)
_LINK = re.compile(r'<(a|img)\b([^>]*?)\b(href|src)="([^"]*)"([^>]*)>', re.S)


@dataclass
class RefPage:
    """A reference page: a markdown file of the repository or a module's API, rendered."""

    stem: str
    title: str
    source: str               # repository path of the markdown file, or the module's name
    body: str                 # HTML
    backend: tuple[str, str]
    headings: list[tuple[int, str, str]] = field(default_factory=list)  # (level, id, text)

    @property
    def href(self) -> str:
        return f"{self.stem}.html"


def _headings(body: str) -> list[tuple[int, str, str]]:
    return [(int(level), anchor, html.unescape(re.sub(r"<[^>]+>", "", inner)).strip())
            for level, anchor, inner in _HEADING.findall(body)]


def github_slug(text: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def _render(markdown: str) -> str:
    from nbconvert.filters import markdown2html_mistune

    return markdown2html_mistune(markdown)


def _doc_sources(docs: Path) -> list[tuple[str, Path]]:
    found = {p.stem: p for p in sorted(docs.glob("*.md"))}
    order = [s for s in DOC_ORDER if s in found] + [s for s in sorted(found) if s not in DOC_ORDER]
    pages = [(s, found[s]) for s in order]
    pages += [(stem, ROOT / rel) for rel, stem in EXTRA_PAGES.items() if (ROOT / rel).is_file()]
    return pages


def doc_pages(docs: Path = DOCS) -> list[RefPage]:
    """The docs pages and :data:`EXTRA_PAGES`, rendered; links still as written (see :func:`link_pages`)."""
    pages = []
    for stem, path in _doc_sources(Path(docs)):
        body = _render(path.read_text(encoding="utf-8"))
        heads = _headings(body)
        title = next((t for level, _, t in heads if level == 1), stem.replace("_", " "))
        rel = str(path.resolve().relative_to(ROOT)) if path.resolve().is_relative_to(ROOT) else str(path)
        pages.append(RefPage(stem, title, rel, body, DOC_BACKENDS.get(stem, DEFAULT_BACKEND), heads))
    return pages


def _anchor(page: RefPage, fragment: str) -> str | None:
    """The id on ``page`` for a fragment written as GitHub's slug or as the renderer's id."""
    fragment = unquote(fragment)
    for _, anchor, text in page.headings:
        if fragment in (anchor, github_slug(text)):
            return anchor
    return None


def link_pages(pages: list[RefPage], site: Path) -> None:
    """Rewrite the links of the markdown pages to the site's pages and assets (in place)."""
    by_source = {(ROOT / p.source).resolve(): p for p in pages if p.source.endswith(".md")}

    for page in pages:
        if not page.source.endswith(".md"):
            continue
        base = (ROOT / page.source).resolve().parent

        def fix(m: re.Match) -> str:
            tag, before, attr, ref, after = m.groups()
            url = urlparse(html.unescape(ref))
            if url.scheme or ref.startswith("//"):
                return m.group(0)
            if not url.path:  # a fragment on this page
                anchor = _anchor(page, url.fragment)
                if anchor is None:
                    WARNINGS.append(f"{page.source}: no heading for #{url.fragment}")
                    anchor = ""
                return f'<{tag}{before}{attr}="#{html.escape(anchor)}"{after}>'
            target = (base / unquote(url.path)).resolve()
            if target in by_source:
                other = by_source[target]
                anchor = _anchor(other, url.fragment) if url.fragment else ""
                if anchor is None:
                    WARNINGS.append(f"{page.source}: no heading for #{url.fragment} in {other.source}")
                    anchor = ""
                return f'<{tag}{before}{attr}="{other.href}{"#" + html.escape(anchor) if anchor else ""}"{after}>'
            if target.is_file() and target.is_relative_to(ROOT) and target.suffix.lower() in (".png", ".jpg", ".jpeg", ".svg", ".gif"):
                rel = target.relative_to(ROOT)
                dst = site / "assets" / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(target, dst)
                return f'<{tag}{before}{attr}="assets/{rel.as_posix()}"{after}>'
            if not target.exists():
                WARNINGS.append(f"{page.source}: the link {ref} leads nowhere ({target})")
            # A file of the repository the site holds no copy of: its path, as text.
            rel = target.relative_to(ROOT).as_posix() if target.is_relative_to(ROOT) else ref
            return f'<{tag}{before}data-path="{html.escape(rel)}" title="{html.escape(rel)} in the repository"{after}>'

        page.body = _LINK.sub(fix, page.body)


# ---------------------------------------------------------------------------------------------
# The API reference.

def _modules(library: Path) -> list[tuple[str, Path]]:
    out = []
    for path in sorted(library.rglob("*.py")):
        rel = path.relative_to(library.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__main__" or any(p.startswith(".") for p in parts):
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append((".".join(parts), path))
    return out


def _docstring_md(doc: str | None) -> str:
    """A docstring as markdown: reST roles and double back-quotes to code spans."""
    if not doc:
        return "*(no docstring)*"
    doc = re.sub(r":(?:func|class|mod|meth|attr|data|exc|obj):`~?([^`]+)`", r"`\1`", doc)
    doc = re.sub(r"``([^`]+)``", r"`\1`", doc)
    return doc


def _signature(node: ast.FunctionDef | ast.AsyncFunctionDef, name: str | None = None) -> str:
    ret = f" -> {ast.unparse(node.returns)}" if node.returns is not None else ""
    prefix = "async def " if isinstance(node, ast.AsyncFunctionDef) else "def "
    return f"{prefix}{name or node.name}({ast.unparse(node.args)}){ret}"


def _public(name: str) -> bool:
    return not name.startswith("_")


def module_markdown(name: str, path: Path) -> str:
    """One module's reference as markdown: docstring, public functions and classes with signatures."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = [f"# {name}", "", f"Source: `{path.relative_to(LIBRARY.parent).as_posix()}`.", "", _docstring_md(ast.get_docstring(tree)), ""]
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _public(node.name):
            out += [f"## {node.name}", "", "```python", _signature(node), "```", "",
                    _docstring_md(ast.get_docstring(node)), ""]
        elif isinstance(node, ast.ClassDef) and _public(node.name):
            bases = ", ".join(ast.unparse(b) for b in node.bases)
            out += [f"## {node.name}", "", "```python", f"class {node.name}({bases})" if bases else f"class {node.name}",
                    "```", "", _docstring_md(ast.get_docstring(node)), ""]
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and (_public(item.name) or item.name == "__init__"):
                    out += [f"### {node.name}.{item.name}", "", "```python", _signature(item), "```", "",
                            _docstring_md(ast.get_docstring(item)), ""]
    return "\n".join(out)


def api_pages(library: Path = LIBRARY) -> list[RefPage]:
    """The API index and one page per module of ``library`` (default ``freereg_lib``)."""
    pages, rows = [], ["| module | what it is |", "|---|---|"]
    for name, path in _modules(Path(library)):
        stem = "api_" + name.replace(".", "_")
        body = _render(module_markdown(name, path))
        heads = _headings(body)
        pages.append(RefPage(stem, name, name, body, API_BACKEND, heads))
        first = (ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or "").strip().split("\n\n")[0]
        first = " ".join(_docstring_md(first).split()).replace("|", "\\|")
        rows.append(f"| [{name}]({stem}.html) | {first} |")
    index_md = ("# API reference\n\nOne page per module of `freereg_lib`, made from its docstrings and signatures "
                "(read from the source; `python -m freereg_lib.commands.site` writes them). Layers, from the bottom: core, "
                "models, pipeline, commands (the project's contributing notes).\n\n" + "\n".join(rows) + "\n")
    body = _render(index_md)
    return [RefPage("api", "API reference", "api", body, API_BACKEND, _headings(body))] + pages


# ---------------------------------------------------------------------------------------------
# The page.

_CSS = """
body { margin: 0; font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; line-height: 1.5; color: #222; }
main.freereg-page { max-width: 1100px; margin: 0 auto; }
.freereg-nav { display: flex; justify-content: space-between; gap: 1em; padding: 0.6em 1em;
               border-bottom: 1px solid #ccc; font-size: 14px; }
.freereg-nav a { text-decoration: none; }
.freereg-backend { margin: 0.6em 1em; padding: 0.4em 0.8em; background: #fff6d6; border-left: 4px solid #d9a400; font-size: 14px; }
.freereg-toc { margin: 0.6em 1em 1.2em 1em; font-size: 14px; }
.freereg-toc ul { margin: 0.3em 0; padding-left: 1.2em; }
.freereg-toc li.level3 { margin-left: 1.5em; list-style: circle; }
article.freereg-doc { padding: 0 1em 2em 1em; }
article.freereg-doc table { border-collapse: collapse; margin: 0.8em 0; font-size: 14px; }
article.freereg-doc th, article.freereg-doc td { border: 1px solid #ccc; padding: 0.25em 0.5em; vertical-align: top; }
article.freereg-doc pre { background: #f6f8fa; padding: 0.6em; overflow-x: auto; font-size: 13px; }
article.freereg-doc code { background: #f6f8fa; padding: 0 0.2em; }
article.freereg-doc img { max-width: 100%; }
a.anchor-link { visibility: hidden; margin-left: 0.3em; text-decoration: none; }
h1:hover a.anchor-link, h2:hover a.anchor-link, h3:hover a.anchor-link { visibility: visible; }
a[data-path] { color: inherit; }
"""


def _pygments_css() -> str:
    try:
        from pygments.formatters import HtmlFormatter
    except ImportError:  # pragma: no cover - nbconvert depends on pygments
        return ""
    return HtmlFormatter().get_style_defs(".highlight")


def _nav(prev: dict | None, next_: dict | None, where: str) -> str:
    left = f'<a class="freereg-prev" href="{prev["href"]}" rel="prev">&larr; {html.escape(prev["title"])}</a>' if prev else ""
    right = f'<a class="freereg-next" href="{next_["href"]}" rel="next">{html.escape(next_["title"])} &rarr;</a>' if next_ else ""
    return (f'<nav aria-label="pages ({where})" class="freereg-nav">\n  <span>{left}</span>\n'
            f'  <span><a class="freereg-home" href="index.html">Contents</a></span>\n  <span>{right}</span>\n</nav>')


def page_html(page: RefPage, prev: dict | None, next_: dict | None) -> str:
    """The HTML of one reference page: navigation, backend line, contents, the body, navigation."""
    toc = [(lvl, a, t) for lvl, a, t in page.headings if lvl in (2, 3)]
    toc_html = ""
    if toc:
        items = "\n".join(f'    <li class="level{lvl}"><a href="#{a}">{html.escape(t)}</a></li>' for lvl, a, t in toc)
        toc_html = (f'<nav aria-label="contents of this page" class="freereg-toc">\n  <strong>On this page</strong>\n'
                    f"  <ul>\n{items}\n  </ul>\n</nav>")
    backend, note = page.backend
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            f"<title>{html.escape(page.title)} · FreeReg companion</title>\n"
            f"<style>{_CSS}{_pygments_css()}</style>\n</head>\n<body>\n<main class=\"freereg-page\">\n"
            f"{_nav(prev, next_, 'top')}\n"
            f'<p class="freereg-backend">Backend: <strong>{html.escape(backend)}</strong>. {html.escape(note)}</p>\n'
            f"{toc_html}\n<article class=\"freereg-doc\">\n{page.body}\n</article>\n"
            f"<p class=\"freereg-source\">Source: <code>{html.escape(page.source)}</code></p>\n"
            f"{_nav(prev, next_, 'bottom')}\n</main>\n</body>\n</html>\n")


def write_pages(pages: Iterable[RefPage], site: Path, prev: dict | None, next_: dict | None) -> None:
    """Write ``pages`` into ``site`` as one chain: ``prev`` before the first, ``next_`` after the last."""
    pages = list(pages)
    for k, page in enumerate(pages):
        p = {"href": pages[k - 1].href, "title": pages[k - 1].title} if k > 0 else prev
        n = {"href": pages[k + 1].href, "title": pages[k + 1].title} if k + 1 < len(pages) else next_
        (site / page.href).write_text(page_html(page, p, n), encoding="utf-8")
