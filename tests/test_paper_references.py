"""Every reference to the paper's figures, tables and sections names a float the paper has, with
the right number for what it shows.

``FIGURES`` / ``TABLES`` / ``SECTIONS`` below are the paper's floats in LaTeX order (FreeReg, ICLR
2024: 10 figures and 13 tables, the appendix continuing the numbering), each with its label in the
LaTeX, what it shows, its panels and the words that name its subject. When the paper's text is on
disk (``PAPER_TEX``, beside the repository) the tables are checked against it.

The scan covers the text a reader sees: the notebooks' cell sources (not outputs), the READMEs,
``freereg_lib``'s Python files (docstrings, comments, strings: plot titles, messages) and its data
files. A reference fails when

* its number is not one of the paper's (``Fig. 11``, ``Table 14``, ``Sec. 4.5``);
* it names a panel the figure does not have (``Fig. 3c``: Fig. 3, the pipeline, has no panels; the
  PCA of the decoder layers is Fig. 4c; the D / G / fused matches are Fig. 5 e-g, not Fig. 4 e-g);
* the words right beside it name the subject of *another* float of the same kind and none of its
  own (``threshold ladders (Table 8)``: the ladders are Table 9, Table 8 is the layer combinations
  on BFO; ``layers (Sec. 4.4)``: Sec. 4.4 is the limitations);
* it is ``Sec. 4.4`` without the word "limitation" beside it (cite a float by number *and* name);
* a file name still carries the old number of the ladders (``table8_rr_ladder.csv``).
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAPER_TEX = ROOT.parent / "shared" / "paper" / "freereg_iclr2024.tex.txt"


@dataclass(frozen=True)
class Float:
    label: str          # \label{...} in the paper's LaTeX
    shows: str          # what it shows (cite it by number and this name)
    words: tuple        # words (lower case, regex) that name its subject
    panels: str = ""    # panel letters, "" when it has none


# The paper's floats, from its figure and table numbers and the LaTeX.
FIGURES = {
    1: Float("fig:teaser", "teaser", (r"teaser",)),
    2: Float("fig:solution", "the idea in four panels (I-IV)", (r"four panels", r"\bi-iv\b", r"idea")),
    3: Float("fig:pipeline", "the FreeReg pipeline", (r"pipeline",)),
    4: Float("fig:difff", "diffusion feature extraction on (a) images, (b) depth maps; (c) PCA of decoder features",
             (r"\bpca\b", r"decoder", r"feature extraction", r"layers?\b"), panels="abc"),
    5: Float("fig:fusefeat", "fused features: (b-d) D / G / fused feature maps, (e-g) D / G / fused matches",
             (r"fus(ed|ion)", r"d / g", r"correspondences?", r"match(es)?\b", r"feature maps?"), panels="abcdefg"),
    6: Float("fig:main", "qualitative results: correspondences of I2P-Matr, FreeReg-D / -G / FreeReg",
             (r"qualitative", r"i2p-matr"), panels="abcde"),
    7: Float("fig:rterror", "rotation and translation errors on three benchmarks (appendix)",
             (r"rotation and translation error", r"error curves?")),
    8: Float("fig:pcvisual", "semantic properties of FreeReg features (appendix)", (r"semantic",)),
    9: Float("fig:supp_main", "additional qualitative results (appendix)", (r"additional qualitative",),
             panels="abcde"),
    10: Float("fig:warping", "patch warping (appendix)", (r"warp",), panels="abc"),
}
TABLES = {
    1: Float("tab:main", "main results (3DMatch, ScanNet, KITTI-DC)",
             (r"main", r"benchmark", r"3dmatch", r"scannet", r"kitti", r"freereg-[dg]", r"baselines?")),
    2: Float("tab:layer", "layer selection (BFO and 3DMatch)", (r"layers?\b", r"feature map")),
    3: Float("tab:step", "diffusion step t_hat (BFO and 3DMatch)",
             (r"t_hat", r"\\hat ?\{?t\}?", r"diffusion step", r"\bsteps?\b")),
    4: Float("tab:fusew", "fusion weight w", (r"fusion", r"weights?\b", r"\bw\b")),
    5: Float("tab:matr", "RGBD-Scenes-v2 against 2D3D-Matr", (r"rgbd-scenes?-v2", r"2d3d-matr")),
    6: Float("tab:bigmodel", "other vision foundation backbones (appendix)", (r"backbones?", r"dino", r"clip")),
    7: Float("tab:sdorcn", "SD vs ControlNet depth features (appendix)", (r"controlnet", r"sd vs")),
    8: Float("tab:supplayersel", "layer combinations on the validation scene BFO (appendix)",
             (r"layer", r"combinations?", r"\bbfo\b")),
    9: Float("tab:pnpandkabsch", "PnP vs Kabsch: RR threshold ladders, RE / TE (appendix)",
             (r"ladders?", r"pnp", r"kabsch", r"thresholds?")),
    10: Float("tab:same_modality", "mono-modality registration (appendix)", (r"mono-modality",)),
    11: Float("tab:ftornot", "fine-tuning FreeReg (appendix)", (r"fine-tun",)),
    12: Float("tab:ftmatr", "2D3D-Matr vs fine-tuned FreeReg (appendix)", (r"2d3d-matr", r"fine-tun")),
    13: Float("tab:accelerate", "fewer DDIM iterations (appendix)", (r"ddim", r"accelerat", r"iterations")),
}
SECTIONS = {
    "1": ("introduction", ()), "2": ("related work", ()), "3": ("method", ()),
    "3.1": ("preliminary: Stable Diffusion and ControlNet", ()),
    "3.2": ("diffusion features", (r"diffusion feature", r"layers?\b", r"decoder")),
    "3.3": ("geometric features", (r"geometric",)),
    "3.4": ("fusion", (r"fus(e|ed|ion)",)),
    "4": ("experiments", ()), "4.1": ("experimental protocol", ()), "4.2": ("results on three benchmarks", ()),
    "4.3": ("more analysis: layers and t_hat on BFO, fusion weight",
            (r"layers?\b", r"t_hat", r"\\hat", r"fusion", r"weight", r"\bbfo\b", r"analysis")),
    "4.3.1": ("ablating diffusion feature extraction (on BFO)", (r"layers?\b", r"t_hat", r"\\hat", r"\bbfo\b")),
    "4.3.2": ("ablating the fusion weight", (r"fusion", r"weight")),
    "4.4": ("limitations", (r"limitation", r"runtime", r"memory")),
    "5": ("conclusion", ()),
}
# Subjects a wrong number tends to be used for; each must sit beside its own float's number.
FIG_TOPICS = {4: (r"decoder", r"pca of"), 5: (r"correspondences?", r"match(es)?\b")}
TABLE_TOPICS = {9: (r"ladders?", r"pnp-vs-kabsch", r"pnp vs kabsch"), 8: (r"layer combinations?",),
                4: (r"fusion weight",), 3: (r"diffusion step", r"t_hat"), 2: (r"layer selection",)}
SECTION_TOPICS = {"4.4": (r"limitation",), "4.3": (r"layer", r"t_hat", r"fusion weight"),
                  "3.2": (r"layer",)}

FIG_RE = re.compile(
    r"\b(?:Figs?\.|Figures?)\s?(?P<nums>\d+(?:\s?\(?[a-z](?:\s?[-/,–]\s?[a-z])*\)?(?![A-Za-z]))?"
    r"(?:\s?(?:,|/|and|&)\s?\d+(?:\s?\(?[a-z](?:\s?[-/,–]\s?[a-z])*\)?(?![A-Za-z]))?)*)"
)
TABLE_RE = re.compile(r"\b(?:Tables?|Tab\.)\s?(?P<nums>\d+(?:\s?(?:,|/|and|&)\s?\d+)*)\b")
SECTION_RE = re.compile(r"(?:\bSecs?\.|\bSections?\b|§)\s?(?P<nums>\d+(?:\.\d+)*(?:\s?(?:,|/|and|&)\s?\d+(?:\.\d+)*)*)")
WINDOW = 70  # characters each side of a reference that count as "beside" it


def _documents() -> list[tuple[str, str]]:
    """(where, text) for every text a reader sees; notebook cells one by one, sources only."""
    docs = []
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(nb.read_text(encoding="utf-8"))["cells"]
        docs += [(f"{nb.relative_to(ROOT)} cell {i}", "".join(c["source"])) for i, c in enumerate(cells)]
    paths = [ROOT / "README.md", ROOT / "assignments" / "README.md", ROOT / "figures" / "README.md",
             ROOT / "benchmarks" / "README.md", ROOT / "Makefile"] + sorted((ROOT / "docs").glob("*.md"))
    paths += sorted((ROOT / "freereg_lib").rglob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))
    paths += [p for ext in ("yaml", "yml", "md", "txt") for p in sorted((ROOT / "freereg_lib" / "data").rglob(f"*.{ext}"))]
    docs += [(str(p.relative_to(ROOT)), p.read_text(encoding="utf-8")) for p in paths if p.is_file()]
    return docs


DOCS = _documents()


def _near(text: str, start: int, end: int) -> str:
    """The words beside a match: WINDOW characters each side, within the same paragraph."""
    lo, hi = max(0, start - WINDOW), min(len(text), end + WINDOW)
    para_lo = text.rfind("\n\n", lo, start)
    para_hi = text.find("\n\n", end, hi)
    return text[(para_lo + 2 if para_lo >= 0 else lo):(para_hi if para_hi >= 0 else hi)].lower()


def _has(text: str, words) -> bool:
    return any(re.search(w, text) for w in words)


def _line(text: str, pos: int) -> str:
    return f"line {text.count(chr(10), 0, pos) + 1}: {text[max(0, pos - 40):pos + 50]!r}"


def _topic_clash(kind: str, num, near: str, floats: dict, topics: dict) -> str | None:
    """A message when ``near`` names another float's subject and nothing of ``num``'s own."""
    own = floats[num].words if kind != "Sec." else floats[num][1]
    if _has(near, own):
        return None
    for other, words in topics.items():
        if other != num and _has(near, words):
            what = floats[other].shows if kind != "Sec." else floats[other][0]
            mine = floats[num].shows if kind != "Sec." else floats[num][0]
            return f"{kind} {num} is {mine}, but the words beside it are about {kind} {other} ({what})"
    return None


def find_problems(where: str, text: str) -> list[str]:
    problems = []
    for m in re.finditer(r"table8_", text):
        problems.append(f"{where}: a file name with the ladders' old number (they are Table 9, "
                        f"{TABLES[9].shows}), {_line(text, m.start())}")
    for m in FIG_RE.finditer(text):
        near = _near(text, m.start(), m.end())
        for part in re.finditer(r"(\d+)\s?\(?([a-z](?:\s?[-/,–]\s?[a-z])*)?\)?", m["nums"]):
            num, panels = int(part[1]), re.findall(r"[a-z]", part[2] or "")
            if num not in FIGURES:
                problems.append(f"{where}: Fig. {num} does not exist (the paper has Figs. 1-{max(FIGURES)}), "
                                f"{_line(text, m.start())}")
                continue
            bad = [p for p in panels if p not in FIGURES[num].panels]
            if bad:
                problems.append(f"{where}: Fig. {num} ({FIGURES[num].shows}) has no panel {'/'.join(bad)}, "
                                f"{_line(text, m.start())}")
            clash = _topic_clash("Fig.", num, near, FIGURES, FIG_TOPICS)
            if clash:
                problems.append(f"{where}: {clash}, {_line(text, m.start())}")
    for m in TABLE_RE.finditer(text):
        near = _near(text, m.start(), m.end())
        for num in map(int, re.findall(r"\d+", m["nums"])):
            if num not in TABLES:
                problems.append(f"{where}: Table {num} does not exist (the paper has Tables 1-{max(TABLES)}), "
                                f"{_line(text, m.start())}")
                continue
            clash = _topic_clash("Table", num, near, TABLES, TABLE_TOPICS)
            if clash:
                problems.append(f"{where}: {clash}, {_line(text, m.start())}")
    for m in SECTION_RE.finditer(text):
        near = _near(text, m.start(), m.end())
        for num in re.findall(r"\d+(?:\.\d+)*", m["nums"]):
            if num not in SECTIONS:
                problems.append(f"{where}: Sec. {num} does not exist in the paper, {_line(text, m.start())}")
                continue
            if num == "4.4" and not re.search(r"limitation", near):
                problems.append(f"{where}: Sec. 4.4 is the limitations; cite it as such, {_line(text, m.start())}")
                continue
            clash = _topic_clash("Sec.", num, near, SECTIONS, SECTION_TOPICS)
            if clash:
                problems.append(f"{where}: {clash}, {_line(text, m.start())}")
    return problems


def test_the_repository_cites_the_paper_right():
    problems = [p for where, text in DOCS for p in find_problems(where, text)]
    assert not problems, f"{len(problems)} wrong reference(s) to the paper:\n" + "\n".join(problems)


def test_the_scan_reads_the_notebooks_and_the_library():
    wheres = {w.split(" cell ")[0] for w, _ in DOCS}
    assert {"README.md", "docs/micro_models.md", "freereg_lib/report/plots.py", "notebooks/04_benchmark.ipynb"} <= wheres
    refs = sum(len(FIG_RE.findall(t)) + len(TABLE_RE.findall(t)) for _, t in DOCS)
    assert refs > 30, f"only {refs} figure / table references found: is the scan reading the files?"


@pytest.mark.parametrize("text, expected", [
    ("the PCA of the decoder layers (the paper's Fig. 3c)", "has no panel c"),
    ("the matches of D, G and fused features (the paper's Fig. 4 e/f/g)", "has no panel e/f/g"),
    ("What to look for (the paper's Fig. 4 caption): reliable but sparse matches", "about Fig. 5"),
    ("the supplementary's PnP-vs-Kabsch table (Table 8)", "about Table 9"),
    ("## 4. Registration recall over threshold ladders (Table 8)", "about Table 9"),
    ("t8.to_csv(out / 'table8_rr_ladder.csv')", "old number"),
    ("layers = [0, 4, 6]  # FreeReg's decoder layers (Sec. 4.4, Table 2 row m)", "Sec. 4.4 is the limitations"),
    ("w_fused = 0.5  # FreeReg's weight (Sec. 4.4)", "Sec. 4.4 is the limitations"),
    ("as in Fig. 11 of the paper", "Fig. 11 does not exist"),
    ("see Table 14", "Table 14 does not exist"),
    ("see Sec. 4.5", "Sec. 4.5 does not exist"),
])
def test_the_scan_catches_wrong_references(text, expected):
    problems = find_problems("example", text)
    assert any(expected in p for p in problems), problems


@pytest.mark.parametrize("text", [
    "the PCA of the decoder layers (Fig. 4c, PCA of decoder features)",
    "the D / G / fused matches (Fig. 5 e-g, fused features and matches) and the feature maps (Fig. 5 b/c/d)",
    "RR over the threshold ladders (Table 9, PnP vs Kabsch)",
    "the layer combinations on BFO (Table 8, layer combinations)",
    "layers (Table 2, layer selection; Sec. 3.2 / 4.3, chosen on the validation scene BFO)",
    "the runtime (Sec. 4.4, limitations)",
    "which layers (Table 2), which diffusion step (Table 3), and SD vs ControlNet (Table 7)",
    "Tables 1 and 2 report FreeReg-D with PnP",
])
def test_the_scan_accepts_right_references(text):
    assert find_problems("example", text) == []


@pytest.mark.skipif(not PAPER_TEX.is_file(), reason="the paper's LaTeX is not on disk (PAPER_TEX)")
def test_the_float_table_is_the_papers():
    tex = PAPER_TEX.read_text(encoding="utf-8")
    floats = re.findall(r"\\begin\{(figure\*?|table\*?|wraptable|wrapfigure)\}(.*?)\\end\{\1\}", tex, re.S)
    labels = {"fig": [], "tab": []}
    for env, body in floats:
        label = re.search(r"\\label\{((?:fig|tab):[^}]*)\}", body)
        assert label, f"a {env} without a label"
        labels["fig" if env.startswith(("figure", "wrapfigure")) else "tab"].append(label[1])
    assert labels["fig"] == [FIGURES[k].label for k in sorted(FIGURES)]
    assert labels["tab"] == [TABLES[k].label for k in sorted(TABLES)]
    # Sections: \section / \subsection / \subsubsection of the main text (before \appendix's content).
    main = tex.split("%% file: content/06_supplementary")[0]
    main = main[main.index("%% file: content/01_introduction"):]
    numbers, counters = [], [0, 0, 0]
    for level, title in re.findall(r"\\(section|subsection|subsubsection)\{(.*?)\}\n", main):
        depth = ("section", "subsection", "subsubsection").index(level)
        counters[depth] += 1
        counters[depth + 1:] = [0] * (2 - depth)
        numbers.append(".".join(map(str, counters[:depth + 1])))
    assert set(SECTIONS) <= set(numbers), sorted(set(SECTIONS) - set(numbers))
    assert "4.5" not in numbers and "3.5" not in numbers
    limitations = re.search(r"\\subsection\{Limitations\}", main)
    assert limitations and numbers[len(re.findall(r"\\(?:sub){0,2}section\{", main[:limitations.start()]))] == "4.4"
