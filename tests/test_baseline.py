"""The position-only baseline row of Table 1: matches from pixel positions alone,
the same solvers and scores, and verdict lines that say when a method does not beat it."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd

from freereg_lib import pipeline
from freereg_lib.config import config_for
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.features import baseline
from freereg_lib.geometry import keypoints
from freereg_lib.models import get_backend


def test_position_matches_pair_the_same_or_nearest_pixel():
    uv_img = keypoints.grid_keypoints((40, 40), (4, 4))
    uv_dep = keypoints.grid_keypoints((20, 20), (4, 4))  # the depth view at half the size
    keep = np.ones(len(uv_dep), dtype=bool)
    keep[5] = False  # no depth at one keypoint: its image keypoint has no partner left
    feats = SimpleNamespace(uv_image=uv_img, uv_depth=uv_dep[keep])
    m = baseline.position_matches(feats, (40, 40), (20, 20))
    assert len(m) == 15 and len(set(m.idx_image)) == len(set(m.idx_depth)) == 15  # one to one
    mapped = (uv_img[m.idx_image] + 0.5) / 2 - 0.5
    assert np.abs(mapped - uv_dep[keep][m.idx_depth]).max() < 0.5  # the same pixel
    assert 5 not in m.idx_image


def test_with_baseline_adds_each_solver_once():
    v = baseline.with_baseline([["FreeReg-D", "pnp"], ["FreeReg-G", "kabsch"], ["FreeReg", "pnp"]])
    assert v[-2:] == [(baseline.METHOD, "pnp"), (baseline.METHOD, "kabsch")] and len(v) == 5
    assert baseline.with_baseline(v) == v


def test_the_baseline_runs_in_the_benchmark_loop_with_the_same_solvers():
    pair = ICLSample().pair(0, 10)  # a small motion: the same pixel is nearly the right match
    cfg = config_for("icl", ransac_iters=2000)
    variants = baseline.with_baseline([("FreeReg-G", "kabsch")])
    rows = pipeline.run_pair(pair, get_backend("stub", cfg), cfg, variants)
    base = [r for r in rows if r["method"] == baseline.METHOD]
    assert len(base) == 1 and base[0]["solver"] == "kabsch" and base[0]["error"] == "", base
    assert math.isnan(base[0]["w"]) and base[0]["n_matches"] > 100 and base[0]["IR"] > 0.2
    table = pipeline.summarize(rows, cfg)
    assert set(table["method"]) == {"FreeReg-G", baseline.METHOD}


def test_verdict_lines_say_when_a_method_does_not_beat_the_baseline():
    table = pd.DataFrame([
        {"method": "FreeReg-D", "solver": "pnp", "RR": 33.3, "IR": 20.0},
        {"method": "FreeReg", "solver": "pnp", "RR": 80.0, "IR": 45.0},
        {"method": "FreeReg-G", "solver": "kabsch", "RR": 50.0, "IR": 30.0},
        {"method": baseline.METHOD, "solver": "pnp", "RR": 66.7, "IR": 25.0},
    ])
    lines = baseline.verdict_lines(table)
    assert len(lines) == 2  # no baseline with Kabsch: FreeReg-G is not compared
    assert lines[0].startswith("FreeReg-D + pnp") and "does NOT beat the position-only baseline (RR, IR" in lines[0]
    assert lines[1].startswith("FreeReg + pnp") and lines[1].endswith("beats the position-only baseline")
