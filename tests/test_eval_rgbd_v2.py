"""The RGBD-Scenes-v2 protocol (Table 5): its metrics on hand-made cases, the summary and bad
arguments of training/evaluate_rgbd_v2, the verdict on a summary, and the loader on a fake folder."""
from __future__ import annotations

import json
import math
import pickle

import cv2
import numpy as np
import pytest

from freereg_lib.data.datasets import registry
from freereg_lib.data.datasets.rgbd_scenes_v2 import RGBDScenesV2
from freereg_lib.geometry import cameras
from freereg_lib.training import evaluate_rgbd_v2 as ev
from freereg_lib.training import verdicts_appendix


def test_the_inlier_ratio_counts_matches_within_5_cm_under_the_true_pose():
    T = cameras.make_pose(np.eye(3), np.array([0.0, 0.0, 1.0]))  # cloud 1 m behind the camera's origin
    pc = np.zeros((4, 3))
    img = np.array([[0, 0, 1.0], [0.049, 0, 1.0], [0.05, 0, 1.0], [0, 0.2, 1.0]])
    assert ev.inlier_ratio(img, pc, T) == 0.5  # 0 and 4.9 cm in; exactly 5 cm is out (strict)
    img[3] = np.nan  # a pixel without true depth is not counted
    assert ev.inlier_ratio(img, pc, T) == pytest.approx(2 / 3)
    assert ev.inlier_ratio(np.full((2, 3), np.nan), np.zeros((2, 3)), T) == 0.0
    assert ev.inlier_ratio(np.zeros((0, 3)), np.zeros((0, 3)), T) == 0.0


def test_fmr_counts_pairs_with_an_inlier_ratio_of_at_least_10_percent():
    assert ev.feature_match_recall([0.1, 0.0999, 0.5, 0.0]) == 0.5
    assert math.isnan(ev.feature_match_recall([]))


def test_the_rmse_is_between_the_cloud_under_the_true_and_the_estimated_pose():
    pts = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [2.0, 3.0, 4.0]])
    T_gt = cameras.make_pose(np.eye(3), np.array([0.1, 0.2, 0.3]))
    T_est = cameras.make_pose(np.eye(3), np.array([0.1, 0.2, 0.3 + 0.08]))
    assert ev.registration_rmse(pts, T_gt, T_est) == pytest.approx(0.08)
    R = cameras.make_pose(np.array([[-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]]), np.zeros(3))  # 180 deg about z
    # each point moves by twice its distance to the z axis: sqrt(mean([4, 4, 0, 52]))
    assert ev.registration_rmse(pts, np.eye(4), R) == pytest.approx(math.sqrt(15.0))


def test_rr_needs_an_rmse_below_10_cm_and_a_solve():
    assert ev.registration_recall([0.05, 0.0999, 0.1, None, float("nan")]) == 0.4


def test_coarse_keypoints_are_every_strided_row_and_column_of_the_grid():
    from freereg_lib.geometry import keypoints

    uv = keypoints.grid_keypoints((480, 640), (8, 8))
    idx = ev.coarse_indices(uv, (480, 640), (8, 8), 2)
    assert idx.tolist() == [r * 8 + c for r in range(0, 8, 2) for c in range(0, 8, 2)]
    kept = uv[[0, 1, 2, 17, 18]]  # the depth side keeps only the keypoints with depth
    assert ev.coarse_indices(kept, (480, 640), (8, 8), 2).tolist() == [0, 2, 4]


def test_reachable_is_the_share_of_image_keypoints_with_a_cloud_keypoint_within_5_cm():
    img = np.array([[0, 0, 1.0], [1.0, 0, 1.0], [np.nan, np.nan, np.nan]])
    pc = np.array([[0.01, 0, 1.0], [5.0, 5.0, 5.0]])
    assert ev.reachable(img, pc, np.eye(4)) == 0.5


def _rec(k, ir, rmse_k, rmse_p):
    row = lambda s, r: {"solver": s, "n_matches": 10, "n_evaluable": 10, "IR": ir, "reachable": 0.5,  # noqa: E731
                        "RMSE": r, "RE": None if r is None else 30 * r, "TE": None if r is None else r,
                        "error": "" if r is not None else "failed"}
    return {"k": k, "pair_seed": k, "pair": f"p{k}", "label": "micro", "seconds": 2.0, "load_average": 1.0,
            "rows": [row("kabsch", rmse_k), row("pnp", rmse_p)]}


def _summary():
    recs = [_rec(0, 0.3, 0.5, 0.05), _rec(1, 0.05, None, 0.02), _rec(2, 0.2, 0.01, 0.5), _rec(3, 0.1, 0.3, 0.09)]
    return ev.summarize(recs, "test")


