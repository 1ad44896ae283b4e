"""Sphinx configuration of the companion's book (``make book``; freereg_lib/commands/book.py lays out the sources).

Sphinx + myst-nb + sphinx-book-theme, the Jupyter Book 1 stack, built offline: the notebooks are rendered
from their stored outputs, MathJax comes from the pinned package django-static-mathjax and is copied
into the site, and nothing is loaded from a network. A notebook's printed lines wrap inside their box
(_static/freereg.css); the search page carries every page's text for its excerpts (see _page_texts).
Nitpicky: a cross-reference that leads nowhere is a warning, and the build turns warnings into errors.
"""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

project = "FreeReg companion"
author = "FreeReg companion contributors"
copyright = "the FreeReg companion contributors"

extensions = ["myst_nb", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax"]
exclude_patterns = ["_build", "**.ipynb_checkpoints", "book_doctrees"]
master_doc = "index"

# The notebooks: the run's outputs as they are; stderr (progress bars, library chatter) stays off the page.
nb_execution_mode = "off"
nb_output_stderr = "remove"
nb_merge_streams = True
myst_enable_extensions = ["dollarmath", "amsmath", "html_image", "colon_fence"]
myst_heading_anchors = 4  # GitHub's heading anchors, as the pages link each other on GitHub
myst_dmath_double_inline = True
# Not failures of the book: a heading level skipped, a code block in a language Pygments lacks (csv).
suppress_warnings = ["myst.header", "misc.highlighting_failure"]

# The API reference: members in source order, the types as written in the signature.
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True
autodoc_default_options = {"members": True}
add_module_names = False
# The docstrings are Google style (Args:, Returns:, Attributes:).
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_ivar = True
napoleon_use_rtype = False

# Every cross-reference must resolve: to the method's own objects. Types of other libraries (numpy,
# torch, pandas, ...) and of the standard library have no pages offline, and the tools beside the method
# (report, commands, training, teaching) are not in the reference: references to those are ignored.
nitpicky = True
nitpick_ignore_regex = [
    (r"py:.*", r"(np|numpy|torch|pd|pandas|o3d|open3d|cv2|PIL|Image|nn|scipy|yaml|dask|distributed|"
               r"diffusers|transformers|safetensors|matplotlib|plt|pathlib|typing|collections|dataclasses|os|"
               r"io|argparse|json|concurrent|types|enum|abc|re)(\..*)?"),
    (r"py:.*", r"freereg_lib\.(report|commands|training|teaching)(\..*)?"),
    (r"py:class", r"(Path|Any|Callable|Iterable|Iterator|Sequence|Mapping|Literal|Optional|Union|ArrayLike|"
                  r"NDArray|Tensor|Module|DataFrame|Series|PointCloud|Generator|TypeVar|Protocol|"
                  r"int|float|str|bool|bytes|dict|list|tuple|set|frozenset|object|None|type|slice|"
                  r"ndarray|dtype|Future|Executor|ThreadPoolExecutor|Enum)"),
    (r"py:(class|obj|data)", r"(optional|array|array-like|callable|default|shape.*|\(.*\)|.* of .*)"),
    (r"py:class", r"freereg_lib\.models\.torch_backends\._TorchBackend"),  # a private base class, shown in "Bases"
]

html_theme = "sphinx_book_theme"
html_title = "FreeReg companion"
html_static_path = ["_static"]
html_css_files = ["freereg.css"]
html_show_sourcelink = False
html_copy_source = False
html_theme_options = {
    "home_page_in_toc": True,
    "show_toc_level": 2,
    "use_download_button": False,
    "use_fullscreen_button": False,
    "use_repository_button": False,
    "navigation_with_keys": False,
}
html_last_updated_fmt = None

# MathJax 3 from the pinned package, copied into the site (see _copy_mathjax); no CDN.
mathjax_path = "mathjax/tex-mml-chtml.js"
mathjax3_config = {"tex": {"inlineMath": [["\\(", "\\)"]], "displayMath": [["\\[", "\\]"]]},
                   "options": {"enableMenu": False}}


def _mathjax_es5() -> Path:
    import mathjax  # django-static-mathjax: MathJax's distribution under mathjax/static/mathjax

    return Path(list(mathjax.__path__)[0]) / "static" / "mathjax" / "es5"


def _copy_mathjax(app, exception) -> None:
    """Copy the parts of MathJax that tex-mml-chtml.js loads into ``_static/mathjax`` of the site."""
    if exception is not None or app.builder.format != "html":
        return
    es5, dst = _mathjax_es5(), Path(app.outdir) / "_static" / "mathjax"
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copy(es5 / "tex-mml-chtml.js", dst / "tex-mml-chtml.js")
    for sub in ("input/tex/extensions", "output/chtml/fonts/woff-v2", "a11y", "ui", "adaptors"):
        if (es5 / sub).is_dir():
            shutil.copytree(es5 / sub, dst / sub, dirs_exist_ok=True)


def _lookup(dotted: str):
    """The object a dotted name names, importing its longest importable module prefix; None if none."""
    import importlib

    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except Exception:  # noqa: BLE001 - not a module: try a shorter prefix
            continue
        try:
            for name in parts[k:]:
                obj = getattr(obj, name)
        except AttributeError:
            return None
        return obj
    return None


def _resolve_reexport(app, env, node, contnode):
    """A reference to a name re-exported elsewhere (``freereg_lib.pipeline.run_pair``, ``Pair`` imported
    into a module) links to the documented object it is; anything else stays unresolved (and fails)."""
    if node.get("refdomain") != "py":
        return None
    from sphinx.util.nodes import make_refnode

    objects = env.get_domain("py").objects
    target, module = node["reftarget"].lstrip("~."), node.get("py:module")
    for cand in ([f"{module}.{target}"] if module else []) + [target]:
        obj = _lookup(cand)
        if obj is None:
            continue
        name = getattr(obj, "__name__", None) if type(obj).__name__ == "module" else (
            f"{getattr(obj, '__module__', '')}.{getattr(obj, '__qualname__', '')}")
        if name in objects:
            entry = objects[name]
            return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode, name)
    return None


