"""The one verdict vocabulary (freereg_lib.report.vocabulary), and that no other code writes a verdict."""
from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import numpy as np
import pytest

from freereg_lib.report import vocabulary as V

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("diff, p, n, sign, both_zero, word", [
    (5.0, 0.01, 100, 1, False, "holds"),
    (5.0, 0.20, 100, 1, False, "same direction, not significant"),
    (-5.0, 0.01, 100, 1, False, "opposite direction, significant"),
    (-5.0, 0.30, 100, 1, False, "opposite direction, not significant"),
    (-5.0, 0.01, 100, -1, False, "holds"),  # a claim that the first side is below
    (0.0, 1.0, 100, 1, False, "no difference"),
    (0.0, 1.0, 100, 1, True, "cannot be told (both values are 0)"),
    (40.0, 0.001, 29, 1, False, "cannot be told (29 pairs, fewer than 30)"),
    (5.0, None, 100, 1, False, "cannot be told (no paired test)"),
])
def test_verdict_words(diff, p, n, sign, both_zero, word):
    assert V.verdict(diff, p, n, sign, both_zero) == word


def test_a_verdict_line_names_values_intervals_difference_p_pairs_and_setting():
    line = V.verdict_line("fused above FreeReg-G (IR)", V.Value("FreeReg", 20.26, (17.39, 23.25)),
                          V.Value("FreeReg-G", 4.29, (3.7, 4.9)), 15.97, 4.9e-5, 100, "micro, FPFH voxel 0.05 m")
    assert line == ("fused above FreeReg-G (IR): holds: FreeReg 20.3 [17.4, 23.2] vs FreeReg-G 4.3 [3.7, 4.9], "
                    "+16.0 points, p < 0.0001; n = 100 pairs, micro, FPFH voxel 0.05 m")


def test_paired_line_tests_the_pairs_and_withholds_a_verdict_on_few():
    a, b = np.r_[np.ones(30), np.zeros(10)], np.r_[np.zeros(30), np.ones(10)]
    line = V.paired_line("A above B (RR)", "A", a, "B", b, "40 pairs")
    assert line.startswith("A above B (RR): holds: A 75.0 [") and "+50.0 points, p = 0.0026; n = 40 pairs" in line
    few = V.paired_line("A above B (RR)", "A", a[:6], "B", b[:6], "6 live pairs")
    assert few.startswith("A above B (RR): cannot be told (6 pairs, fewer than 30): A 100.0")
    assert "no p" in few


# Files where "holds" is a verb of a message, not a verdict (reason beside each).
VERB_ONLY = {
    "freereg_lib/commands/book_inputs.py": "'--out X: holds the run folder' (a folder's contents)",
    "freereg_lib/commands/user_inputs.py": "'K.txt holds 5 numbers' (a file's contents)",
}
# A verdict word alone or closing a claim ("holds", "holds here", "does not hold (...)"), also after a
# claim's colon inside a longer literal or an f-string's part (f"{claim}: holds ({p})"); a message's verb
# ("... holds no point", "the map holds: 3") has an object after it or no colon before it.
VERDICT_WORD = re.compile(r"(?:^|:)\s*(holds|does not hold|same direction, not significant|"
                          r"opposite direction, (?:not )?significant)(\s*$|\s+here\b|\s+in the mean|\s*[(:,;])")


def _verdict_literals(tree: ast.AST):
    """String literals that start with a verdict word, except docstrings and dictionary keys."""
    skip = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            skip.add(id(body[0].value))
        if isinstance(node, ast.Dict):
            skip.update(id(k) for k in node.keys if k is not None)
        if isinstance(node, ast.Subscript):
            skip.add(id(node.slice))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" and node.args:
            skip.add(id(node.args[0]))
    for node in ast.walk(tree):
        if (isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip
                and VERDICT_WORD.search(node.value)):
            yield node.lineno, node.value


def test_no_code_but_the_vocabulary_writes_a_verdict_word():
    found = []
    for path in sorted((ROOT / "freereg_lib").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "freereg_lib/report/vocabulary.py" or rel in VERB_ONLY:
            continue
        found += [f"{rel}:{ln}: {text!r}" for ln, text in _verdict_literals(ast.parse(path.read_text()))]
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        for cell in json.loads(path.read_text())["cells"]:
            if cell["cell_type"] == "code":
                try:
                    tree = ast.parse("".join(cell["source"]))
                except SyntaxError:  # a cell with IPython magics
                    continue
                found += [f"{path.name}: {text!r}" for _, text in _verdict_literals(tree)]
    assert not found, "verdict words written outside freereg_lib/report/vocabulary.py:\n" + "\n".join(found)


@pytest.mark.parametrize("source, found", [
    ('print(f"fused above both: {\'holds\' if a > b else \'does not hold\'} here")', ["holds", "does not hold"]),
    # An f-string or a format string that writes the verdict after the claim's colon.
    ('print(f"{claim}: holds ({a} vs {b})")', [": holds ("]),
    ('line = "%s: holds, p = %.4f" % (claim, p)', ["%s: holds, p = %.4f"]),
    ('print(f"PnP at least level with Kabsch: opposite direction, significant: {p}")',
     ["PnP at least level with Kabsch: opposite direction, significant: "]),
    ('s = claim + ": does not hold here"', [": does not hold here"]),
    # A verb of a message is no verdict.
    ('print(f"the colours no depth map holds: {x}", "the cloud holds no point", {"holds": 1}["holds"])', []),
])
def test_the_scan_catches_a_planted_verdict(source, found):
    assert [t for _, t in _verdict_literals(ast.parse(source))] == found
