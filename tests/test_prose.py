"""Prose that cannot drift from its output: :mod:`freereg_lib.report.prose` on a run and on planted faults.

* A contradiction planted into a hand-made tiny notebook (the prose says 384 channels beside a
  printed ``(1408, 304)``; "RR 50.0 %" beside a printed 33.3) is flagged, naming the cell; so is a
  ``{glue}`` name the run did not glue. The executed notebooks are checked where they run with other
  parameters (tests/test_notebooks.py: every run has no problem; faults planted into notebook 00's
  executed copy are flagged).
* The committed notebooks state no number by hand that is not exempt, and every glue name their
  Markdown references is glued by one of their code cells (a static check: no run needed).
* Directions and descriptions (:mod:`freereg_lib.report.claims`): each contradiction a review quoted
  (:data:`PLANTED`), put beside the printed lines of the run it was quoted from (:data:`QUOTED_RUNS`), is
  flagged by reading the notebook's ``check:`` line, and not flagged beside checks that answer yes; the
  committed prose is flagged beside neither answer; a printed verdict its own numbers contradict ("holds"
  on 0 against 0) is flagged. tests/test_notebooks.py plants :data:`PLANTED` into every parameter run;
  ``FREEREG_PROSE_RUN=runs/reproduce`` does the same on a run of ``make reproduce``.
"""
from __future__ import annotations

import copy
import os
import re
from pathlib import Path

import pytest

from freereg_lib.report.prose import Problem, check_notebook, glue_references, stated_numbers, stated_verdicts

nbformat = pytest.importorskip("nbformat")

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
CHECKED = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))


def _tiny(markdown: str, printed: str, glued: dict[str, object] | None = None) -> dict:
    """A two-cell notebook: Markdown, then a code cell that printed ``printed`` and glued ``glued``."""
    nb = nbformat.v4.new_notebook()
    md = nbformat.v4.new_markdown_cell(markdown)
    md.id = "prose"
    code = nbformat.v4.new_code_cell("print(...)")
    code.id = "run"
    code.outputs = [nbformat.v4.new_output("stream", name="stdout", text=printed)]
    for name, value in (glued or {}).items():
        code.outputs.append(nbformat.v4.new_output(
            "display_data", data={"application/papermill.record/text/plain": repr(value)},
            metadata={"scrapbook": {"name": name, "mime_prefix": "application/papermill.record/"}}))
    nb.cells = [md, code]
    return nb


@pytest.mark.parametrize("markdown, printed, flagged", [
    ("The descriptors have 384 channels.", "descriptors: image (1408, 304), depth (1408, 304)", ["384"]),
    ("FreeReg registers RR 50.0 % of the pairs.", "RR with the fused matches: Kabsch 33.3, PnP 33.3", ["50.0 %"]),
    # The paper's own number passes only where the sentence says it is the paper's.
    ("Kabsch registers RR 63.8 % of the pairs.", "RR 33.3", ["63.8 %"]),
])
def test_a_contradiction_in_a_tiny_notebook_is_flagged(markdown, printed, flagged):
    problems = check_notebook(_tiny(markdown, printed), "tiny")
    assert [p.found for p in problems] == flagged
    assert all(isinstance(p, Problem) and p.cell == 0 and p.cell_id == "prose" for p in problems)


@pytest.mark.parametrize("markdown, flagged", [
    # The contradictions of an earlier round, planted back as hand-typed verdicts.
    ("PnP at least level with Kabsch at the largest error: holds.", ["holds"]),
    ("The paper's Table 5 claim (PnP above Kabsch) does not hold here.", ["does not hold"]),
    ("Fine-tuning raises IR and RR: it holds in the mean.", ["holds"]),
    ("Fused above both halves: opposite direction.", ["opposite direction"]),
    # A verb about contents is no verdict.
    ("The cloud holds no points of that object, and `verdict holds` is code.", []),
])
def test_a_verdict_typed_in_prose_is_flagged(markdown, flagged):
    problems = check_notebook(_tiny(markdown, "opposite direction, significant: PnP 8.5 vs Kabsch 15.0"), "tiny")
    assert [p.found for p in problems if p.kind == "verdict"] == flagged


def test_glued_numbers_paper_numbers_and_names_of_things_pass():
    markdown = ("The descriptors have {glue:text}`channels` channels, and RR is {glue:text}`rr:.1f` %; the paper's "
                "RR is 63.8 % (Table 1, main results). The layers (0, 4, 6) of Table 2 rows j-m, Sec. 3.4, Fig. 4c, "
                "notebook 03 and `range(1000, 0, -50)` name things.")
    nb = _tiny(markdown, "(1408, 304)\nRR 33.3", glued={"channels": 304, "rr": 33.33})
    assert check_notebook(nb, "tiny") == []
    assert [p.found for p in check_notebook(_tiny(markdown, "", glued={"channels": 304}), "tiny")] == ["rr"]


