"""Prose that cannot drift from its run: the numbers a notebook's Markdown states, checked.

A notebook's Markdown may state a number about its own run only through the run: a value glued with
myst-nb's ``glue`` (``from myst_nb import glue``; in Markdown ``{glue:text}`name``` or
``{glue}`name```) or a line the run prints. A number typed by hand stays when the run changes (another
backend, seed, number of pairs, a retrained model) and then contradicts the output beside it.

:func:`check_notebook` takes an executed notebook (an nbformat dict) and returns its
:class:`Problem` s:

* ``number``: a number in a Markdown cell that is neither glued nor one of the exempt kinds below;
* ``glue``: a ``{glue...}`` reference whose name the run did not glue (the book would fail on it);
* ``verdict``: a verdict on a claim of the paper typed in prose ("the fusion claim holds here"): verdicts
  are printed by the run through :mod:`freereg_lib.report.vocabulary`, with their numbers and test;
* ``claim``: a direction or a description ("the sky stays empty", "recall falls as the error grows")
  that a check line the run printed contradicts (:mod:`freereg_lib.report.claims`);
* ``printed verdict``: a printed line whose verdict is not the vocabulary's for its own numbers.

Exempt, because they do not depend on the run:

* names of things: paper floats, sections, equations, notebooks, layers and rows ("Table 2, layer
  selection", "Sec. 3.4, fusion", "Fig. 4c, PCA of decoder features", "notebook 03", "layers 0, 4 and
  6", "rows a-i"), years of citations,
  versions ("v1.5"), digits inside words ("3DMatch", "x10", "T_pc_sensor"), the numbering of
  headings and lists;
* code: inline code spans and fenced blocks quote the notebook's own source and parameters;
* the paper's own numbers, quoted as the paper's: a value of the paper's tables
  (``freereg_lib/data/paper_tables/*.csv``) in a sentence that names the paper or one of its tables;
* declared facts of the paper and the code (:data:`FACTS`): each a pattern for the phrase that
  states it and the reason it cannot change with a run. The list is kept short on purpose: a fact
  that can change with a parameter or a retrained model is glued instead.

``python -m freereg_lib.report.prose runs/reproduce/*.ipynb`` prints the problems of executed notebooks.
This module owns those rules and :data:`FACTS`; the notebooks own their glue.
"""
from __future__ import annotations

import argparse
import csv
import functools
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

PAPER_TABLES = Path(__file__).resolve().parents[1] / "data" / "paper_tables"


@dataclass(frozen=True)
class Fact:
    """A number the prose may state by hand: the phrase that states it (a regex) and why it is fixed."""

    pattern: str
    why: str


@dataclass(frozen=True)
class Problem:
    """One finding: the Markdown cell (index among all cells, and its id), the kind, and what was found."""

    cell: int
    cell_id: str
    kind: str      # "number" | "glue" | "verdict" | "claim" | "printed verdict"
    found: str     # the number as written, the glue name, or the verdict words
    context: str   # the words around it

    def __str__(self) -> str:
        what = {"number": f"number {self.found!r} is neither glued nor a declared fact",
                "glue": f"glue name {self.found!r} was not glued by this run",
                "verdict": f"verdict {self.found!r} typed by hand (a verdict is printed by the run, "
                           "freereg_lib.report.vocabulary)",
                "claim": f"claim contradicted by the run: {self.found}",
                "printed verdict": f"printed verdict {self.found}"}[self.kind]
        return f"cell {self.cell} (id {self.cell_id}): {what}: ...{self.context}..."


