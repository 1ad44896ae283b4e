"""A cloud 5,000 km from its origin gets the pose it gets at the origin.

A depth PNG's cloud seen from its own sensor ties exactly: its points project onto pixel edges
(column and row 0 at 0 +- 1e-13) and its depths sit on whole millimetres, which the dense PNG's
round trip truncates. A float64 cloud written 5e6 m away keeps its points only to ~1e-9 m, and
that tipped those ties another way: 1,498 pixels of the densified depth view differed from the
origin's (ICL 60-70), and so did the pose (Kabsch RE 2.88 against 1.11 deg; a report had a
registered pose at the origin and RE 11.8 deg at 5e6 m). ``cfg.cloud_snap_m`` (``freereg register
--cloud-snap``) rounds the depth-camera coordinates to a grid first (0, the official projection,
is the default). A float32 cloud that far keeps only 0.5 m steps and is refused in one line.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from freereg_lib.commands import cli
from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.geometry import cameras
from freereg_lib.models import get_backend
from freereg_lib.pipeline import register as R
from freereg_lib.pipeline import steps
from freereg_lib.report import pair_files as PF

OFFSET = np.array([5.0e6, 3.0e6, 100.0])


@pytest.fixture(scope="module")
def sensor_pair():
    """ICL 60-70, its cloud (frame 70's depth PNG) in its sensor's frame and no sensor depth map (a
    user's cloud file: the depth view is the cloud's projection)."""
    pair = ICLSample().pair(60, 70)
    sens = cameras.transform(cameras.invert(pair.T_pc_sensor), pair.points)
    return dataclasses.replace(pair, points=sens, T_pc_sensor=np.eye(4), sensor_depth=None,
                               T_cam_pc=pair.T_cam_pc @ pair.T_pc_sensor)


def _moved(pair, offset):
    T = cameras.make_pose(np.eye(3), offset)
    out = dataclasses.replace(pair, points=pair.points + T[:3, 3], T_pc_sensor=T,
                              T_cam_pc=pair.T_cam_pc @ cameras.invert(T), meta=dict(pair.meta))
    out.meta.update(depth_camera=True, has_gt=True)
    return out


def _view(pair, cfg):
    return steps.depth_view(R._recentred(pair, None, None, lambda s: None)[0], cfg)


def test_both_settings_of_the_snap_on_a_far_depth_view(sensor_pair):
    assert FreeRegConfig().cloud_snap_m == 0.0 and config_for("demo").cloud_snap_m == 0.0  # official
    near, far = _moved(sensor_pair, np.zeros(3)), _moved(sensor_pair, OFFSET)
    official = config_for("demo")
    a, b = _view(near, official), _view(far, official)
    assert (a.hint_depth != b.hint_depth).sum() > 100  # the ties tip: millimetres and pixel edges
    snapped = official.override(cloud_snap_m=1e-6)
    a, b = _view(near, snapped), _view(far, snapped)
    assert np.array_equal(a.raw, b.raw) and np.array_equal(a.hint_depth, b.hint_depth)


@pytest.mark.parametrize("solver", ["kabsch", "pnp"])
def test_a_float64_cloud_5e6_m_away_gets_the_pose_it_gets_at_the_origin(sensor_pair, solver):
    # The far cloud is re-centred on its sensor (its depth-camera frame, as at the origin), so PnP,
    # which OpenCV solves in the cloud's frame, gets the origin's points too.
    cfg = config_for("demo", ransac_iters=2000, cloud_snap_m=1e-6)
    backend = get_backend("stub", cfg, mono_mae=1e-9)  # the true depth: a pose to recover
    near = R.register(_moved(sensor_pair, np.zeros(3)), backend, cfg, method="FreeReg-G", solver=solver)
    far = R.register(_moved(sensor_pair, OFFSET), backend, cfg, method="FreeReg-G", solver=solver)
    assert near.pose.success and near.errors["registered_gt"] and near.errors["RE"] < 10, near.errors
    assert far.n_inliers == near.n_inliers and far.registered == near.registered
    rot = cameras.rotation_error_deg(far.T_pc_cam[:3, :3], near.T_pc_cam[:3, :3])
    shift = np.abs(far.T_pc_cam[:3, 3] - OFFSET - near.T_pc_cam[:3, 3]).max()
    assert rot < 1e-5 and shift < 1e-6, (rot, shift)
    assert abs(far.errors["RE"] - near.errors["RE"]) < 1e-4 and abs(far.errors["TE"] - near.errors["TE"]) < 1e-6


def _files(pair, folder, offset, dtype):
    T = cameras.make_pose(np.eye(3), offset)
    PF._write_image_and_depth(pair, folder / "image.png", folder / "depth.png")
    cloud = PF.write_ply(folder / f"cloud_{dtype.__name__}_{int(offset[0])}.ply", (pair.points + offset).astype(dtype))
    np.savetxt(folder / "pose.txt", T)
    np.savetxt(folder / "gt.txt", T @ cameras.invert(pair.T_cam_pc))
    K = pair.K_image
    return [str(folder / "image.png"), str(cloud), "--K", *(f"{v:.9f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])),
            "--depth-pose", str(folder / "pose.txt"), "--gt-T-pc-cam", str(folder / "gt.txt"),
            "--image-depth", str(folder / "depth.png"), "--stub-true-depth", "--backend", "stub",
            "--ransac-iters", "2000", "--solver", "kabsch", "--cloud-snap", "1e-6", "--out", str(folder / "out")]


def test_register_a_float64_ply_5e6_m_away_as_at_the_origin_and_refuse_a_float32_one(sensor_pair, tmp_path,
                                                                                      capsys):
    poses = {}
    for name, offset, dtype in [("near", np.zeros(3), np.float64), ("far", OFFSET, np.float64)]:
        (tmp_path / name).mkdir()
        assert cli.main(["register", *_files(sensor_pair, tmp_path / name, offset, dtype)]) == 0, capsys.readouterr()
        poses[name] = np.loadtxt(tmp_path / name / "out" / "T_pc_cam.txt")
        poses[name][:3, 3] -= offset
    out = capsys.readouterr().out
    assert out.count("registered at (20 deg, 0.5 m)") == 2, out
    assert np.abs(poses["far"] - poses["near"]).max() < 3e-9  # T_pc_cam.txt holds 9 decimals
    (tmp_path / "far32").mkdir()
    assert cli.main(["register", *_files(sensor_pair, tmp_path / "far32", OFFSET, np.float32)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "stored in float32" in err[0] and "steps of 0.5 m" in err[0] and "cloud_float32" in err[0]


def test_a_negative_cloud_snap_is_refused_in_one_line(sensor_pair, tmp_path, capsys):
    argv = _files(sensor_pair, tmp_path, np.zeros(3), np.float64)
    argv[argv.index("--cloud-snap") + 1] = "-1"
    assert cli.main(["register", *argv]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == ["freereg register: error: --cloud-snap must be a number >= 0 (metres; 0: none), got -1.0"]
