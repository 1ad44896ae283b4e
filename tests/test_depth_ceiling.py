"""The depth ceiling (freereg_lib.training.depth_ceiling): the resolution ceiling keeps holes and
constants, the error is exact on a hand-made case, and on a rooms pair the true depth's FreeReg-G
inlier ratio is above a depth blurred until its local shapes are gone."""
from __future__ import annotations

import json

import numpy as np
import pytest

from freereg_lib.training import depth_ceiling as C


def test_at_resolution_keeps_holes_and_constants():
    depth = np.full((480, 640), 2.5)
    depth[100:120, 200:260] = 0.0
    out = C.at_resolution(depth)
    assert out.shape == depth.shape and out.dtype == np.float64
    assert np.all(out[100:120, 200:260] == 0)
    assert np.allclose(out[300:, 400:], 2.5, atol=1e-5)


def test_at_resolution_loses_detail_finer_than_the_model_pixels():
    stripes = np.where((np.arange(640) // 2) % 2 == 0, 2.0, 3.0)[None].repeat(480, 0)  # 2-pixel stripes
    assert np.abs(C.at_resolution(stripes) - 2.5).max() < 0.15  # of 0.5


def test_error_bands_split_the_log_error_in_two():
    truth = np.full((120, 160), 2.0)
    truth[10:20, 30:60] = 0.0  # a hole
    stripes = np.where((np.arange(160) // 2) % 2 == 0, 1.1, 1 / 1.1)[None]  # 2-pixel stripes: all fine
    depth = np.where(truth > 0, truth * 1.3 * stripes, 0.0)  # one scale (all coarse) times the stripes
    coarse, fine = C.error_bands(depth, truth, sigma_px=8)
    valid = truth > 0
    np.testing.assert_allclose(coarse[valid] * fine[valid] / truth[valid], depth[valid], rtol=1e-12)  # the parts multiply back
    assert np.all(coarse[~valid] == 0) and np.all(fine[~valid] == 0)
    np.testing.assert_allclose(coarse[40:100, 60:130], 2.6, rtol=2e-3)  # the scale, the stripes averaged out
    np.testing.assert_allclose(fine[40:100, 60:130] / (2.0 * stripes[:, 60:130]), 1.0, atol=2e-3)
    # beside the hole the coarse band is the neighbours' average, not pulled towards exp(0) by the hole
    np.testing.assert_allclose(coarse[21, 30:60], 2.6, rtol=5e-3)


def test_mean_abs_error_counts_only_pixels_with_a_true_depth():
    truth = np.array([[1.0, 2.0], [0.0, 4.0]])
    depth = np.array([[1.5, 2.0], [9.0, 3.0]])
    assert C.mean_abs_error(depth, truth) == pytest.approx((0.5 + 0.0 + 1.0) / 3)


def test_the_true_depth_beats_a_blurred_one(tmp_path):
    from freereg_lib.data import sources

    out = tmp_path / "ceiling.json"
    C.main(["--split", "rooms-dev", "--pairs", "2", "--out", str(out)])
    res = json.loads(out.read_text())
    assert res["n_pairs"] == 2 and res["split"] == "rooms development"
    assert set(res["summary"]) == {"true", "true at 96 x 128"}

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.models import get_backend

    pair = list(sources.iter_pairs("synthetic_rooms", 2, seed=5150))[1]
    cfg = FreeRegConfig(seed=0)
    backend = get_backend("stub", cfg)
    true_ir, n_true = C.geometric_ir(pair, pair.depth_gt, backend, cfg)
    assert (true_ir, n_true) == (pytest.approx(res["rows"]["true"][1]["IR"]), res["rows"]["true"][1]["n_evaluable"])
    import cv2

    smooth = cv2.GaussianBlur(pair.depth_gt.astype(np.float32), (0, 0), 25).astype(np.float64)  # shapes blurred away
    rough_ir, n_rough = C.geometric_ir(pair, smooth, backend, cfg)
    assert n_true >= 3 and n_rough >= 3
    assert true_ir > 0.15 and rough_ir < 0.5 * true_ir
