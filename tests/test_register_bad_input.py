"""``freereg register`` and the loaders on bad input (geometry checked where data enters).

Each case failed on the code before it (a traceback, or a silently wrong number): ``--views 0``
and ``--depth-scale 0`` (tracebacks), ``--depth-size H W`` (accepted, RE 63 deg), ``--cloud-scale``
0 or -1 (accepted), a photo with an EXIF rotation (rotated, its depth not), a K with skew (used by
the projection, ignored by the lifting), a cloud 5,000 km from its origin (PnP degraded), depth in
2 mm units or off by 3x (passed the unit check), a PLY header counting fewer vertices than its
body (half the cloud read), an inverted pose (passed). Now each ends in one line, exit status 2
(or, for the far cloud, the same pose as near the origin).
"""
from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from freereg_lib.commands import cli
from freereg_lib.config import config_for
from freereg_lib.data.datasets.common import read_points, read_rgb
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.geometry import cameras
from freereg_lib.models import get_backend
from freereg_lib.commands import user_inputs as UI
from freereg_lib.pipeline import register as R
from freereg_lib.report import pair_files as PF

ROOT = Path(__file__).resolve().parent.parent
FAST = ["--ransac-iters", "2000", "--backend", "stub"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """An ICL pair (image 10, cloud of frame 40) at 160 x 120, written as a user brings it, with
    the cloud in a frame turned and moved away from the camera's (so an inverted pose shows none
    of it)."""
    tmp = tmp_path_factory.mktemp("bad_input")
    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    T_world = cameras.make_pose(cameras.rotation_about([0, 0, 1], 0.7), [3.0, -2.0, 0.5])
    paths = PF.write_user_files(pair, tmp / "in", T_world)
    K = pair.K_image
    paths["K"] = [f"{v:.6f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])]
    paths["pair"], paths["T_world"], paths["tmp"] = pair, T_world, tmp
    return paths


def _run(argv, capsys):
    rc = cli.main(["register", *argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _one_line(rc, err, expected):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("freereg register: error: "), err
    assert "Traceback" not in err and expected in lines[0], lines[0]
    return lines[0]


def _base(files):
    return [str(files["image"]), str(files["cloud"]), "--K", *files["K"]]


# --------------------------------------------------------------------------------------
# Scales, counts and sizes: one line, exit 2.

@pytest.mark.parametrize("argv, expected", [
    (["--views", "0"], "--views must be >= 1"),
    (["--views", "-3"], "--views must be >= 1"),
    (["--cloud-scale", "0"], "--cloud-scale must be a positive number"),
    (["--cloud-scale", "-1"], "--cloud-scale must be a positive number"),
    (["--cloud-scale", "nan"], "--cloud-scale must be a positive number"),
])
def test_counts_and_scales_out_of_range_end_in_one_line(files, argv, expected, capsys, tmp_path):
    rc, out, err = _run([*_base(files), *argv, *FAST, "--image-depth", str(files["image_depth"]),
                         "--out", str(tmp_path / "out")], capsys)
    _one_line(rc, err, expected)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("scale", ["0", "-1000", "inf"])
def test_depth_scale_zero_or_negative_ends_in_one_line(files, scale, capsys, tmp_path):
    rc, out, err = _run([*_base(files), "--image-depth", str(files["image_depth"]), "--depth-scale", scale, *FAST,
                         "--out", str(tmp_path / "out")], capsys)
    _one_line(rc, err, "--depth-scale must be a positive number")


def test_the_command_with_depth_scale_zero_prints_one_line_and_exits_2(files):
    proc = subprocess.run([sys.executable, "-m", "freereg_lib", "register", *_base(files), "--image-depth",
                           str(files["image_depth"]), "--depth-scale", "0", "--backend", "stub"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("freereg register: error: --depth-scale must be"), proc.stderr


def test_depth_size_given_as_h_w_is_refused(files, capsys, tmp_path):
    # The image is 160 x 120 (W x H); the depth camera the same size, given the wrong way round.
    rc, out, err = _run([*_base(files), "--depth-pose", "identity", "--depth-size", "120", "160", *FAST,
                         "--image-depth", str(files["image_depth"]), "--out", str(tmp_path / "o")], capsys)
    line = _one_line(rc, err, "you gave H W?")
    assert "--depth-size 160 120" in line
    # With the depth camera's own intrinsics, W x H is checked against its principal point.
    K = files["pair"].K_image
    rc, out, err = _run([*_base(files), "--depth-pose", "identity", "--depth-K", *files["K"], "--depth-size", "120",
                         "160", *FAST, "--image-depth", str(files["image_depth"]), "--out", str(tmp_path / "o")],
                        capsys)
    line = _one_line(rc, err, "you gave H W?")
    assert f"({K[0, 2]:g}, {K[1, 2]:g})" in line and "--depth-size 160 120 fits it" in line


def test_a_depth_size_of_another_aspect_needs_its_intrinsics(files):
    with pytest.raises(R.InputError, match="give --depth-K"):
        UI.load_inputs(files["image"], files["cloud"], [float(v) for v in files["K"]], depth_size=(100, 100))
    pair = UI.load_inputs(files["image"], files["cloud"], [float(v) for v in files["K"]], depth_size=(60, 80))
    assert pair.depth_size == (60, 80)  # half the image, same aspect: accepted


# --------------------------------------------------------------------------------------
# Photos with an EXIF orientation; intrinsics with skew.

def _jpeg_with_orientation(path: Path, rgb: np.ndarray, tag: int) -> Path:
    from PIL import Image

    im = Image.fromarray(rgb)
    exif = Image.Exif()
    exif[0x0112] = tag
    im.save(path, quality=95, exif=exif.tobytes())
    return path


def test_an_exif_rotation_is_applied_to_neither_view(files, capsys):
    pair = files["pair"]
    photo = _jpeg_with_orientation(files["tmp"] / "rotated.jpg", pair.image, 6)  # "rotate 90 deg clockwise"
    img = read_rgb(photo)
    assert img.shape == pair.image.shape  # as stored: 120 x 160, not turned to 160 x 120
    assert np.abs(img.astype(int) - pair.image.astype(int)).mean() < 8  # the same pixels (JPEG)
    loaded = UI.load_inputs(photo, files["cloud"], [float(v) for v in files["K"]],
                           image_depth=files["image_depth"])  # the depth map, as stored, fits it
    assert loaded.image.shape[:2] == loaded.depth_gt.shape
    note = " ".join(loaded.meta["notes"])
    assert "EXIF orientation 6" in note and "NOT applied" in note


def test_intrinsics_with_skew_are_refused(files, capsys, tmp_path):
    K = files["pair"].K_image.copy()
    K[0, 1] = 4.0
    with pytest.raises(ValueError, match="skew K\\[0, 1\\] = 4"):
        cameras.check_intrinsics(K, (120, 160))
    (tmp_path / "K.txt").write_text("\n".join(" ".join(f"{v:.6f}" for v in row) for row in K))
    rc, out, err = _run([str(files["image"]), str(files["cloud"]), "--intrinsics", str(tmp_path / "K.txt"), *FAST,
                         "--image-depth", str(files["image_depth"])], capsys)
    _one_line(rc, err, "skew")
    # Zero skew keeps the projection and the lifting exactly as they were.
    cameras.check_intrinsics(files["pair"].K_image, (120, 160))


# --------------------------------------------------------------------------------------
# Depth units against the cloud; the PLY header; poses that look away.

@pytest.mark.parametrize("factor, fits", [(2.0, "500"), (1 / 3, "3000"), (10.0, "100")])
def test_depth_in_other_units_is_caught_against_the_cloud(files, factor, fits, capsys, tmp_path):
    # factor 2: 2 mm units read as millimetres (depth halves); 1/3 and 10: a depth off by 3x / 10x
    # whose median still lies in the 0.1..20 m range the reader checks.
    depth = files["pair"].depth_gt
    raw = np.clip(np.round(depth * 1000 / factor), 0, 65534).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "depth.png"), raw)
    rc, out, err = _run([*_base(files), "--image-depth", str(tmp_path / "depth.png"), "--gt-T-pc-cam",
                         str(files["gt_T_pc_cam"]), *FAST, "--out", str(tmp_path / "o")], capsys)
    line = _one_line(rc, err, "--depth-scale 1000 looks wrong")
    suggested = float(re.search(r"--depth-scale ([\d.e+]+) fits", line).group(1))
    assert abs(suggested / float(fits) - 1) < 0.05, line


def test_depth_in_the_right_units_passes_the_check(files):
    pair = UI.load_inputs(files["image"], files["cloud"], [float(v) for v in files["K"]],
                         gt_T_cam_pc=cameras.invert(np.loadtxt(files["gt_T_pc_cam"])), image_depth=files["image_depth"])
    assert pair.depth_gt is not None


def test_a_ply_whose_header_counts_fewer_vertices_than_its_body_is_refused(files, capsys, tmp_path):
    n = len(read_points(files["cloud"]))
    data = Path(files["cloud"]).read_bytes()
    bad = tmp_path / "half.ply"
    bad.write_bytes(data.replace(f"element vertex {n}\n".encode(), f"element vertex {n // 2}\n".encode(), 1))
    with pytest.raises(ValueError, match=f"header declares {n // 2} vertices but the body holds {n}"):
        read_points(bad)
    ascii_ply = tmp_path / "half_ascii.ply"
    pts = read_points(files["cloud"])[:100]
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 50\nproperty float x\nproperty float y\n"
                         "property float z\nend_header\n" + "\n".join(" ".join(f"{v:.5f}" for v in p) for p in pts))
    with pytest.raises(ValueError, match="header declares 50 vertices but the body holds 100"):
        read_points(ascii_ply)
    rc, out, err = _run([str(files["image"]), str(bad), "--K", *files["K"], *FAST], capsys)
    _one_line(rc, err, "header declares")


def test_an_inverted_ground_truth_pose_is_refused(files, capsys, tmp_path):
    # gt_T_pc_cam given as --gt-T-cam-pc: the camera then looks away from the whole cloud.
    rc, out, err = _run([*_base(files), "--gt-T-cam-pc", str(files["gt_T_pc_cam"]), *FAST,
                         "--image-depth", str(files["image_depth"]), "--out", str(tmp_path / "o")], capsys)
    _one_line(rc, err, "did you give --gt-T-cam-pc for --gt-T-pc-cam")


def test_an_inverted_depth_pose_is_refused(files, capsys, tmp_path):
    # The sensor's pose in the cloud's frame is T_world (the cloud of frame 40 was moved by it);
    # its inverse, T_sensor_pc, shows none of the cloud.
    np.savetxt(tmp_path / "right.txt", files["T_world"])
    np.savetxt(tmp_path / "inverted.txt", cameras.invert(files["T_world"]))
    pair = UI.load_inputs(files["image"], files["cloud"], [float(v) for v in files["K"]],
                         depth_pose=np.loadtxt(tmp_path / "right.txt"))
    assert pair.meta["depth_camera"]
    rc, out, err = _run([*_base(files), "--depth-pose", str(tmp_path / "inverted.txt"), *FAST,
                         "--image-depth", str(files["image_depth"]), "--out", str(tmp_path / "o")], capsys)
    _one_line(rc, err, "--depth-pose")
    assert "its inverse shows" in err


# --------------------------------------------------------------------------------------
# A cloud 5,000 km from its origin (UTM): re-centred before solving, restored after.

def test_a_cloud_far_from_its_origin_gets_the_pose_it_gets_near_it():
    # An ICL pair with its sensor (the depth side is the sensor's own depth map) and the true depth
    # as the monocular one; its cloud and poses moved 5,831 km away (UTM-like). Its points sit on
    # a 2^-20 m grid, so moving them there and back is exact: the far cloud, re-centred, hands the
    # solver exactly what the near cloud moved by the same whole metres does, and the pose comes
    # back in the far coordinates. Before, PnP ran on coordinates of 5e6 m (on this pair: 8
    # inliers and RE 29 deg, against 33 inliers and 3.9 deg near the origin).
    from freereg_lib.commands import inputs_check as IC

    pair = ICLSample().pair(60, 70)
    pair = dataclasses.replace(pair, points=np.round(pair.points * 2.0**20) / 2.0**20)
    pair.meta.update(depth_camera=True, has_gt=True)
    offset = np.array([5.0e6, 3.0e6, 100.0])
    T_off = cameras.make_pose(np.eye(3), offset)
    far = dataclasses.replace(pair, points=pair.points + offset, T_pc_sensor=T_off @ pair.T_pc_sensor,
                              T_cam_pc=pair.T_cam_pc @ cameras.invert(T_off))
    assert R.recentre_offset(far.points) is not None and R.recentre_offset(pair.points) is None  # near: left alone
    c = np.round(far.T_pc_sensor[:3, 3])  # a cloud with its depth camera is re-centred on that sensor
    c_near = c - offset  # the same whole metres, seen from the near cloud
    near = dataclasses.replace(pair, points=pair.points - c_near, T_pc_sensor=R.shift_frame(pair.T_pc_sensor, c_near),
                               T_cam_pc=R.shift_pose(pair.T_cam_pc, c_near))
    cfg = config_for("demo", ransac_iters=3000)
    backend = get_backend("stub", cfg, mono_mae=1e-9)
    lines: list[str] = []
    near_reg = R.register(near, backend, cfg, method="FreeReg-G", solver="pnp", log=None)
    far_reg = R.register(far, backend, cfg, method="FreeReg-G", solver="pnp", log=lines.append)
    assert any("re-centred" in ln for ln in lines), lines
    assert near_reg.pose.success and near_reg.n_inliers == far_reg.n_inliers and near_reg.n_inliers >= 20
    expected = near_reg.T_cam_pc @ cameras.make_pose(np.eye(3), -c_near) @ cameras.invert(T_off)
    re_deg = cameras.rotation_error_deg(far_reg.T_cam_pc[:3, :3], expected[:3, :3])
    centre = np.linalg.norm(cameras.invert(far_reg.T_cam_pc)[:3, 3] - cameras.invert(expected)[:3, 3])
    assert re_deg < 1e-3 and centre < 1e-6, (re_deg, centre)
    assert abs(far_reg.errors["RE"] - near_reg.errors["RE"]) < 1e-3 and far_reg.errors["RE"] < 10
    assert np.array_equal(far_reg.pair.points, far.points) and np.allclose(far_reg.pair.T_cam_pc, far.T_cam_pc)


# --------------------------------------------------------------------------------------
# A depth PNG with scattered 65535 pixels (a sensor's "no reading").

def test_scattered_65535_depth_pixels_are_read_as_no_depth_with_a_note(files, tmp_path):
    # As the official code, whose depth masks ((0.01, 10) m indoors) drop the 65.535 m they
    # would read as: no depth there, and one line counts them. Before, nothing said so, and a
    # stub run on such a file ended in "3 usable matches" under a hint about --K.
    raw = cv2.imread(str(files["image_depth"]), cv2.IMREAD_UNCHANGED)
    bad = np.random.default_rng(0).random(raw.shape) < 0.2
    holed = raw.copy()
    holed[bad] = 65535
    cv2.imwrite(str(tmp_path / "holed.png"), holed)
    K = [float(v) for v in files["K"]]
    pair = UI.load_inputs(files["image"], files["cloud"], K, image_depth=tmp_path / "holed.png",
                          gt_T_cam_pc=cameras.invert(np.loadtxt(files["gt_T_pc_cam"])))
    assert np.all(pair.depth_gt[bad] == 0) and np.array_equal(pair.depth_gt[~bad], raw[~bad] / 1000.0)
    notes = [n for n in pair.meta["notes"] if "65535" in n]
    assert notes == [f"--image-depth {tmp_path / 'holed.png'}: {int(bad.sum())} of {raw.size} pixels "
                     f"({100 * bad.mean():.2g} %) hold 65535, a depth sensor's 'no reading': read as no depth, as 0 is"]
    hint = UI.failure_hint(pair, None, "--K", "--depth-scale 1000")
    holes = 100 * np.mean(pair.depth_gt == 0)  # the file's own zeros and the 65535s
    assert f"none at {holes:.0f} % of its pixels (0 or 65535)" in hint and "--backend stub" in hint, hint
    clean = UI.load_inputs(files["image"], files["cloud"], K, image_depth=files["image_depth"])
    assert not any("65535" in n for n in clean.meta["notes"])