@pytest.mark.parametrize("path", CHECKED, ids=lambda p: p.stem)
def test_the_committed_notebooks_state_no_number_by_hand_and_glue_what_they_reference(path):
    nb = nbformat.read(path, as_version=4)
    from freereg_lib.report.prose import COMMON, FACTS

    facts = COMMON + FACTS.get(path.stem, ())
    typed = [(c.get("id"), n, ctx) for c in nb.cells if c.cell_type == "markdown"
             for n, ctx in stated_numbers(c.source, facts)]
    assert not typed, f"{path.name}: numbers typed by hand (glue them, or declare a fact in prose.FACTS): {typed}"
    verdicts = [(c.get("id"), w, ctx) for c in nb.cells if c.cell_type == "markdown" for w, ctx in stated_verdicts(c.source)]
    assert not verdicts, f"{path.name}: verdicts typed by hand (print them through the vocabulary): {verdicts}"
    # Every referenced name must be glued by a code cell (an f-string name matches any text in its braces).
    glue_calls = [re.sub(r"\\\{[^}]*\\\}", ".+", re.escape(m.group(1)))
                  for c in nb.cells if c.cell_type == "code"
                  for m in re.finditer(r"""\bglue\(\s*f?["']([^"']+)["']""", c.source)]
    missing = [n for c in nb.cells if c.cell_type == "markdown" for n in glue_references(c.source)
               if not any(re.fullmatch(g, n) for g in glue_calls)]
    assert not missing, f"{path.name}: glue names referenced but glued by no code cell: {missing}"


# --------------------------------------------------------------------------------------
# Directions and descriptions (freereg_lib.report.claims): the contradictions a review quoted, planted back.

from freereg_lib.report import claims  # noqa: E402

# {notebook: sentences its Markdown once stated, each contradicted by that run's output}. Each is checkable
# against a `check:` line the notebook now prints; tests/test_notebooks.py plants them into every
# parameter run, and test_the_executed_notebooks_of_a_run_... into a run of `make reproduce`.
PLANTED = {
    "00_preliminaries": [
        "`fill_in_multiscale` dilates near, middle and far points with their own kernels, so near objects win, and it "
        "leaves the region above the topmost measurement empty rather than inventing a sky depth.",
        "Neither variant invents depth above the topmost LiDAR ring (we run both without extrapolation), so the sky "
        "stays empty.",
    ],
    "01_diffusion_features": [
        "What to look for: the diffusion features put matches on the right *object*, but they are coarse.",
        "FreeReg-D matches by mutual nearest neighbours; the matches land on the right objects but are coarse.",
    ],
    "02_geometric_features": [
        "Kabsch solves with the depth, so its recall falls and its errors grow as the depth error grows.",
        "PnP solves without the depth, and loses only what the matches lose.",
        "PnP is at least level with Kabsch at the largest error.",
    ],
    "03_fusion": [
        "Diffusion colours follow objects and agree across the two sides; geometric colours follow local shape.",
        "The fused map keeps the high values where both agree, so its peak is both on the right object and near "
        "the right place.",
    ],
    "05_your_data": [
        "Each candidate runs the whole chain; the one whose pose has the most RANSAC inliers (with a plausible "
        "scale) is kept, then the cloud is rendered again from the estimated camera pose.",
    ],
}

