"""The front door for one's own data: ``freereg register`` and ``freereg_lib.pipeline.register``.

* the command on the official demo layout the tests write and on the embedded ICL sample (tiny
  backend: random weights, the numbers mean nothing): outputs exist, the pose files parse and are
  each other's inverse, the overlay PNG is drawn, RE / TE are printed when the truth is given;
* a synthetic pair whose cloud comes without its sensor pose registers through the virtual depth
  cameras (stub backend, FreeReg, Kabsch; the pose is right and, against the per-run null,
  REGISTERED), and the chosen camera is printed;
* bad inputs stop with one line each (exit status 2, no traceback);
* the console script is declared and the virtual cameras look horizontally with image y down.
Kabsch runs with fewer iterations than the paper's 50k.
"""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from freereg_lib.commands import cli
from freereg_lib.config import config_for
from freereg_lib.data import synthetic
from freereg_lib.data.datasets.icl import ICL_ROOT, ICLSample
from freereg_lib.geometry import cameras
from freereg_lib.models import get_backend
from freereg_lib.pipeline import register as R
from freereg_lib.report import pair_files as PF

ROOT = Path(__file__).resolve().parent.parent
FAST = ["--ransac-iters", "3000"]


def _run(argv, capsys):
    rc = cli.main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


def _check_outputs(out: Path):
    T = np.loadtxt(out / "T_cam_pc.txt")
    T_inv = np.loadtxt(out / "T_pc_cam.txt")
    assert T.shape == (4, 4) and np.allclose(T @ T_inv, np.eye(4), atol=1e-6)
    doc = json.loads((out / "registration.json").read_text())
    assert np.allclose(np.array(doc["T_cam_pc"], dtype=float), T, atol=1e-6)
    assert doc["result"].startswith(("REGISTERED", "FAILED")) and "T_pc_cam" in doc["conventions"]
    for png in ("overlay.png", "matches.png"):
        data = (out / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, png
    return doc


def test_command_on_the_demo_layout_with_the_tiny_backend(tmp_path, capsys):
    from test_loaders import make_demo

    root, *_ = make_demo(tmp_path / "demo", rgb_size=(120, 160), dpt_size=(60, 80))
    rc, out, err = _run(["register", "--demo", str(root), "--backend", "tiny", "--device", "cpu",
                         "--out", str(tmp_path / "out"), *FAST], capsys)
    assert rc == 0, err
    doc = _check_outputs(tmp_path / "out")
    assert doc["method"] == "FreeReg" and doc["depth_camera"]["name"] == "given"  # the demo's sensor frame
    assert re.search(r"RE [\d.]+ deg, TE [\d.]+ m", out) or "RE - deg" in out, out
    assert "T_pc_cam (the pose of the camera in the cloud's frame)" in out and "result: " in out


def test_command_on_the_icl_sample_files_with_the_tiny_backend(tmp_path, capsys):
    icl = ICLSample()
    pair = icl.pair(10, 40)  # the cloud of frame 40 in its own camera frame
    np.save(tmp_path / "cloud.npy", pair.points[::4])
    np.savetxt(tmp_path / "gt.txt", pair.T_cam_pc)
    rc, out, err = _run(["register", str(ICL_ROOT / "color" / "00010.jpg"), str(tmp_path / "cloud.npy"),
                         "--intrinsics", str(ICL_ROOT / "intrinsics.json"), "--depth-pose", "identity",
                         "--gt-T-cam-pc", str(tmp_path / "gt.txt"), "--image-depth", str(ICL_ROOT / "depth" / "00010.png"),
                         "--backend", "tiny", "--device", "cpu", "--out", str(tmp_path / "out"), *FAST], capsys)
    assert rc == 0, err
    _check_outputs(tmp_path / "out")
    assert re.search(r"RE ([\d.]+|-) deg, TE ([\d.]+|-) m", out) and "IR " in out, out


@pytest.mark.slow
def test_a_synthetic_cloud_without_its_sensor_pose_registers_through_virtual_cameras(capsys):
    # Measured (10k iterations, 8 directions): seeds 0, 1, 2, 4 register (RE 1.2-3.1 deg, TE 0.10-0.37 m),
    # seed 3 misses by 7 cm (5.1 deg, 0.575 m); 30-90 s a pair on the 2-core CI machine. Two directions
    # (four virtual cameras, a quarter of the features) keep seed 4's choice, behind/yaw0 then refined,
    # and its pose and verdict to the digit.
    pair = synthetic.make_pair("indoor", seed=4)
    pair.meta["depth_camera"] = False  # the cloud comes without its sensor pose
    cfg = config_for("synthetic_indoor", ransac_iters=10_000)
    reg = R.register(pair, get_backend("stub", cfg), cfg, solver="kabsch", n_yaw=2)
    out = capsys.readouterr().out
    assert reg.camera.virtual and f"depth camera used: {reg.camera.name}" in out
    assert "candidate depth cameras" in out and "<- chosen" in out
    assert reg.method == "FreeReg" and reg.errors["registered_gt"], reg.errors
    assert reg.errors["RE"] < 20 and reg.errors["TE"] < 0.5, reg.errors
    # An absolute inlier count fitted on ICL's 156-500 matches called this right pose FAILED (33
    # inliers of the virtual view's 87 matches); against the per-run null it is REGISTERED.
    assert reg.registered and " x the " in reg.result and "matches shuffled" in reg.result, reg.result


def test_the_command_picks_a_virtual_camera_for_files_without_a_sensor_pose(tmp_path, capsys):
    pair = PF.downscale_pair(synthetic.make_pair("indoor", seed=0, image_size=(240, 320)), 0.5)
    T_world = cameras.make_pose(cameras.rotation_about([0, 0, 1], 0.7), [3.0, -2.0, 0.5])
    paths = PF.write_user_files(pair, tmp_path / "in", T_world)
    rc, out, err = _run(["register", str(paths["image"]), str(paths["cloud"]), "--intrinsics", str(paths["intrinsics"]),
                         "--image-depth", str(paths["image_depth"]), "--gt-T-pc-cam", str(paths["gt_T_pc_cam"]),
                         "--backend", "stub", "--views", "2", "--up", "z", "--out", str(tmp_path / "out"), *FAST], capsys)
    assert rc == 0, err
    assert "FreeReg-G" in out  # the stub has no diffusion features for files
    chosen = re.search(r"depth camera used: (\S+):", out)
    assert chosen and chosen.group(1) != "given", out
    doc = _check_outputs(tmp_path / "out")
    assert doc["depth_camera"]["virtual"] and len(doc["ground_truth"]) >= 2


# --------------------------------------------------------------------------------------
# Bad inputs: one line each.

def _bad_inputs(tmp_path):
    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    paths = PF.write_user_files(pair, tmp_path / "in")
    img, cloud = str(paths["image"]), str(paths["cloud"])
    K = [str(v) for v in (pair.K_image[0, 0], pair.K_image[1, 1], pair.K_image[0, 2], pair.K_image[1, 2])]
    np.save(tmp_path / "mm.npy", pair.points * 1000)
    np.save(tmp_path / "empty.npy", np.zeros((0, 3)))
    (tmp_path / "broken.png").write_bytes(b"not an image")
    return {
        "missing intrinsics": ([img, cloud], "missing image intrinsics"),
        "a cloud in millimetres": ([img, str(tmp_path / "mm.npy"), "--K", *K], "looks like millimetres"),
        "intrinsics for another image": ([img, cloud, "--K", *K[:2], str(4 * float(K[2])), str(4 * float(K[3]))],
                                         "principal point"),
        "an empty cloud": ([img, str(tmp_path / "empty.npy"), "--K", *K], "empty point cloud"),
        "an unreadable image": ([str(tmp_path / "broken.png"), cloud, "--K", *K], "cannot read the image"),
        "a missing cloud": ([img, str(tmp_path / "nope.ply"), "--K", *K], "missing point cloud file"),
        "the stub without the image's depth": ([img, cloud, "--K", *K, "--backend", "stub"], "--image-depth"),
    }


@pytest.mark.parametrize("case", ["missing intrinsics", "a cloud in millimetres", "intrinsics for another image",
                                  "an empty cloud", "an unreadable image", "a missing cloud",
                                  "the stub without the image's depth"])
def test_bad_inputs_stop_with_one_clear_line(case, tmp_path, capsys):
    argv, expected = _bad_inputs(tmp_path)[case]
    rc, out, err = _run(["register", *argv, "--out", str(tmp_path / "out"), *FAST], capsys)
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("freereg register: error: "), err
    assert expected in lines[0] and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_python_dash_m_runs_the_command_without_a_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "freereg_lib", "register", str(tmp_path / "x.png"),
                           str(tmp_path / "y.ply"), "--K", "500", "500", "320", "240"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == f"freereg register: error: missing image file: {tmp_path / 'x.png'}"


# --------------------------------------------------------------------------------------
# Pieces.

def test_the_console_script_is_declared():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["freereg"] == "freereg_lib.commands.cli:main" and callable(cli.main)


def test_virtual_cameras_look_horizontally_with_image_y_down():
    rng = np.random.default_rng(0)
    room = rng.uniform([-3, -2, 0], [3, 2, 2.5], size=(5000, 3))  # z up, wider than tall
    cfg = config_for("demo")
    K = cameras.intrinsics(500, 500, 319.5, 239.5)
    assert R.up_axis(room)[0] @ [0, 0, 1] > 0.99  # auto: the thinnest direction, signed towards +z
    cams = R.virtual_cameras(room, K, (480, 640), cfg, n_yaw=4, up="z")
    names = [c.name for c in cams]
    assert "origin" in names  # half the room lies in front of the origin (+z)
    ring = [c for c in cams if "yaw" in c.name]
    assert len(ring) == 8 and all(c.virtual and c.size == (480, 640) for c in ring)
    for c in ring:
        R_ = c.T_pc_sensor[:3, :3]
        assert abs(R_[2, 2]) < 1e-9  # optical axis horizontal
        assert R_[:, 1] @ [0, 0, 1] < -0.99  # image y points down
    rough = np.eye(4)
    assert R.virtual_cameras(room, K, (480, 640), cfg, rough_T_pc_cam=rough, n_yaw=1)[1].name == "rough"
    big = R.virtual_cameras(room, cameras.intrinsics(1000, 1000, 639.5, 479.5), (960, 1280), cfg, n_yaw=1)
    assert big[0].size == (480, 640)  # rendered at most 640 wide, intrinsics scaled
