"""The verdict of ``freereg register`` (REGISTERED / FAILED without ground truth): the rows its rule
is fitted and reported on are measured with the command's chain (``tools/verdict_holdout.py``);
the rule and its rates: ``tests/test_verdict_holdout.py``."""
from __future__ import annotations

import importlib.util
from pathlib import Path

from freereg_lib.pipeline import register as R

ROOT = Path(__file__).resolve().parents[1]


def test_the_rows_are_measured_with_the_commands_chain(tmp_path):
    spec = importlib.util.spec_from_file_location("verdict_holdout", ROOT / "tools" / "verdict_holdout.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    out = tmp_path / "rows.csv"
    rows = tool.half_rows("report", str(out), n_pairs=1, iters=300)
    assert rows["pair"].tolist() == ["icl/00110-00120"] * 4 and (rows["gap"] == 10).all()
    assert set(zip(rows["depth"], rows["solver"])) == {(d, s) for d in ("stub", "true") for s in ("kabsch", "pnp")}
    assert (rows["n_matches"] > 50).all() and {"success", "n_inliers", "scale", "RE", "TE"} <= set(rows)
    assert tool.half_rows("report", str(out), n_pairs=1, iters=300).equals(rows)  # a rerun skips what is there


def test_the_thresholds_are_per_solver_unless_given():
    assert R.verdict_thresholds("kabsch") == (R.MIN_INLIERS["kabsch"], R.MIN_INLIER_RATIO["kabsch"], R.MAX_SCALE)
    assert R.verdict_thresholds("pnp") == (R.MIN_INLIERS["pnp"], R.MIN_INLIER_RATIO["pnp"], R.MAX_SCALE)
    assert R.verdict_thresholds("pnp", 3, 0.5, 2) == (3, 0.5, 2.0)