# The paper's settings, stated in several notebooks: Sec. 4.1, the implementation details and the
# appendix, and FreeRegConfig's defaults. A run's parameters change the code's value, never the paper's;
# where a notebook states the value its run used (a parameter), it glues it instead.
COMMON: tuple[Fact, ...] = (
    Fact(r"\\tau_c\$?(?: =)? \$?0\.3\$? m|0\.3 m indoor|3 m KITTI|within 0\.3 m", "tau_c, the correct-match distance"),
    Fact(r"20° and 0\.5 m|20°, 0\.5 m", "the paper's RR thresholds (Sec. 4.1)"),
    Fact(r"(?:more than|IR >) 5 %|\(5 %\)", "FMR's 5 % inlier ratio (Sec. 4.1)"),
    Fact(r"\\hat t\$?(?: =)? \$?150|\$t = 150\$|before\*? 150|chose 150|whether 150", "t_hat = 150, the paper's step"),
    Fact(r"\$w = (?:0\.5|1|0)\$|\$w\$ = 0\.5-0\.6", "the fusion weights the paper names (Sec. 3.4, Table 4)"),
    Fact(r"\((?:0, 4, 6|0, 4|4, 6|0, 6)\)", "the paper's layer sets (Table 2 rows j-m)"),
    Fact(r"1210(?:-pair| pairs)", "3DMatch's test pairs, the paper's benchmark size"),
    Fact(r"512 x 704", "the paper's diffusion input size (Table 2's feature-map column)"),
    Fact(r"per 16 x 16 input pixels|one per 64 x 64|\b(?:8 x 11|16 x 22|32 x 44)\b",
         "the feature-map sizes of SD's decoder for a 512 x 704 input (Table 2)"),
    Fact(r"(?:to|at most|fewer than) 128 (?:PCA )?channels|\(128 PCA channels each\)",
         "the paper's PCA size per layer (cfg.pca_dim)"),
    Fact(r"9\.3 s (?:per|a) pair", "the paper's runtime on an RTX 4090 (Sec. 4.4, limitations; Table 13, DDIM iterations)"),
    Fact(r"3-component PCA", "the figures' PCA colouring (plots.pca_rgb, plots.keypoint_feature_pca)"),
)

# Facts of one notebook: {notebook stem: facts}, each with the reason no run can change it.
FACTS: dict[str, tuple[Fact, ...]] = {
    "00_preliminaries": (
        Fact(r"\(0\.01, 10\) m|pixels (?:stay|are) 0", "the official code's depth range; 0 marks no depth"),
        Fact(r"6×6 edge filter|7×7 diamond kernel|64-(?:line|ring) LiDAR|to 255 m",
             "IP-Basic's and the edge filter's kernels, the synthetic LiDAR, the official copy's sky depth"),
        Fact(r"\\sqrt\{0\.0(?:0085|12)\}|4 channels, scaled by 0\.18215|\(13 residuals\)|0-255|\$w = 4\$",
             "Stable Diffusion v1.5's schedule and VAE, ControlNet's residuals and hint range, the guidance scale"),
        Fact(r"\$T = 1000\$|\$t = (?:1000|999)\$|20 steps|951, 901, …, 1",
             "the DDIM schedule the paper samples with, range(1000, 0, -50), and the scheduler's last step"),
        Fact(r"0 with fewer than 3 evaluable|gives TE = 0|\$N \\times 3\$|\$4 \\times 4\$",
             "the metrics' definitions (the official code's rules); notation"),
    ),
    "01_diffusion_features": (
        Fact(r"128 x 192|4 x 6(?:, 8 x 12 and 16 x 24| cells)", "the micro models' input and map sizes (their architecture)"),
        Fact(r"384 channels with SD's layers|32 x 44 = 1408 on a 640 x 480 image|0\.\.255",
             "the paper's descriptor (3 x 128), its keypoint grid, ControlNet's hint range"),
        Fact(r"adds 14 points of RR", "Table 7's gap, the paper's (RR 19.2 against 33.2)"),
        Fact(r"100 pairs of seed 2026 \(the development set and 70 more\)", "the micro model card's fixed evaluation set"),
    ),
    "02_geometric_features": (
        Fact(r"about 0\.27 m on its indoor sets and 3\.4 m on KITTI|\(0\.27 m indoors by default\)",
             "ZoeDepth's error, the paper's, and the stub's default (mono_mae)"),
        Fact(r"32-d descriptor|33-d histogram|\(voxel 0\.025 m\) or KITTI \(0\.3 m\)|\(0\.5 m indoors, 5 m outdoors\)",
             "FCGF's and FPFH's sizes, FCGF's voxels and tau_g, the paper's"),
        Fact(r"FreeReg-G \(w = 0|100 / `n_pairs` points|\$4\\times4\$|\$3\\times3\$",
             "FreeReg-G's weight; one pair's share of RR; notation"),
    ),
    "04_benchmark": (Fact(r"below 100 %", "a share of pairs"),),
    "06_appendix": (
        Fact(r"for 1\.4 points of registration recall|the 21 combinations|lists 21 combinations|spread over 1000",
             "Table 13's RR change and Table 8's row count, the paper's; the DDIM schedule's span"),
    ),
    "05_your_data": (
        Fact(r"scale near 1|are 0 or 100", "the plausibility rule (a scale near one); a single pair's FMR and RR"),
        Fact(r"default inputs are the embedded ICL living-room frames 180 and 200 at half resolution",
             "the parameters' defaults (icl_frames, scale), named as defaults"),
    ),
}

