"""Bad input gets a clear answer, and no run loses its results.

Every case feeds one kind of bad input (a missing or unreadable file, an empty or NaN cloud,
an all-zero depth map, an image of the wrong kind, intrinsics that do not fit, a pose that
is not rigid, too few matches, a cloud outside the view, missing weights, a wrong device, a
notebook that fails) and checks the message, or, inside a benchmark, the failure recorded in
the rows while the run goes on. Pairs are small synthetic scenes (120 x 160) with the stub
backend and a small configuration, so each test takes a fraction of a second to a few seconds.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from freereg_lib import config_for, pipeline
from freereg_lib.data import synthetic
from freereg_lib.data.datasets import common
from freereg_lib.data.datasets.icl import ICL_ROOT, ICLSample
from freereg_lib.data.datasets.pairlists import PairEntry, PairSource
from freereg_lib.data.pair import Pair, UnreadablePair
from freereg_lib.geometry import cameras, metrics, projection
from freereg_lib.models import MissingWeightsError, get_backend

ROOT = Path(__file__).resolve().parent.parent
SIZE = (120, 160)
CFG = config_for("synthetic_indoor").override(
    ransac_iters=1000, keypoint_grid=(12, 16), resize_hw=(128, 192), pca_dim=16)
ONE = [("FreeReg-D", "pnp")]  # the cheapest variant: no geometric features


@pytest.fixture(scope="module")
def pair() -> Pair:
    return synthetic.make_pair("indoor", seed=0, image_size=SIZE)


@pytest.fixture(scope="module")
def stub():
    return get_backend("stub", CFG)


def _with(pair: Pair, **changes) -> Pair:
    return dataclasses.replace(pair, **changes)


def _failed_row(rows: list[dict], match: str) -> dict:
    """The single failure every variant row of a pair records, checked the paper's way."""
    assert rows
    for r in rows:
        assert r["registered"] is False and r["IR"] == 0.0 and r["IN"] == 0 and r["n_matches"] == 0
        assert math.isnan(r["RE"]) and math.isnan(r["TE"])
        assert r["error"] == rows[0]["error"]
    assert re.search(match, rows[0]["error"]), rows[0]["error"]
    return rows[0]


# --------------------------------------------------------------------------------------
# File readers: missing and unreadable files name the file.

def test_missing_and_unreadable_image_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"missing file: .*nope\.png"):
        common.read_rgb(tmp_path / "nope.png")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(ValueError, match=r"cannot decode image .*junk\.png"):
        common.read_rgb(tmp_path / "junk.png")
    (tmp_path / "empty.jpg").write_bytes(b"")
    with pytest.raises(ValueError, match=r"cannot decode image .*empty\.jpg"):
        common.read_rgb(tmp_path / "empty.jpg")


def test_depth_reader_refuses_missing_colour_and_8_bit_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"missing file: .*d\.png"):
        common.read_depth(tmp_path / "d.png")
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(ValueError, match=r"rgb\.png as a single-channel 16-bit depth PNG"):
        common.read_depth(tmp_path / "rgb.png")
    cv2.imwrite(str(tmp_path / "vis.png"), np.full((4, 5), 200, np.uint8))
    with pytest.raises(ValueError, match=r"vis\.png is an 8-bit image, not a 16-bit depth PNG"):
        common.read_depth(tmp_path / "vis.png")
    cv2.imwrite(str(tmp_path / "ok.png"), np.full((4, 5), 1500, np.uint16))
    assert common.read_depth(tmp_path / "ok.png").max() == 1.5