# Search excerpts offline: Sphinx's search loads each result's page with fetch() to cut its excerpt, which
# browsers refuse on file://. Every page's text goes into _static/freereg_page_texts.js, and the search page
# loads it with _static/freereg_search_offline.js, which answers those fetches from it on file://.
PAGE_TEXTS_JS = "freereg_page_texts.js"
_page_texts: dict[str, str] = {}  # docname -> its text, as _searchable makes it
_DROP = re.compile(r'<(script|style)\b.*?</\1>|<a class="headerlink"[^>]*>.*?</a>', re.S)
_INLINE_TAG = re.compile(r"</?(a|em|strong|code|span|sub|sup|b|i|abbr|cite|var|kbd|samp|mark|small)\b[^>]*>")
_SECTION = re.compile(r"<section\b[^>]*?\sid=\"([^\"]*)\"[^>]*>")


def _searchable(body: str) -> str:
    """A page body reduced to its text and its sections (with their ids: a result's anchor names one)."""
    text = _INLINE_TAG.sub("", _DROP.sub("", body))
    text = _SECTION.sub(lambda m: f'\x00section id="{m.group(1)}"\x01', text).replace("</section>", "\x00/section\x01")
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]*>", " ", text))
    return '<div role="main">' + text.replace("\x00", "<").replace("\x01", ">") + "</div>"


def _collect_page_text(app, pagename, templatename, context, doctree) -> None:
    if app.builder.format != "html":
        return
    if pagename == "search":
        app.add_js_file(PAGE_TEXTS_JS)
        app.add_js_file("freereg_search_offline.js")
    elif doctree is not None and context.get("body"):
        _page_texts[pagename] = _searchable(context["body"])


def _write_page_texts(app, exception) -> None:
    if exception is not None or app.builder.format != "html":
        return
    out = Path(app.outdir) / "_static" / PAGE_TEXTS_JS
    out.write_text("window.FREEREG_PAGE_TEXTS = " + json.dumps(_page_texts, sort_keys=True) + ";\n", encoding="utf-8")


def setup(app) -> None:
    app.connect("build-finished", _copy_mathjax)
    app.connect("html-page-context", _collect_page_text)
    app.connect("build-finished", _write_page_texts)
    app.connect("missing-reference", _resolve_reexport)