def test_the_summary_counts_ir_fmr_rr_and_the_paired_difference():
    res = _summary()
    k, p = res["results"]["kabsch"], res["results"]["pnp"]
    assert res["n_pairs"] == 4 and res["matcher"] == ev.MATCHER
    assert k["IR"]["mean"] == pytest.approx(16.25) and p["IR"]["mean"] == pytest.approx(16.25)
    assert k["FMR"]["mean"] == 75.0  # 0.3, 0.2 and 0.1 (>= 10 %)
    assert k["RR"]["mean"] == 25.0 and p["RR"]["mean"] == 75.0 and k["errors"] == 1
    t = res["tests"]["RR: pnp - kabsch"]
    assert t["diff"] == 50.0 and t["diff_ci"][0] <= 50.0 <= t["diff_ci"][1] and 0 < t["p"] <= 1
    # the main RR (RE < 20 deg, TE < 0.5 m; here RE = 30 RMSE, TE = RMSE): Kabsch 0.01 and 0.3 (0.5: TE
    # not below 0.5; None: failed), PnP 0.05, 0.02, 0.09 (0.5: TE not below 0.5)
    assert k["RR_main"]["mean"] == 50.0 and p["RR_main"]["mean"] == 75.0
    assert res["tests"]["RR_main: pnp - kabsch"]["diff"] == 25.0
    assert k["RMSE_median"] == pytest.approx(0.4) and p["RMSE_median"] == pytest.approx(0.07)
    assert "FreeReg+pnp" in ev.report(res) and "+50.0 points" in ev.report(res)


def test_the_verdict_reads_the_summary(tmp_path, monkeypatch):
    path = tmp_path / "rgbd.json"
    path.write_text(json.dumps(_summary()))
    monkeypatch.setattr(verdicts_appendix, "RGBD_V2_JSON", path)
    lines = verdicts_appendix.table5()
    text = "\n".join(lines)
    assert "RR 34.1" in text and "57.3" in text, text  # the paper's Kabsch and PnP means
    assert "PnP above Kabsch at RR (RMSE < 10 cm), the paper: +23.2 points: cannot be told (4 pairs, fewer than 30)" in text, text
    assert "PnP above Kabsch at the main RR (RE < 20 deg, TE < 0.5 m): cannot be told (4 pairs" in text, text
    assert "4 synthetic test pairs" in text, text
    assert "PnP 75.0 [25.0, 100.0] vs Kabsch 50.0 [0.0, 100.0], +25.0 points" in text, text


@pytest.mark.parametrize("argv, message", [
    (["--pairs", "0", "--rows", "r.jsonl"], "--pairs 0: must be >= 1"),
    (["--summarize", "--rows", "missing.jsonl"], "no such file"),
])
def test_bad_arguments_stop_with_one_line(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        ev.main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err


# ---- the loader ------------------------------------------------------------------------

K = np.array([[500.0, 0, 31.5], [0, 500.0, 23.5], [0, 0, 1]])


def _fake(root, drop: str | None = None):
    """A one-pair RGBD-Scenes-v2 folder in 2D3D-MATR's layout (64 x 48 images)."""
    scene = "rgbd-scenes-v2-scene_11"
    d = root / "data" / scene
    (d / "seq").mkdir(parents=True)
    (root / "metadata").mkdir()
    np.savetxt(d / "camera-intrinsics.txt", K)
    cv2.imwrite(str(d / "seq" / "image_000010.color.png"), np.full((48, 64, 3), 90, np.uint8))
    cv2.imwrite(str(d / "seq" / "image_000010.depth.png"), np.full((48, 64), 1500, np.uint16))
    np.save(d / "seq" / "cloud_000020.npy", np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3)) + [0, 0, 1.5])
    T = cameras.make_pose(np.eye(3), np.array([0.05, 0.0, 0.0]))
    rec = {"scene_name": scene, "image_file": f"{scene}/seq/image_000010.color.png",
           "depth_file": f"{scene}/seq/image_000010.depth.png", "cloud_file": f"{scene}/seq/cloud_000020.npy",
           "overlap": 0.62, "cloud_to_image": T}
    if drop:
        del rec[drop]
    (root / "metadata" / "test.pkl").write_bytes(pickle.dumps([rec]))
    return root


def test_the_loader_reads_a_pair_of_the_layout(tmp_path):
    ds = registry.open_dataset("rgbd-scenes-v2", _fake(tmp_path / "v2"))
    assert isinstance(ds, RGBDScenesV2) and len(ds) == 1
    (pair,) = list(ds.pairs())
    assert pair.name == "rgbd_scenes_v2/rgbd-scenes-v2-scene_11/image_000010.color-cloud_000020"
    assert pair.image.shape == (48, 64, 3) and pair.depth_size == (48, 64) and pair.points.shape == (200, 3)
    np.testing.assert_allclose(pair.depth_gt, 1.5)
    np.testing.assert_allclose(pair.K_image, K)
    np.testing.assert_allclose(pair.T_cam_pc[:3, 3], [0.05, 0, 0])
    assert pair.meta["overlap"] == pytest.approx(0.62)


def test_the_loader_names_what_is_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing RGBD-Scenes-v2 root folder"):
        RGBDScenesV2(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="missing metadata file: .*test.pkl"):
        RGBDScenesV2(tmp_path / "empty")
    root = _fake(tmp_path / "v2")
    (root / "data" / "rgbd-scenes-v2-scene_11" / "seq" / "cloud_000020.npy").unlink()
    ds = RGBDScenesV2(root)
    with pytest.raises(FileNotFoundError, match="missing point cloud: .*cloud_000020.npy"):
        ds.pair(ds.pair_list()[0])
    with pytest.raises(ValueError, match="entry 0 is not a dict with the keys"):
        RGBDScenesV2(_fake(tmp_path / "v3", drop="cloud_to_image"))
    (root / "metadata" / "test.pkl").write_text("not a pickle")
    with pytest.raises(ValueError, match="cannot read it as a pickled list"):
        RGBDScenesV2(root)