def test_pose_readers_name_the_file_and_what_was_expected(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"missing file: .*pose\.txt"):
        common.read_pose_txt(tmp_path / "pose.txt")
    (tmp_path / "words.txt").write_text("1 0 0 0\n0 one 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"cannot read .*words\.txt as a 4 x 4 pose"):
        common.read_pose_txt(tmp_path / "words.txt")
    np.savetxt(tmp_path / "3x4.txt", np.eye(4)[:3])
    with pytest.raises(ValueError, match=r"3x4\.txt does not hold a finite 4 x 4 pose \(got shape \(3, 4\)\)"):
        common.read_pose_txt(tmp_path / "3x4.txt")
    np.savetxt(tmp_path / "nan.txt", np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match=r"nan\.txt does not hold a finite 4 x 4 pose"):
        common.read_pose_txt(tmp_path / "nan.txt")
    (tmp_path / "t.log").write_text("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 x 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"t\.log, entry at non-empty line 1: expected a header"):
        common.read_redwood_log(tmp_path / "t.log")
    (tmp_path / "short.log").write_text("0 0 1\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n")
    with pytest.raises(ValueError, match=r"short\.log, frame 0: expected 4 rows of 4 finite numbers"):
        common.read_redwood_log(tmp_path / "short.log")


def test_point_cloud_reader_formats_empty_and_non_finite(tmp_path):
    pts = np.random.default_rng(0).normal(size=(6, 3))
    np.save(tmp_path / "c.npy", pts)
    np.savetxt(tmp_path / "c.xyz", np.c_[pts, np.ones((6, 3))])  # x y z nx ny nz
    (tmp_path / "c.ply").write_text("ply\nformat ascii 1.0\nelement vertex 6\nproperty double x\nproperty double y\n"
                                    "property double z\nend_header\n" + "\n".join(" ".join(repr(float(v)) for v in p) for p in pts))
    for name in ("c.npy", "c.xyz", "c.ply"):
        np.testing.assert_allclose(common.read_points(tmp_path / name), pts, rtol=1e-12, err_msg=name)
    with pytest.raises(FileNotFoundError, match=r"missing file: .*gone\.ply"):
        common.read_points(tmp_path / "gone.ply")
    np.save(tmp_path / "empty.npy", np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"empty\.npy holds no point \(an empty point cloud\)"):
        common.read_points(tmp_path / "empty.npy")
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                        "property float y\nproperty float z\nend_header\n")
    with pytest.raises(ValueError, match=r"empty\.ply holds no vertex \(an empty point cloud\)"):
        common.read_points(tmp_path / "empty.ply")
    np.save(tmp_path / "flat.npy", pts[:, :2])
    with pytest.raises(ValueError, match=r"flat\.npy holds an array of shape \(6, 2\).*expected \(N, 3\)"):
        common.read_points(tmp_path / "flat.npy")
    (tmp_path / "c.pcd").write_text("")
    with pytest.raises(ValueError, match=r"unknown point cloud format '\.pcd'"):
        common.read_points(tmp_path / "c.pcd")
    (tmp_path / "bad.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(ValueError, match=r"cannot read the points of .*bad\.npy"):
        common.read_points(tmp_path / "bad.npy")
    holes = pts.copy()
    holes[[1, 4], 2] = [np.nan, np.inf]
    np.save(tmp_path / "holes.npy", holes)
    with pytest.warns(RuntimeWarning, match=r"holes\.npy: dropped 2 of 6 points that are NaN or inf"):
        kept = common.read_points(tmp_path / "holes.npy")
    np.testing.assert_array_equal(kept, pts[[0, 2, 3, 5]])
    assert np.isnan(common.read_points(tmp_path / "holes.npy", drop_nonfinite=False)).sum() == 1
    np.save(tmp_path / "allnan.npy", np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match=r"allnan\.npy: all 3 points are NaN or inf"):
        common.read_points(tmp_path / "allnan.npy")


@pytest.fixture()
def icl_copy(tmp_path) -> Path:
    dst = tmp_path / "icl"
    shutil.copytree(ICL_ROOT, dst)
    return dst


def test_icl_pair_with_a_missing_or_all_zero_depth_file_is_recorded_and_the_run_goes_on(icl_copy, stub):
    ds = ICLSample(icl_copy)
    (icl_copy / "depth" / "00010.png").unlink()  # frame 10: the cloud of (0, 10), the image side of (10, x)
    cv2.imwrite(str(icl_copy / "depth" / "00020.png"), np.zeros((480, 640), np.uint16))
    with pytest.raises(FileNotFoundError, match=r"missing file: .*depth/00010\.png"):
        ds.pair(0, 10)
    with pytest.raises(ValueError, match=r"depth/00020\.png has no valid pixel \(all zero\): the point cloud of "
                                         r"frame 20 would be empty"):
        ds.pair(0, 20)
    pairs = list(ds.pairs(n=4))
    assert [p.name for p in pairs] == ["icl/00000-00010", "icl/00000-00020", "icl/00000-00030", "icl/00000-00040"]
    assert [type(p) for p in pairs] == [UnreadablePair, UnreadablePair, Pair, Pair]
    with pytest.raises(FileNotFoundError, match="00010.png"):
        pairs[0].image  # used directly, the placeholder raises the loader's own error
    rows = pipeline.run_pairs(pairs[:3], stub, CFG, ONE, progress=False)
    assert [r["pair"] for r in rows] == [p.name for p in pairs[:3]]
    _failed_row(rows[:1], r"^FileNotFoundError: missing file: .*depth/00010\.png")
    _failed_row(rows[1:2], r"^ValueError: .*00020\.png has no valid pixel")


def test_a_loader_error_in_the_middle_of_a_dataset_is_one_failed_pair(pair, stub):
    """A PairSource's pairs() yields every pair; the one that cannot be read is recorded."""

    class Three(PairSource):
        dataset = "fake"

        def pair_list(self):
            return [PairEntry("s", str(k), str(k + 1), 1.0) for k in range(3)]

        def pair(self, entry):
            if entry.image_frame == "1":
                raise FileNotFoundError("missing depth image: /data/s/1.depth.png")
            return _with(pair, name=f"fake/{entry.key}")

    rows = pipeline.run_pairs(Three().pairs(), stub, CFG, ONE, progress=False)
    assert [r["pair"] for r in rows] == ["fake/s/0-1", "fake/s/1-2", "fake/s/2-3"]
    assert rows[0]["error"] == rows[2]["error"] == "" and rows[0] == {**rows[2], "pair": rows[0]["pair"]}
    _failed_row(rows[1:2], r"^FileNotFoundError: missing depth image: /data/s/1\.depth\.png")
    agg = metrics.aggregate(rows, CFG.rr_rot_deg, CFG.rr_trans_m)
    assert agg["n_pairs"] == 3 and agg["n_failed"] >= 1


# --------------------------------------------------------------------------------------
# Pair.validate: each field, named, with what was expected.

@pytest.mark.parametrize("field, value, message", [
    ("image", "gray", r"image must be an \(H, W, 3\) uint8 RGB array, got shape \(120, 160\); a grayscale image"),
    ("image", "rgba", r"image must be an .* got shape \(120, 160, 4\); an RGBA image: drop alpha"),
    ("image", "float", r"image must be uint8 RGB \(0\.\.255\), got dtype float64; values in \[0, 1\]"),
    ("points", np.zeros((0, 3)), r"the point cloud is empty \(0 points\)"),
    ("points", np.zeros((10, 2)), r"points must be an \(N, 3\) float array of x, y, z, got shape \(10, 2\)"),
    ("K_image", cameras.intrinsics(-100.0, 100.0, 80, 60), r"K_image has focal lengths fx = -100, fy = 100 px; both must be > 0"),
    ("K_image", cameras.intrinsics(100.0, 0.0, 80, 60), r"K_image has focal lengths .*both must be > 0"),
    ("K_image", cameras.intrinsics(525.0, 525.0, 319.5, 239.5),
     r"K_image's principal point \(cx, cy\) = \(319\.5, 239\.5\) lies outside its 160 x 120 \(W x H\) image"),
    ("K_depth", cameras.intrinsics(0.8, 0.8, 0.5, -0.7), r"K_depth holds normalised intrinsics: multiply row 0 by W and row 1 by H"),
    ("K_depth", np.eye(4), r"K_depth must be a \(3, 3\) intrinsics matrix"),
    ("K_image", np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 2]]), r"K_image must have the last row \[0, 0, 1\]"),
    ("depth_size", (120, 0), r"depth_size must be \(H_d, W_d\), two positive integers, got \(120, 0\)"),
    ("depth_size", (120.5, 160), r"depth_size must be \(H_d, W_d\)"),
    ("T_cam_pc", "reflect", r"T_cam_pc is not a rigid transform: .*det\(R\) = -1; det\(R\) < 0 is a reflection"),
    ("T_cam_pc", "scaled", r"T_cam_pc is not a rigid transform: .*R carries a scale of 1\.5"),
    ("T_pc_sensor", "transposed", r"T_pc_sensor is not a rigid transform: .*it looks transposed: pass T\.T"),
    ("T_pc_sensor", "lastrow", r"T_pc_sensor is not a rigid transform: .*its last row is \[0\.0, 0\.0, 1\.0, 1\.0\]"),
    ("T_cam_pc", "nan", r"T_cam_pc has non-finite entries"),
    ("T_cam_pc", np.eye(3), r"T_cam_pc must be a \(4, 4\) pose"),
    ("depth_gt", "zero", r"depth_gt has no valid pixel \(all zero: no true depth anywhere\); pass depth_gt=None"),
    ("depth_gt", np.ones((60, 80)), r"depth_gt must be \(H, W\) = \(120, 160\) like the image, got shape \(60, 80\)"),
    ("image_ids", np.zeros((60, 80), np.int32), r"image_ids must be \(H, W\) = \(120, 160\)"),
    ("point_ids", np.zeros(3, np.int32), r"point_ids must be \(N,\) = \(\d+,\) like points, got shape \(3,\)"),
])
def test_validate_names_the_field_and_what_was_expected(pair, field, value, message):
    T = pair.T_cam_pc
    made = {
        "gray": lambda: pair.image[..., 0], "rgba": lambda: np.dstack([pair.image, pair.image[..., :1]]),
        "float": lambda: pair.image / 255.0, "reflect": lambda: T @ np.diag([1.0, 1.0, -1.0, 1.0]),
        "scaled": lambda: T @ np.diag([1.5, 1.5, 1.5, 1.0]), "transposed": lambda: pair.T_pc_sensor.T,
        "lastrow": lambda: pair.T_pc_sensor + _lastrow(),
        "nan": lambda: np.where(np.eye(4, dtype=bool), np.nan, T), "zero": lambda: np.zeros_like(pair.depth_gt),
    }
    bad = _with(pair, **{field: made[value]() if isinstance(value, str) else value})
    with pytest.raises(ValueError, match=rf"^pair synthetic-indoor/seed0000: {message}"):
        bad.validate()