# Names of things: a keyword, then one number or a list of them ("Tables 1 and 2", "layers 0, 4, 6").
_ITEM = r"\d+(?:\.\d+)*[a-z]?(?:\s*-\s*(?:\d+|[a-zA-Z]\b))?"
_NAMES = re.compile(
    r"\b(?:coarse|medium|fine|Notebooks?|Tables?|Tab\.|Figs?\.|Figures?|Sec\.|Secs\.|Sections?|sections?|Eqs?\.|Equations?|Appendix|"
    r"notebooks?|Exercise|layers?|rows?|Table\s+\d+\s+rows?|Fig\.\s*\d+-[IV]+)[\s(-]*"
    + _ITEM + r"(?:\s*(?:,|and|or|to|/)\s*" + _ITEM + r")*")
_YEAR = re.compile(r"(?:et al\.,?|ICLR|\(|,)\s*(?:19|20)\d\d\b")
_NUMBER = re.compile(r"(?<![\w.\\])[+\-−]?\d+(?:_\d{3})*(?:\.\d+)?(?:\s?%)?(?![\w])")
_CODE_SPAN = re.compile(r"(`+)(?!\{)(.+?)\1", re.S)
_FENCE = re.compile(r"^(```|~~~|:::).*?^\1\s*$", re.S | re.M)
GLUE_ROLE = re.compile(r"\{glue(?::(?:any|text|md|math|figure))?\}`([^`]+)`")
_GLUE_DIRECTIVE = re.compile(r"^(?:```|:::)\{glue(?::(?:any|figure|math|md))?\}\s+(\S+)", re.M)
_MASKS = (
    re.compile(r"\]\([^)]*\)"),                         # link targets
    re.compile(r"https?://\S+"),
    re.compile(r"<[^>\n]+>"),                           # HTML tags and comments
    re.compile(r"^\s*#+\s*\d+\s*(?:·|\.)", re.M),       # "# 00 ·", "## 5."
    re.compile(r"^\s*(?:\d+\.|[-*])\s", re.M),          # list markers
    re.compile(r"\b\d+(?:\.\d+)?-[Dd]\b"),              # "3-D", "2-D"
    re.compile(r"\b(?:SE|SO)\(3\)"),                  # the groups' names
)
# Inside math, the integers 0, 1, 2 and -1 are notation (exponents, 1 - w, identity blocks, inverses).
_MATH = re.compile(r"\$\$.+?\$\$|\$[^$\n]+\$", re.S)
_NOTATION = re.compile(r"(?<![\w.])-?[012](?![\w.])")
_PAPERISH = re.compile(r"paper|\bTables?\s+\d|appendix", re.I)
_SENTENCE_END = re.compile(r"(?<=[.!?:;])\s+(?=[A-Z*(`$])|\n\s*\n")


@functools.cache
def paper_numbers() -> frozenset[float]:
    """Every number in the paper's tables (cells and the numbers inside text cells such as ladders)."""
    values: set[float] = set()
    for path in PAPER_TABLES.glob("*.csv"):
        with path.open(newline="") as fh:
            for row in csv.reader(fh):
                for cell in row:
                    values.update(float(x) for x in re.findall(r"\d+(?:\.\d+)?", cell))
    return frozenset(values)


def _blank(text: str, span: tuple[int, int]) -> str:
    a, b = span
    return text[:a] + re.sub(r"[^\n]", " ", text[a:b]) + text[b:]


def _value(token: str) -> float | None:
    try:
        return float(token.replace("%", "").replace("_", "").replace("−", "-").strip())
    except ValueError:
        return None


def glue_references(markdown: str) -> list[str]:
    """The glue names a Markdown text references (roles and directives; a role's ``:format`` removed)."""
    names = [m.group(1).rsplit(":", 1)[0] if ":" in m.group(1) else m.group(1) for m in GLUE_ROLE.finditer(markdown)]
    return [n.split("::")[-1].strip() for n in names] + [m.group(1) for m in _GLUE_DIRECTIVE.finditer(markdown)]


def glued_names(nb: Mapping[str, Any]) -> set[str]:
    """The names the run glued: outputs that myst-nb's ``glue`` marks with ``metadata.scrapbook.name``."""
    return {out["metadata"]["scrapbook"]["name"]
            for cell in nb.get("cells", []) if cell.get("cell_type") == "code"
            for out in cell.get("outputs", []) if "scrapbook" in (out.get("metadata") or {})}