# The printed lines of the runs a review quoted, computed as the notebooks compute them now.
RR_KABSCH, RR_PNP, FMR = [33, 33, 33, 67, 0], [0, 0, 0, 0, 0], [100, 100, 100, 100, 67]
QUOTED_RUNS = {
    "00_preliminaries": ["fill_in_multiscale: 100.0% of pixels have depth"] + [
        claims.check_line(f"{name}: the sky above the topmost ring stays empty", ok, evidence)
        for name, ok, evidence in (("raw", True, "0.0% of its pixels have depth"),
                                   ("fill_in_fast", False, "2.1% of its pixels have depth, median 10 m"),
                                   ("fill_in_multiscale", False, "100.0% of its pixels have depth, median 255 m"))],
    "01_diffusion_features": [
        "{'IR': 0.109, 'IN': 6, 'RE': 21.824, 'TE': 1.718, 'registered': False, 'n_evaluable': 55}",
        claims.check_line("most matches land on the right object (IR at least 50 %)", 0.109 >= 0.5,
                          "IR 10.9 % of 55 evaluable matches, tau_c 0.3 m")],
    "02_geometric_features": [
        claims.check_line("Kabsch's RR falls with the depth error", claims.falls(RR_KABSCH), "RR 33, 33, 33, 67, 0 %"),
        claims.check_line("Kabsch's median RE grows with the depth error", claims.grows([35.0, 38.7, 47.8, 55.4, 10.4]),
                          "35.0, 38.7, 47.8, 55.4, 10.4 deg"),
        claims.check_line("PnP loses only what the matches lose (at the smallest error its RR at least Kabsch's, "
                          "then down no more than FMR)", RR_PNP[0] >= RR_KABSCH[0], "PnP 0 %, Kabsch 33 %"),
        claims.check_line("PnP at least level with Kabsch at the largest error", None, "PnP 0 %, Kabsch 0 %", "both 0 %")],
    "03_fusion": [
        claims.check_line("diffusion colours agree across the two sides (true partners' colours at most half as far "
                          "apart as random pairs')", False, "0.97 x as far apart, over 212 true partners"),
        claims.check_line("the fused similarity's peak lies at the right place (within tau_c of the true point)",
                          False, "1.84 m from it, 0 px from the depth map's border")],
    "05_your_data": [
        "  origin             31776     133      18   0.45  <- chosen scale 0.45 is implausible: not scored",
        claims.check_line("the kept candidate camera has a plausible scale", False,
                          "origin, scale 0.45; plausible 0.67 to 1.50")],
}


def _answer(lines: list[str], ok: bool) -> list[str]:
    """The same check lines, each answering ``ok`` (yes or no)."""
    return [re.sub(r"^(check: .+): (?:yes|no|not shown \(.*?;) ?\(?(.*?)\)?$",
                   lambda m: f"{m.group(1)}: {'yes' if ok else 'no'} ({m.group(2)})", line) for line in lines]


@pytest.mark.parametrize("stem", PLANTED)
def test_each_quoted_contradiction_is_flagged_by_reading_the_printed_check(stem):
    printed = "\n".join(QUOTED_RUNS[stem])
    for sentence in PLANTED[stem]:
        flagged = [p for p in check_notebook(_tiny(sentence, printed), stem) if p.kind == "claim"]
        assert flagged and all(p.cell_id == "prose" for p in flagged), (sentence, printed)
        # The same sentence beside a run whose checks all answer yes is true there: not flagged. So the
        # check reads the output, not the sentence.
        assert not [p for p in check_notebook(_tiny(sentence, "\n".join(_answer(QUOTED_RUNS[stem], True))), stem)
                    if p.kind == "claim"], sentence
        # Without any printed check the claim is not judged (it is a description to phrase as what to look for).
        assert not [p for p in check_notebook(_tiny(sentence, "no check printed"), stem) if p.kind == "claim"]


@pytest.mark.parametrize("sentence, flagged", [
    ("The sky stays empty.", True),
    ("The sky does not stay empty.", False),          # a denial agrees with a check that says no
    ("The sky should stay empty.", False),            # what to look for
    ("In the paper the sky stays empty.", False),     # the paper's reading
    ("Whether the sky stays empty is for the run to show.", False),
    ("As the sky stays empty, nothing else is drawn.", False),  # a condition, not a claim
])
def test_denials_hedges_and_conditions(sentence, flagged):
    nb = _tiny(sentence, claims.check_line("fill_in_multiscale: the sky above the topmost ring stays empty", False,
                                           "100.0% of its pixels have depth"))
    assert bool([p for p in check_notebook(nb, "tiny") if p.kind == "claim"]) is flagged


def test_a_claim_about_a_rival_is_not_read_against_another_check():
    nb = _tiny("The geometric colours agree across the two sides.",
               claims.check_line("diffusion colours agree across the two sides", False, "0.97 x"))
    assert not check_notebook(nb, "tiny")


@pytest.mark.parametrize("line, problem", [
    # The printed verdict a review quoted (0 against 0), in the old form and in the vocabulary's.
    ("PnP at least level with Kabsch at the largest error: holds (PnP 0 %, Kabsch 0 %)", "not in the vocabulary's form"),
    ("PnP at least level with Kabsch (RR): holds: PnP 0.0 [0.0, 0.0] vs Kabsch 0.0 [0.0, 0.0], +0.0 points, "
     "p = 1.0000; n = 30 pairs, 30 pairs", "cannot be told (both values are 0)"),
    ("fused above FreeReg-G (IR): holds: FreeReg 20.3 vs FreeReg-G 19.4, +0.9 points, p = 0.2659; n = 100 pairs, x",
     "same direction, not significant"),
    ("fused above FreeReg-G (IR): holds: FreeReg 20.3 vs FreeReg-G 4.3, +16.0 points, no p; n = 6 pairs, x",
     "cannot be told (6 pairs, fewer than 30)"),
    ("fused above FreeReg-G (IR): holds: FreeReg 20.3 [17.4, 23.2] vs FreeReg-G 4.3 [3.7, 4.9], +16.0 points, "
     "p < 0.0001; n = 100 pairs, micro", None),
    ("the colours no depth map holds: +3.1 (p = 0.0100)", None),
])
def test_a_printed_verdict_must_be_the_vocabularys_for_its_numbers(line, problem):
    found = [p for p in check_notebook(_tiny("Nothing typed.", line), "tiny") if p.kind == "printed verdict"]
    assert (problem is None and not found) or (found and problem in found[0].found), found
    assert (claims.verdict_problem(line) is None) is (problem is None)