def _lastrow() -> np.ndarray:
    out = np.zeros((4, 4))
    out[3, 2] = 1.0
    return out


def test_validate_accepts_every_pair_the_library_makes(pair):
    assert pair.validate() is pair
    for p in ICLSample().pairs(n=3):
        p.validate()
    synthetic.make_pair("outdoor", seed=1, image_size=(64, 208)).validate()


def test_bad_pairs_inside_a_benchmark_are_recorded_failures_that_count_as_not_registered(pair, stub):
    """A grayscale image, a reflected pose and an all-zero depth_gt in one run: every pair
    gets its rows, the bad ones with the validation message, and RR counts them as failures."""
    bad = [
        _with(pair, name="gray", image=pair.image[..., 0]),
        _with(pair, name="reflect", T_cam_pc=pair.T_cam_pc @ np.diag([1.0, -1.0, 1.0, 1.0])),
        _with(pair, name="nodepth", depth_gt=np.zeros_like(pair.depth_gt)),
        _with(pair, name="intrinsics", K_depth=cameras.intrinsics(525.0, 525.0, 319.5, 239.5)),
    ]
    rows = pipeline.run_pairs([pair, *bad], stub, CFG, ONE, progress=False)
    assert [r["pair"] for r in rows] == [pair.name, "gray", "reflect", "nodepth", "intrinsics"]
    assert rows[0]["error"] == ""
    _failed_row(rows[1:2], r"^ValueError: pair gray: image must be an \(H, W, 3\) uint8")
    _failed_row(rows[2:3], r"^ValueError: pair reflect: T_cam_pc is not a rigid transform")
    _failed_row(rows[3:4], r"^ValueError: pair nodepth: depth_gt has no valid pixel")
    _failed_row(rows[4:5], r"^ValueError: pair intrinsics: K_depth's principal point")
    agg = metrics.aggregate(rows, CFG.rr_rot_deg, CFG.rr_trans_m)
    assert agg["n_pairs"] == 5 and agg["n_failed"] >= 4
    assert agg["RR"] == 100.0 * rows[0]["registered"] / 5


