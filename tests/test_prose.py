"""Prose that cannot drift from its output: :mod:`freereg_lib.report.prose` on a run and on planted faults.

* A contradiction planted into a hand-made tiny notebook (the prose says 384 channels beside a
  printed ``(1408, 304)``; "RR 50.0 %" beside a printed 33.3) is flagged, naming the cell; so is a
  ``{glue}`` name the run did not glue. The executed notebooks are checked where they run with other
  parameters (tests/test_notebooks.py: every run has no problem; faults planted into notebook 00's
  executed copy are flagged).
* The committed notebooks state no number by hand that is not exempt, and every glue name their
  Markdown references is glued by one of their code cells (a static check: no run needed).
"""
from __future__ import annotations

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
