"""Data entering the library: real-data quirks are fixed where the files are read, and files or
pairs that would give silently wrong numbers are refused with a message naming the file or field.

Each case is one a new user met on real data: 7-Scenes / 3DMatch pose files that are
orthonormal only to ~3e-4 and depth PNGs that mark "no measurement" with 65535; normalised or
other-resolution intrinsics; depth or translations in millimetres; transposed pose files;
overlaps in percent; truncated JPEGs; a misspelt key in the demo's intrinsics.json; depth_size
given as (W, H). The trees are the tiny rendered ones of ``test_loaders``.
"""
from __future__ import annotations

import dataclasses
import json
import warnings

import cv2
import numpy as np
import pytest
from test_loaders import POSES, assert_convention, make_3dmatch, make_demo, make_scannet, render, write_rgb

from freereg_lib import config_for
from freereg_lib.data import sources, synthetic
from freereg_lib.data.datasets import common, pairlists, registry
from freereg_lib.data.datasets.demo import load_demo_pair
from freereg_lib.data.datasets.scannet import ScanNet
from freereg_lib.data.datasets.threedmatch import FreeRegScenes, ThreeDMatch
from freereg_lib.geometry import cameras, projection

K3 = cameras.intrinsics(585, 585, 320, 240)


@pytest.fixture(scope="module")
def pair():
    return synthetic.make_pair("indoor", seed=0, image_size=(120, 160))


def _off_orthonormal(T: np.ndarray, eps: float = 1.5e-4) -> np.ndarray:
    """``T`` with R multiplied by ``I + E`` (E symmetric, entries ``eps``): max |R^T R - I| ~ 2 eps,
    as 7-Scenes / 3DMatch pose files are written."""
    E = np.array([[1.0, 0.6, -0.4], [0.6, -0.8, 0.5], [-0.4, 0.5, 0.9]]) * eps
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ (np.eye(3) + E)
    return out


# --------------------------------------------------------------------------------------
# A 7-Scenes-like scene in the 3DMatch layout: loads, warns once, holes are 0.

def make_7scenes(root):
    """make_3dmatch's tree with pose files off orthonormal by ~3e-4 and 65535 in every depth PNG."""
    root = make_3dmatch(root)
    q = root / "7-scenes-fake" / "query"
    for k, T in enumerate(POSES[:3]):
        np.savetxt(q / f"{k}_pose.txt", _off_orthonormal(T))
        raw = cv2.imread(str(q / f"{k}.depth.png"), cv2.IMREAD_UNCHANGED)
        raw[:40] = 65535  # the top rows: no measurement
        raw[200:220, 300:400] = 65535
        cv2.imwrite(str(q / f"{k}.depth.png"), raw)
    return root