# --------------------------------------------------------------------------------------
# Clouds: empty, NaN / inf, outside the view.

def test_empty_cloud_in_the_middle_of_a_run_loses_nothing(pair, stub):
    variants = [("FreeReg-D", "pnp"), ("FreeReg-D", "kabsch")]
    pairs = [_with(pair, name="a"), _with(pair, name="empty", points=np.zeros((0, 3)), point_ids=None),
             _with(pair, name="c")]
    rows = pipeline.run_pairs(pairs, stub, CFG, variants, progress=False)
    assert [(r["pair"], r["solver"]) for r in rows] == [(n, s) for n in ("a", "empty", "c") for _, s in variants]
    assert all(r["error"] == "" for r in rows if r["pair"] != "empty")
    _failed_row(rows[2:4], r"^ValueError: pair empty: the point cloud is empty \(0 points\)")
    assert [r["IN"] for r in rows[:2]] == [r["IN"] for r in rows[4:]]  # the pairs around it are unaffected


def test_nan_points_are_refused_with_their_count_or_dropped_with_a_warning(pair, stub):
    pts = pair.points.copy()
    pts[::100, 1] = np.nan
    pts[1, 0] = -np.inf
    n_bad = len(pts[::100]) + 1
    holes = _with(pair, points=pts)
    _failed_row(pipeline.run_pair(holes, stub, CFG, ONE),
                rf"^ValueError: pair synthetic-indoor/seed0000: {n_bad} of {len(pts)} points are not finite "
                r"\(NaN or inf\); drop them with pair = pair.drop_nonfinite_points\(\)")
    with pytest.warns(RuntimeWarning, match=rf"dropped {n_bad} of {len(pts)} points that are NaN or inf"):
        clean = holes.drop_nonfinite_points()
    assert len(clean.points) == len(clean.point_ids) == len(pts) - n_bad and np.isfinite(clean.points).all()
    assert pipeline.run_pair(clean, stub, CFG, ONE)[0]["error"] == ""
    assert pair.drop_nonfinite_points() is pair