def test_every_line_the_vocabulary_prints_passes_the_printed_verdict_check():
    from freereg_lib.report import vocabulary as V

    for a, b, n in (([1] * 30 + [0] * 10, [0] * 30 + [1] * 10, 40), ([0] * 40, [0] * 40, 40), ([1, 0] * 3, [0, 1] * 3, 6),
                    ([1, 0] * 20, [0, 1] * 20, 40), ([0] * 30 + [1] * 10, [1] * 30 + [0] * 10, 40)):
        line = V.paired_line("A above B (RR)", "A", a, "B", b, f"{n} pairs")
        assert claims.verdict_problem(line) is None, line


@pytest.mark.parametrize("path", CHECKED, ids=lambda p: p.stem)
def test_the_committed_prose_stands_whatever_its_checks_answer(path):
    """The tree's Markdown states no claim that its notebook's checks could contradict: beside the check lines
    the notebook prints (as in the quoted runs), all answering yes or all no, nothing is flagged: what a
    check decides is said as what to look for, or as the check's reading."""
    nb = nbformat.read(path, as_version=4)
    lines = [line for line in QUOTED_RUNS.get(path.stem, []) if line.startswith("check:")]
    printed_by_code = "".join(c.source for c in nb.cells if c.cell_type == "code")
    assert ("claims.check_line(" in printed_by_code) is bool(lines), f"{path.name}: QUOTED_RUNS and its checks differ"
    for ok in (True, False):
        code = nbformat.v4.new_code_cell("print(...)")
        code.outputs = [nbformat.v4.new_output("stream", name="stdout", text="\n".join(_answer(lines, ok)))]
        md = [c for c in nb.cells if c.cell_type == "markdown"]
        found = [(p.cell_id, p.found) for p in check_notebook({"cells": md + [code]}, path.stem) if p.kind == "claim"]
        assert not found, f"{path.name}: claims a printed check could contradict: {found}"


def assert_planted_contradictions_flagged(nb, stem: str) -> list[str]:
    """Plant each of ``stem``'s :data:`PLANTED` sentences into the executed notebook ``nb``'s Markdown:
    a printed check must be about it, and it is flagged exactly when that check contradicts it. Returns
    what was flagged (for a report); tests/test_notebooks.py calls this on every parameter run."""
    checks = claims.printed_checks(nb)
    flagged = []
    for sentence in PLANTED.get(stem, []):
        judged = claims.judgements(sentence, checks)
        assert judged, f"{stem}: no printed check line is about {sentence!r} (checks: {checks})"
        planted = copy.deepcopy(nb)
        first = next(c for c in planted["cells"] if c["cell_type"] == "markdown")
        first["source"] += "\n\n" + sentence
        found = [p for p in check_notebook(planted, stem) if p.kind == "claim"]
        assert bool(found) is any(j.contradicted for j in judged), (sentence, [str(j) for j in judged], found)
        flagged += [str(p) for p in found]
    return flagged


PROSE_RUN = os.environ.get("FREEREG_PROSE_RUN")  # a folder of executed notebooks, e.g. runs/reproduce


@pytest.mark.skipif(not PROSE_RUN, reason="set FREEREG_PROSE_RUN=<run folder> (e.g. runs/reproduce after "
                                          "`make reproduce`) to check that run's executed notebooks")
def test_the_executed_notebooks_of_a_run_pass_and_flag_the_planted_contradictions():
    """The prose check on a real run: no problem in any executed notebook, and every quoted contradiction,
    planted back, is read against the check its notebook printed and flagged where that run contradicts it."""
    paths = sorted((ROOT / PROSE_RUN).glob("[0-9][0-9]_*.ipynb"))
    assert paths, f"{PROSE_RUN}: no executed notebooks"
    for path in paths:
        stem = path.name.split(".")[0]
        nb = nbformat.read(path, as_version=4)
        assert check_notebook(nb, stem) == [], [str(p) for p in check_notebook(nb, stem)]
        assert_planted_contradictions_flagged(nb, stem)