def test_7scenes_poses_and_65535_depth_load_with_a_warning_and_holes(tmp_path):
    root = make_7scenes(tmp_path / "3dm")
    q = root / "7-scenes-fake" / "query"
    assert 2e-4 < cameras.orthonormality(np.loadtxt(q / "0_pose.txt")[:3, :3]) < 4e-4
    ds = ThreeDMatch(root)
    with pytest.warns(RuntimeWarning, match=r"query/0_pose\.txt: R is orthonormal only to 3\.\de-04 .*"
                                            r"re-orthonormalised .*Further pose files in .*query are fixed"):
        pair = ds.pair(ds.pair_list()[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same folder does not warn twice, and the pair is rigid
        pair2 = ds.pair(ds.pair_list()[1])
        pair.validate()
        pair2.validate()
    assert cameras.orthonormality(pair.T_cam_pc[:3, :3]) < 1e-12
    np.testing.assert_allclose(pair.T_cam_pc, cameras.invert(POSES[0]) @ POSES[1], atol=2e-3)
    # 65535 is a hole: nothing at 65.5 m in the cloud, the true depth or the sensor depth.
    assert pair.points[:, 2].max() < 10 and pair.depth_gt.max() < 10 and pair.sensor_depth.max() < 10
    assert not pair.sensor_depth[:40].any() and not pair.depth_gt[:40].any()
    assert_convention(pair)


def test_3dmatch_sensor_depth_is_the_depth_png_bit_for_bit(tmp_path):
    root = make_7scenes(tmp_path / "3dm")
    ds = ThreeDMatch(root)
    with pytest.warns(RuntimeWarning):
        pair = ds.pair(ds.pair_list()[0])
    raw = cv2.imread(str(root / "7-scenes-fake" / "query" / "1.depth.png"), cv2.IMREAD_UNCHANGED)
    expected = np.where(raw == 65535, 0.0, raw.astype(np.float64) / 1000.0)
    assert pair.sensor_depth.dtype == np.float64 and pair.sensor_depth.shape == pair.depth_size
    assert pair.sensor_depth.tobytes() == expected.tobytes()
    assert (pair.sensor_depth[raw == 65535] == 0).all() and (raw == 65535).sum() > 1000
    # The cloud is the back-projection of exactly that array (no voxel grid on 3DMatch).
    assert np.array_equal(pair.points, cameras.backproject(pair.sensor_depth, K3)[0])
    # And the pipeline's depth map is that raw sensor depth, holes kept (no densification).
    from freereg_lib import config_for, pipeline

    view = pipeline.depth_view(pair, config_for("3dmatch"))
    in_range = np.where((expected > 0.01) & (expected < 10.0), expected, 0.0)
    assert view.dense.tobytes() == in_range.tobytes()


def test_scannet_and_kitti_fill_sensor_depth(tmp_path):
    root, K_col, K_dep = make_scannet(tmp_path / "scannet")
    ds = ScanNet(root, frame_step=1, max_gap=20)
    pair = ds.pair(ds.pair_list()[0])  # (0, 10)
    expected = common.read_depth(root / "scene0707_00" / "depth" / "10.png")
    assert pair.sensor_depth.tobytes() == expected.tobytes()
    # No 3 cm voxel grid: the cloud is the depth map's back-projection, as the official code's.
    assert np.array_equal(pair.points, cameras.backproject(pair.sensor_depth, K_dep)[0])
    pair.validate()
    # The official ScanNet layout (FreeRegScenes with ScanNet's cameras) likewise.
    off = registry.open_dataset("scannet", make_3dmatch(tmp_path / "sn"))
    assert off.voxel is None


def test_kitti_sensor_depth_is_scan_j_projected_on_the_depth_camera(tmp_path):
    from test_loaders import test_kitti_calibration_oxts_poses_crop_and_pose_convention as make_kitti

    from freereg_lib.data.datasets.kitti import KittiDC

    make_kitti(tmp_path)  # writes the drive (and checks the loader's conventions)
    ds = KittiDC(tmp_path / "kitti", frame_step=1)
    entry = ds.pair_list()[0]
    pair = ds.pair(entry)
    T_cam2_velo, _ = ds.calibration("2011_09_26")
    scan_j = ds.scan(entry.scene, entry.cloud_frame)
    expected, _ = projection.project_to_depth(scan_j, pair.K_depth, T_cam2_velo, pair.depth_size, depth_min=0.1)
    assert np.array_equal(pair.sensor_depth, expected) and (pair.sensor_depth > 0).any()
    assert np.array_equal(pair.points, scan_j)
    pair.validate()  # outdoor depths (20 m) pass the units check


# --------------------------------------------------------------------------------------
# Pose files.

def test_pose_files_transposed_bad_last_row_and_far_from_a_rotation_are_refused(tmp_path):
    T = POSES[1]
    np.savetxt(tmp_path / "t.txt", T.T)
    with pytest.raises(ValueError, match=r"t\.txt is not a rigid transform: .*it looks transposed: pass T\.T"):
        common.read_pose_txt(tmp_path / "t.txt")
    np.savetxt(tmp_path / "t7.txt", _off_orthonormal(T).T)  # transposed and 7-Scenes-rounded
    with pytest.raises(ValueError, match=r"t7\.txt is not a rigid transform: .*looks transposed"):
        common.read_pose_txt(tmp_path / "t7.txt")
    bad = T.copy()
    bad[3] = [0.0, 0.0, 0.5, 1.0]
    np.savetxt(tmp_path / "row.txt", bad)
    with pytest.raises(ValueError, match=r"row\.txt is not a rigid transform: .*its last row is \[0\.0, 0\.0, 0\.5, 1\.0\]"):
        common.read_pose_txt(tmp_path / "row.txt")
    sheared = _off_orthonormal(T, 2e-2)  # max |R^T R - I| ~ 4e-2: no rotation
    np.savetxt(tmp_path / "shear.txt", sheared)
    with pytest.raises(ValueError, match=r"shear\.txt is not a rigid transform: .*max \|R\^T R - I\| = 0\.0[34]\d*, "
                                         r".*farther from a rotation than the 0\.01") as info:
        common.read_pose_txt(tmp_path / "shear.txt")
    assert "scale of" not in str(info.value)  # not "R carries a scale of 1 (a similarity)"
    # Off by 3e-4 in a pair built by hand: check_pose fixes it, with the real deviation named.
    with pytest.warns(RuntimeWarning, match=r"T: R is orthonormal only to 3\.\de-04"):
        fixed = cameras.check_pose(_off_orthonormal(T), "T")
    assert cameras.is_rigid(fixed, 1e-12) and np.allclose(fixed, T, atol=1e-3)


def test_translations_in_millimetres_are_refused(tmp_path, pair):
    root = make_3dmatch(tmp_path / "3dm")
    q = root / "7-scenes-fake" / "query"
    T = POSES[1].copy()
    T[:3, 3] *= 1000
    np.savetxt(q / "1_pose.txt", T)
    ds = ThreeDMatch(root)
    with pytest.raises(ValueError, match=r"1_pose\.txt: the translation \|t\| = \d{4}\.\d* is longer than the 100 m "
                                         r"this dataset allows; it looks like millimetres read as metres"):
        ds.pair(ds.pair_list()[0])
    mm = pair.T_cam_pc.copy()
    mm[:3, 3] *= 1000
    mm[:3, 3] += [0, 0, 500]  # wherever the synthetic camera is, 500 m puts it far away
    with pytest.raises(ValueError, match=r"^pair .*: T_cam_pc puts its camera .* m from the point cloud, which is "
                                         r".* m across: its translation looks like millimetres"):
        dataclasses.replace(pair, T_cam_pc=mm).validate()


# --------------------------------------------------------------------------------------
# Depth units, overlaps, intrinsics, sizes.

def test_depth_in_millimetres_where_metres_are_expected(tmp_path, pair):
    root = make_3dmatch(tmp_path / "3dm")
    ds = FreeRegScenes(root, "3dmatch", K3, K3, (480, 640), (480, 640), depth_scale=1.0)  # mm read as m
    with pytest.raises(ValueError, match=r"1\.depth\.png: the median depth \d{4} m is outside the 0\.1\.\.20 m "
                                         r"expected for this dataset; it looks like millimetres read as metres; "
                                         r"depth_scale \(raw value per metre\) is 1, try 1000"):
        ds.pair(ds.pair_list()[0])
    # A hand-built pair whose true depth is in millimetres: refused, not scored as IR 0.
    with pytest.raises(ValueError, match=r"^pair .*: depth_gt's median \d+ is \d+ x the median depth .* m of the point "
                                         r"cloud seen from the depth camera: depth_gt looks like millimetres"):
        dataclasses.replace(pair, depth_gt=pair.depth_gt * 1000).validate()
    with pytest.raises(ValueError, match=r"sensor_depth's median .* looks like millimetres"):
        dataclasses.replace(pair, sensor_depth=np.full(pair.depth_size, 2500.0)).validate()
    # Synthetic indoor / outdoor pairs pass (the embedded ICL ones: test_robustness).
    synthetic.make_pair("outdoor", seed=1, image_size=(64, 208)).validate()


def test_overlaps_in_percent_are_refused(tmp_path):
    root = make_3dmatch(tmp_path / "3dm", overlaps="0 1 62\n0 2 21\n1 2 45\n")
    with pytest.raises(ValueError, match=r"overlap\.txt: overlaps range over 21\.\.62, expected fractions in \[0, 1\]; "
                                         r"they look like percentages"):
        ThreeDMatch(root).pair_list()
    with pytest.raises(ValueError, match=r"min_overlap = 30: it is a fraction"):
        ThreeDMatch(root, min_overlap=30)


@pytest.mark.parametrize("K, message", [
    (cameras.intrinsics(0.9, 1.2, 0.5, 0.5), r"K_image holds normalised intrinsics: multiply row 0 by W and row 1 by H "
                                             r"\(K\[0\] \*= 160; K\[1\] \*= 120\)"),
    (cameras.intrinsics(1.1, 1.1, 0.49, 0.51), r"K_image holds normalised intrinsics"),
    # Made for a 2x image: the principal point is at this image's far corner.
    (cameras.intrinsics(280.0, 280.0, 159.5, 119.5), r"K_image's principal point \(cx, cy\) = \(159\.5, 119\.5\) is far "
                                                     r"from the centre .*K looks made for a 320 x 240 image"),
    # Made for a 4x image: outside this one.
    (cameras.intrinsics(560.0, 560.0, 319.5, 239.5), r"K_image's principal point .* lies outside its 160 x 120 .*K looks made for a 640 x 480 image"),
    # Made for a half-size image: inside, but at the centre of an 80 x 60 image.
    (cameras.intrinsics(70.0, 70.0, 39.5, 29.5), r"K_image's principal point .* is far from the centre \(79\.5, 59\.5\) .*looks made for a 80 x 60 "
                                                 r"image.*scale_intrinsics\(K, 2, 2\)"),
])
def test_normalised_and_other_resolution_intrinsics_are_refused(pair, K, message):
    with pytest.raises(ValueError, match=rf"^pair synthetic-indoor/seed0000: {message}"):
        dataclasses.replace(pair, K_image=K).validate()


def test_intrinsics_checked_where_they_enter(tmp_path):
    with pytest.raises(ValueError, match=r"3dmatch K_image holds normalised intrinsics"):
        FreeRegScenes(make_3dmatch(tmp_path / "3dm"), "3dmatch", K3 / np.array([[640], [480], [1]]), K3,
                      (480, 640), (480, 640))
    # KITTI's cropped camera (principal point off centre along one axis) passes.
    cameras.check_intrinsics(cameras.intrinsics(721.5, 721.5, 609.6, 22.9), (225, 1242), "K")
    root, K_col, _ = make_scannet(tmp_path / "scannet")
    M = np.eye(4)
    M[:3, :3] = K_col / np.array([[96], [72], [1]])
    np.savetxt(root / "scene0707_00" / "intrinsic" / "intrinsic_color.txt", M)
    ds = ScanNet(root, frame_step=1, max_gap=20)
    with pytest.raises(ValueError, match=r"intrinsic_color\.txt holds normalised intrinsics"):
        ds.pair(ds.pair_list()[0])


def test_depth_size_given_as_w_h_is_refused(pair):
    H, W = pair.depth_size
    with pytest.raises(ValueError, match=rf"^pair .*: depth_size is \(H, W\); you gave \(W, H\)\? depth_size = "
                                         rf"\({W}, {H}\) .*\({H}, {W}\) fits it"):
        dataclasses.replace(pair, depth_size=(W, H)).validate()


# --------------------------------------------------------------------------------------
# Image files.

def test_truncated_jpeg_and_png_are_refused_naming_the_file(tmp_path):
    img = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8), (9, 9), 3)
    for ext in ("jpg", "png"):
        cv2.imwrite(str(tmp_path / f"ok.{ext}"), img)
        data = (tmp_path / f"ok.{ext}").read_bytes()
        (tmp_path / f"cut.{ext}").write_bytes(data[: len(data) * 2 // 3])
        kind = "JPEG" if ext == "jpg" else "PNG"
        with pytest.raises(ValueError, match=rf"cut\.{ext} is a truncated {kind} .*the file was cut short"):
            common.read_rgb(tmp_path / f"cut.{ext}")
        assert common.read_rgb(tmp_path / f"ok.{ext}").shape == (120, 160, 3)
    # Data after a JPEG's end (some cameras append their own) is not a truncation.
    (tmp_path / "trailer.jpg").write_bytes((tmp_path / "ok.jpg").read_bytes() + b"\x00" * 10 + b"x" * 8000)
    np.testing.assert_array_equal(common.read_rgb(tmp_path / "trailer.jpg"), common.read_rgb(tmp_path / "ok.jpg"))
    depth = (tmp_path / "d.png")
    cv2.imwrite(str(depth), np.random.default_rng(1).integers(500, 3000, (120, 160)).astype(np.uint16))
    (tmp_path / "dcut.png").write_bytes(depth.read_bytes()[:-200])
    with pytest.raises(ValueError, match=r"dcut\.png is a truncated PNG"):
        common.read_depth(tmp_path / "dcut.png")
    # Through a loader: the ScanNet export's colour JPEGs.
    root, _, _ = make_scannet(tmp_path / "scannet")
    jpg = root / "scene0707_00" / "color" / "0.jpg"
    write_rgb(jpg, (72, 96), 0)
    jpg.write_bytes(jpg.read_bytes()[:-400])
    ds = ScanNet(root, frame_step=1, max_gap=20)
    with pytest.raises(ValueError, match=r"color/0\.jpg is a truncated JPEG"):
        ds.pair(ds.pair_list()[0])


# --------------------------------------------------------------------------------------
# The demo.

def test_demo_intrinsics_with_a_misspelt_key_are_refused(tmp_path):
    root, *_ = make_demo(tmp_path / "demo")
    path = root / "intrinsics.json"
    cams = json.loads(path.read_text())
    cams["rgb_intrinsics"] = cams.pop("rgb_intrinsic")
    path.write_text(json.dumps(cams))
    with pytest.raises(ValueError, match=r"intrinsics\.json: unknown key\(s\) \['rgb_intrinsics'\] \('rgb_intrinsics': "
                                         r"did you mean 'rgb_intrinsic'\?\); expected keys: \['dpt_intrinsic', "
                                         r"'dpt_scale', 'dpt_size', 'rgb_intrinsic', 'rgb_size'\]"):
        load_demo_pair(root)
    cams["rgb_intrinsic"] = cams.pop("rgb_intrinsics")
    cams["dpt_size"] = cams["dpt_size"][::-1]  # [H, W]
    path.write_text(json.dumps(cams))
    with pytest.raises(ValueError, match=r"intrinsics\.json: dpt_size is \[W, H\] .*you gave \[H, W\]\?"):
        load_demo_pair(root)


def test_demo_is_a_dataset_everywhere(tmp_path):
    root, *_ = make_demo(tmp_path / "demo")
    cfg = config_for("demo")
    assert not cfg.outdoor and cfg.depth_max == 15.0  # the official config/demo.yaml (ScanNet's setting)
    pairs = list(sources.iter_pairs("demo", None, root=str(root)))
    assert [p.name for p in pairs] == ["demo/source_rgb-target_pc"]
    assert pairs[0].validate() is pairs[0] and pairs[0].meta["dataset"] == "demo"
    assert config_for("Demo") == cfg