def test_cloud_behind_the_depth_camera_says_where_the_points_went(pair, stub):
    behind = cameras.transform(pair.T_pc_sensor @ np.diag([1.0, 1.0, -1.0, 1.0]) @ cameras.invert(pair.T_pc_sensor),
                               pair.points)  # mirrored through the sensor's image plane
    row = _failed_row(pipeline.run_pair(_with(pair, points=behind), stub, CFG, ONE),
                      r"no point of the cloud projects into the depth view; of its \d+ points 0 lie in front")
    assert "check T_pc_sensor" in row["error"]


def test_cloud_that_misses_every_depth_keypoint(pair, stub):
    """The cloud covers a 3 x 3 pixel patch between the keypoints of the grid."""
    uv, _ = cameras.project(cameras.transform(cameras.invert(pair.T_pc_sensor), pair.points), pair.K_depth)
    keep = (np.abs(uv[:, 0] - 30) < 1.5) & (np.abs(uv[:, 1] - 30) < 1.5)  # keypoints sit at 5, 15, 25, 35, ...
    assert keep.sum() >= 4
    patch = _with(pair, points=pair.points[keep], point_ids=pair.point_ids[keep])
    _failed_row(pipeline.run_pair(patch, stub, CFG.override(densify="none"), ONE),
                r"no depth keypoint has a valid depth: none of the 192 keypoints of the 12 x 16 grid "
                r"\(cfg\.keypoint_grid\) falls on one of the 9 pixels")