def stated_numbers(markdown: str, facts: Sequence[Fact] = ()) -> list[tuple[str, str]]:
    """The numbers a Markdown text states by hand, each with its context, after every exemption."""
    text = markdown
    for m in _MATH.finditer(markdown):
        for n in _NOTATION.finditer(m.group()):
            text = _blank(text, (m.start() + n.start(), m.start() + n.end()))
    for rx in (_FENCE, GLUE_ROLE, _CODE_SPAN, *_MASKS, _NAMES, _YEAR):
        for m in list(rx.finditer(text)):
            text = _blank(text, m.span())
    for fact in facts:  # a space in a pattern stands for any run of white space (the source wraps lines)
        for m in list(re.finditer(fact.pattern.replace(" ", r"\s+"), markdown, re.M)):
            text = _blank(text, m.span())
    sentences = [(m.start(), m.end()) for m in re.finditer(r"(?:(?!" + _SENTENCE_END.pattern + r").)+", markdown, re.S)]
    found = []
    for m in _NUMBER.finditer(text):
        sentence = next((markdown[a:b] for a, b in sentences if a <= m.start() < b), markdown)
        value = _value(m.group())
        if value is not None and abs(value) in paper_numbers() and _PAPERISH.search(sentence):
            continue  # the paper's number, quoted in a sentence that says whose it is
        context = " ".join(markdown[max(0, m.start() - 50):m.end() + 30].split())
        found.append((m.group().strip(), context))
    return found


# A verdict stated in prose: the vocabulary's words closing a claim ("the claim holds", "does not hold
# here", "holds in the mean"); the verb of a sentence about contents ("the cloud holds no point") is not one.
VERDICT_PROSE = re.compile(r"\b(holds|does not hold|do not hold|same direction, not significant|"
                           r"opposite direction)(?=\s*(?:$|[.,;:)]|here\b|in the mean\b|on (?:these|this|the)\b))",
                           re.IGNORECASE | re.MULTILINE)


def stated_verdicts(markdown: str) -> list[tuple[str, str]]:
    """``(verdict words, context)`` for each verdict Markdown states by hand (outside code spans): a
    verdict comes from the run's printout, where the numbers and the test behind it stand beside it."""
    text = re.sub(r"`[^`]*`", lambda m: " " * len(m.group()), markdown)
    return [(m.group(1), " ".join(text[max(0, m.start() - 60):m.end() + 20].split()))
            for m in VERDICT_PROSE.finditer(text)]


def notebook_name(nb: Mapping[str, Any]) -> str:
    """The notebook's stem, from papermill's record of its input (``""`` when unknown)."""
    path = (nb.get("metadata", {}).get("papermill") or {}).get("input_path") or ""
    return Path(path).stem


def check_notebook(nb: Mapping[str, Any], name: str | None = None) -> list[Problem]:
    """The problems of an executed notebook: hand-typed numbers, glue names not glued, verdicts typed by
    hand, claims its printed checks contradict, printed verdicts its own numbers contradict.

    Args:
        nb: the executed notebook, as nbformat reads it (a dict works too).
        name: the notebook's stem, which selects its :data:`FACTS`; by default papermill's input path.
    """
    name = notebook_name(nb) if name is None else name
    facts = COMMON + FACTS.get(name, ())
    from freereg_lib.report import claims

    glued, checks = glued_names(nb), claims.printed_checks(nb)
    problems = []
    for k, cell in enumerate(nb.get("cells", [])):
        if cell.get("cell_type") != "markdown":
            problems += [Problem(k, str(cell.get("id", "")), "printed verdict", why, line[:120])
                         for line, why in claims.printed_verdicts({"cells": [cell]})]
            continue
        source = cell["source"] if isinstance(cell["source"], str) else "".join(cell["source"])
        cid = str(cell.get("id", ""))
        problems += [Problem(k, cid, "glue", ref, ref) for ref in glue_references(source) if ref not in glued]
        problems += [Problem(k, cid, "number", num, ctx) for num, ctx in stated_numbers(source, facts)]
        problems += [Problem(k, cid, "verdict", words, ctx) for words, ctx in stated_verdicts(source)]
        problems += [Problem(k, cid, "claim", str(c), " ".join(c.clause.split())[:120])
                     for c in claims.contradictions(source, checks)]
    return problems


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("notebooks", nargs="+", type=Path, help="executed notebooks (.ipynb)")
    args = ap.parse_args(list(argv) if argv is not None else None)
    import nbformat

    bad = 0
    for path in args.notebooks:
        # "04_benchmark.executed.ipynb" is notebook 04's run: its facts are 04's.
        problems = check_notebook(nbformat.read(path, as_version=4), path.name.split(".")[0])
        bad += len(problems)
        print(f"{path}: {len(problems)} problem(s)")
        for p in problems:
            print(f"  {p}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
