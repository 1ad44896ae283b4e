"""The verdict rule of ``freereg register``: fitted on some real frames, reported on others.

``tests/fixtures/verdict_icl_fit_rows.csv`` and ``verdict_icl_report_rows.csv`` were written by
``python tools/verdict_holdout.py fit|report --out ...``: every pair within frames 0-100 of the
shipped ICL sample and every pair within frames 110-210 (gaps 10-100), each with the stub's and the
true depth, by Kabsch and by PnP. The command's thresholds must be ``fit_rule`` of the first; the
rates docs/your_data.md states are counted here on the second with the command's own verdict, so a
change of the thresholds or of the rows fails until the docs are re-measured."""
from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from freereg_lib.commands import verdict_measure as V

ROOT = Path(__file__).resolve().parents[1]
FIT = ROOT / "tests" / "fixtures" / "verdict_icl_fit_rows.csv"
REPORT = ROOT / "tests" / "fixtures" / "verdict_icl_report_rows.csv"


@pytest.fixture(scope="module")
def fit():
    return pd.read_csv(FIT)


@pytest.fixture(scope="module")
def report():
    return pd.read_csv(REPORT)


def test_the_fit_and_report_rows_share_no_frame(fit, report):
    assert V.frames_of(fit) == set(V.SPLIT["fit"]) and V.frames_of(report) == set(V.SPLIT["report"])
    assert not V.frames_of(fit) & V.frames_of(report)
    for half, table in (("fit", fit), ("report", report)):
        want = [f"icl/{i:05d}-{j:05d}" for i, j in V.pairs_within(V.SPLIT[half])]
        assert sorted(table["pair"].unique()) == want and len(want) == 55 and len(table) == 4 * 55
        assert set(table.groupby(["depth", "solver"]).size()) == {55}


def _rows(solver: str, good: list[tuple[int, int, float]], other=()) -> list[dict]:
    """Hand-made rows: ``good`` (inliers, matches, scale) within (5 deg, 0.1 m); ``other`` any rows."""
    return ([{"solver": solver, "success": True, "n_inliers": n, "n_matches": m, "scale": s, "RE": 1.0, "TE": 0.05}
             for n, m, s in good] + [{"solver": solver, **r} for r in other])


def test_fit_rule_takes_a_fifth_below_the_weakest_right_pose():
    table = pd.DataFrame(
        _rows("kabsch", [(50, 200, 1.1), (40, 100, 0.95)],
              # wrong, right but not within (5 deg, 0.1 m), unsolved: none of them moves a threshold
              [{"success": True, "n_inliers": 5, "n_matches": 200, "scale": 2.0, "RE": 40.0, "TE": 2.0},
               {"success": True, "n_inliers": 10, "n_matches": 200, "scale": 1.4, "RE": 8.0, "TE": 0.2},
               {"success": False, "n_inliers": 0, "n_matches": 200, "scale": 1.0, "RE": 1.0, "TE": 0.01}])
        + _rows("pnp", [(15, 180, 1.0), (30, 100, 1.0)],
                [{"success": True, "n_inliers": 12, "n_matches": 300, "scale": 1.0, "RE": 90.0, "TE": 3.0}]))
    # Kabsch: 0.8 x 40 = 32 inliers; 0.8 x 25 % = 20 %; the scale farthest from 1 is 1.1 (0.95 is
    # 1 / 1.053), 1.1 ** 1.25 = 1.126, rounded up to 1.15. PnP: 0.8 x 15 = 12; 0.8 x 8.33 % = 6.67 %,
    # rounded down to 6.5 %.
    rule = V.fit_rule(table)
    assert rule == {"min_inliers": {"kabsch": 32, "pnp": 12}, "min_ratio": {"kabsch": 0.2, "pnp": 0.065},
                    "max_scale": 1.15}
    assert V.verdicts(table, rule).tolist() == [True, True, False, False, False, True, True, False]
    with pytest.raises(ValueError, match="no right pnp pose"):
        V.fit_rule(table[table["solver"] == "kabsch"])


def test_the_command_uses_the_rule_fitted_on_the_fit_rows(fit):
    assert V.fit_rule(fit) == V.command_rule()
    assert V.command_rule() == {"min_inliers": {"kabsch": 48, "pnp": 16}, "min_ratio": {"kabsch": 0.24, "pnp": 0.075},
                                "max_scale": 1.25}
    assert V.rates(fit, V.verdicts(fit))["FN"] == 0  # by construction


def test_the_documented_rates_on_the_report_frames(report):
    got = {s: V.rates(sub, V.verdicts(sub)) for s, sub in report.groupby("solver")}
    got["all"] = V.rates(report, V.verdicts(report))
    keys = ("rows", "good", "FN", "wrong", "FP", "right", "missed_right")
    assert {s: tuple(r[k] for k in keys) for s, r in got.items()} == {
        "kabsch": (110, 67, 5, 1, 0, 109, 19),
        "pnp": (110, 35, 2, 26, 7, 84, 10),
        "all": (220, 102, 7, 27, 7, 193, 29)}
    assert got["all"]["FN_ci"] == pytest.approx((0.028, 0.136), abs=5e-4)
    assert got["all"]["FP_ci"] == pytest.approx((0.111, 0.463), abs=5e-4)
    doc = (ROOT / "docs" / "your_data.md").read_text()
    for line in V.table_lines(report):
        assert line in doc, line


def test_clopper_pearson():
    assert V.clopper_pearson(0, 36)[0] == 0 and V.clopper_pearson(0, 36)[1] == pytest.approx(0.0974, abs=1e-4)
    assert V.clopper_pearson(5, 27) == pytest.approx((0.0630, 0.3808), abs=1e-4)
    assert V.clopper_pearson(3, 3)[1] == 1.0