def test_projection_refuses_points_that_are_not_xyz():
    with pytest.raises(ValueError, match=r"points must be \(N, 3\) x, y, z, got shape \(6, 2\)"):
        projection.project_to_depth(np.ones((6, 2)), np.eye(3), np.eye(4), (4, 4))
    with pytest.raises(ValueError, match=r"size must be \(H, W\) with both sides > 0"):
        projection.project_to_depth(np.ones((6, 3)), np.eye(3), np.eye(4), (0, 4))
    depth, index = projection.project_to_depth(np.zeros((0, 3)), np.eye(3), np.eye(4), (2, 2))
    assert not depth.any() and (index == -1).all()


# --------------------------------------------------------------------------------------
# Solvers: too few matches is a failed row, not an exception.

def test_too_few_matches_is_a_recorded_failure_not_registered(pair, stub):
    rows = pipeline.run_pair(pair, stub, CFG.override(keypoint_grid=(2, 2)),
                             [("FreeReg-D", "pnp"), ("FreeReg-D", "kabsch")])
    pnp, kabsch = rows
    assert pnp["n_matches"] <= 4 and kabsch["n_matches"] <= 4
    assert pnp["error"].startswith(f"{pnp['n_matches']} usable matches") and "PnP-RANSAC needs at least 8" in pnp["error"]
    assert "Kabsch-RANSAC needs at least 5" in kabsch["error"]
    for r in rows:
        assert r["registered"] is False and math.isnan(r["RE"]) and math.isnan(r["TE"]) and r["n_inliers"] == 0
    assert metrics.aggregate(rows)["RR"] == 0.0 and metrics.aggregate(rows)["n_failed"] == 2


def test_aggregate_refuses_ir_given_in_percent():
    rows = [{"pair": "p", "IR": 0.4, "IN": 3, "RE": 1.0, "TE": 0.1}, {"pair": "q", "IR": 43.0, "IN": 3}]
    with pytest.raises(ValueError, match=r"IR must be a fraction in \[0, 1\].*row 1 \(pair 'q'\) has IR = 43\.0"):
        metrics.aggregate(rows)


# --------------------------------------------------------------------------------------
# Backends: weights and devices.

@pytest.fixture()
def no_weights(tmp_path, monkeypatch):
    hub = pytest.importorskip("huggingface_hub.constants")
    monkeypatch.setattr(hub, "HF_HUB_CACHE", str(tmp_path / "hf_cache"))
    monkeypatch.delenv("FREEREG_WEIGHTS", raising=False)
    return tmp_path


def test_missing_weights_folder_says_it_does_not_exist(no_weights):
    with pytest.raises(MissingWeightsError) as info:
        get_backend("real", CFG, device="cpu", weights_dir=str(no_weights / "wieghts"), load=("mono",))
    msg = str(info.value)
    assert "weights_dir" in msg and "wieghts does not exist (a typo" in msg
    assert "huggingface-cli download Intel/zoedepth-nyu" in msg and 'backend="stub"' in msg


def test_weights_dir_pointing_at_a_model_folder_names_its_parent(no_weights):
    model = no_weights / "weights" / "zoedepth-nyu"
    model.mkdir(parents=True)
    (model / "config.json").write_text("{}")
    with pytest.raises(MissingWeightsError, match=r"is itself a model folder; .*pass weights_dir='.*weights'"):
        get_backend("real", CFG, device="cpu", weights_dir=str(model), load=("mono",))
    assert get_backend("real", CFG, device="cpu", weights_dir=str(model.parent), load=("mono",)).paths["zoe"] == str(model)


def test_a_model_folder_without_its_config_is_pointed_out(no_weights):
    (no_weights / "weights" / "zoedepth-nyu").mkdir(parents=True)  # an interrupted download
    with pytest.raises(MissingWeightsError, match=r"zoedepth-nyu \(exists, but holds no model_index\.json or "
                                                  r"config\.json: an incomplete download"):
        get_backend("real", CFG, device="cpu", weights_dir=str(no_weights / "weights"), load=("mono",))


def test_cuda_without_cuda_and_unknown_devices_are_clear():
    torch = pytest.importorskip("torch")
    with pytest.raises(ValueError, match=r"unsupported device 'gpu'; use None .*'cpu', 'cuda' or 'cuda:N'"):
        get_backend("tiny", CFG, device="gpu")
    if torch.cuda.is_available():
        n = torch.cuda.device_count()
        with pytest.raises(RuntimeError, match=rf"has {n} CUDA device\(s\).*Use device='cuda:0'"):
            get_backend("tiny", CFG, device=f"cuda:{n}")
    else:
        for kind in ("tiny", "real"):  # real: the device is checked before the weights
            with pytest.raises(RuntimeError, match=r"device='cuda' was requested but CUDA is not available.*"
                                                   r"Use device='cpu' or device=None"):
                get_backend(kind, CFG, device="cuda")


# --------------------------------------------------------------------------------------
# Determinism: same seed, same pair, same rows.

def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def test_same_seed_gives_bit_identical_pairs_and_identical_rows(pair):
    again = synthetic.make_pair("indoor", seed=0, image_size=SIZE)
    for f in dataclasses.fields(Pair):
        a, b = getattr(pair, f.name), getattr(again, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f.name
        else:
            assert a == b, f.name
    rows = [pipeline.run_pair(p, get_backend("stub", CFG), CFG) for p in (pair, again)]
    assert len(rows[0]) == 4
    for r0, r1 in zip(*rows):
        assert r0.keys() == r1.keys() and all(_same(r0[k], r1[k]) for k in r0), (r0, r1)
    s0, s1 = (pipeline.summarize(r, CFG) for r in rows)
    assert s0.equals(s1)


# --------------------------------------------------------------------------------------
# Papermill: a failing notebook keeps its executed copy, the command exits non-zero and
# says what finished.

def test_batch_command_with_a_failing_notebook(tmp_path, capsys):
    """``python -m freereg_lib batch run`` exits with ``main()``'s status (in-process here:
    a subprocess would add seconds of start-up for nothing)."""
    from freereg_lib.commands import batch

    flag = tmp_path / "fail.txt"
    flag.write_text("seed=1,scale=1.0\n")
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({
        "name": "midrun", "notebooks": [str(ROOT / "tests" / "fixtures" / "batch_fixture.ipynb")],
        "base": {"n_pairs": 2, "fail_flag": str(flag)}, "grid": {"seed": [0, 1]}}))
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 1
    assert "sys.exit(main())" in Path(batch.__file__).read_text()
    out = capsys.readouterr().out
    assert "1 job(s) ran, 0 already done (skipped), 1 failed" in out
    assert "  finished batch_fixture-seed=0-" in out
    assert "FAILED batch_fixture-seed=1-" in out and "RuntimeError: simulated failure of seed=1,scale=1.0" in out
    run_dir = tmp_path / "runs" / "midrun"
    failed = next(run_dir.glob("batch_fixture-seed=1-*"))
    nb = json.loads((failed / "notebook.ipynb").read_text())
    errors = [o for c in nb["cells"] for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert errors and errors[0]["ename"] == "RuntimeError" and "simulated failure" in errors[0]["evalue"]
    assert any("injected-parameters" in c["metadata"].get("tags", []) and c.get("execution_count") for c in nb["cells"])
    assert "simulated failure" in (failed / "error.txt").read_text() and not (failed / "done.json").exists()
    finished = next(run_dir.glob("batch_fixture-seed=0-*"))
    assert (finished / "done.json").is_file() and (finished / "out" / "pairs.csv").is_file()
    md = (run_dir / "results.md").read_text()
    assert finished.name in md.split("Not in the table:")[0] and failed.name in md.split("Not in the table:")[1]


def test_fused_matching_without_geometric_features_is_a_clear_error():
    cfg = config_for("synthetic_indoor")
    pair = synthetic.make_pair("indoor", seed=0, image_size=(96, 128))
    feats = pipeline.compute_features(pair, get_backend("stub", cfg), cfg, geometric=False)
    assert len(pipeline.match(feats, 1.0)) > 0  # diffusion only needs no geometric part
    with pytest.raises(ValueError, match="geometric features were not computed"):
        pipeline.match(feats, 0.5)
