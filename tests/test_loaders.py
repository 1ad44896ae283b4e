"""Dataset loaders on tiny fake trees written in each documented layout.

Depth maps are rendered exactly (ray casting an analytic room with a box in it), so a
loader's pose convention is pinned by warping the cloud of frame j into image i with
``T_cam_pc`` and comparing with image i's true depth; the inverse pose must fail.
"""
import json

import cv2
import numpy as np
import pytest

from freereg_lib.data.datasets import pairlists, registry
from freereg_lib.data.datasets.demo import load_demo_pair
from freereg_lib.data.datasets.kitti import KittiDC
from freereg_lib.data.datasets.scannet import ScanNet, frame_overlap
from freereg_lib.data.datasets.threedmatch import FreeRegScenes, ThreeDMatch
from freereg_lib.geometry import cameras, projection

ROOM = (np.array([-3.0, -2.5, 0.0]), np.array([3.0, 2.5, 2.8]))
BOX = (np.array([0.8, -0.6, 0.0]), np.array([1.6, 0.4, 1.1]))


def render(K, T_world_cam, size):
    """True depth ``(H, W)`` of the room (with its box) seen from ``T_world_cam``."""
    H, W = size
    uv = cameras.pixel_grid(H, W).reshape(-1, 2)
    rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T  # z = 1: ray length t is the depth
    d = rays @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (ROOM[0] - o) / d, (ROOM[1] - o) / d
        depth = np.nanmin(np.maximum(t1, t2), axis=1)  # leaving the room from inside
        b1, b2 = (BOX[0] - o) / d, (BOX[1] - o) / d
        near, far = np.nanmax(np.minimum(b1, b2), axis=1), np.nanmin(np.maximum(b1, b2), axis=1)
    hit = (far >= near) & (near > 0)
    depth[hit] = np.minimum(depth[hit], near[hit])
    return depth.reshape(H, W)


def write_depth(path, depth, scale=1000.0):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.round(depth * scale).astype(np.uint16))


def write_rgb(path, size, seed):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, (*size, 3), dtype=np.uint8))


def warp_check(pair):
    """(coverage, median |error| in m) of the cloud warped into the image vs the true depth."""
    warped, _ = projection.project_to_depth(pair.points, pair.K_image, pair.T_cam_pc, pair.image_size)
    both = (warped > 0) & (pair.depth_gt > 0)
    return both.mean(), (float(np.median(np.abs(warped[both] - pair.depth_gt[both]))) if both.any() else np.inf)


def assert_convention(pair, coverage=0.3, tol=0.02):
    cov, err = warp_check(pair)
    assert cov > coverage and err < tol, (cov, err)
    wrong = pair.__class__(**{**pair.__dict__, "T_cam_pc": cameras.invert(pair.T_cam_pc)})
    cov, err = warp_check(wrong)
    assert not (cov > coverage and err < tol), "the inverse pose passes too: the check is blind"


POSES = [  # indoor camera poses (eye, target) inside the room
    cameras.look_at([-1.8, -0.6, 1.4], [2.0, 0.2, 0.8]),
    cameras.look_at([-1.5, -0.3, 1.5], [2.0, 0.6, 0.7]),
    cameras.look_at([-1.0, 0.2, 1.3], [2.5, 1.4, 1.0]),
    cameras.look_at([-1.0, 0.0, 1.3], [-3.0, 0.5, 1.0]),  # looks the other way: no overlap
]


# --------------------------------------------------------------------------------------
# 3DMatch / the official FreeReg layout.

def make_3dmatch(root, scene="7-scenes-fake", overlaps="0 1 0.62\n0 2 0.21\n1 2 0.45\n"):
    q = root / scene / "query"
    K = cameras.intrinsics(585, 585, 320, 240)
    for k, T in enumerate(POSES[:3]):
        write_rgb(q / f"{k}.color.png", (480, 640), k)
        write_depth(q / f"{k}.depth.png", render(K, T, (480, 640)))
        np.savetxt(q / f"{k}_pose.txt", T)
    (q / "overlap.txt").write_text(overlaps)
    return root


def test_3dmatch_pairs_follow_the_overlap_rule_and_the_pose_convention(tmp_path):
    ds = ThreeDMatch(make_3dmatch(tmp_path / "3dm"))
    entries = ds.pair_list()
    assert [(e.image_frame, e.cloud_frame) for e in entries] == [("0", "1"), ("1", "2")]
    assert (tmp_path / "3dm" / "freereg_pairs_overlap0.3.txt").is_file()
    pair = ds.pair(entries[0])
    assert pair.image.shape == (480, 640, 3) and pair.depth_size == (480, 640)
    assert pair.name == "3dmatch/7-scenes-fake/0-1" and pair.meta["overlap"] == pytest.approx(0.62)
    np.testing.assert_allclose(pair.T_cam_pc, cameras.invert(POSES[0]) @ POSES[1], atol=1e-9)
    assert_convention(pair)
    assert_convention(ds.pair(entries[1]))


def test_pair_lists_are_built_once_fixed_and_refused_for_another_rule(tmp_path):
    root = make_3dmatch(tmp_path / "3dm")
    ThreeDMatch(root).pair_list()
    (root / "7-scenes-fake" / "query" / "overlap.txt").write_text("0 2 0.9\n")  # the data changes...
    assert len(ThreeDMatch(root).pair_list()) == 2  # ...the saved list does not
    header, entries = pairlists.read_pair_list(root / "freereg_pairs_overlap0.3.txt")
    assert header["dataset"] == "3dmatch" and header["rule"] == "overlap > 0.3"
    own = tmp_path / "lists" / "mine.txt"
    assert [e.key for e in ThreeDMatch(root, 0.5, pair_list=own).pair_list()] == ["7-scenes-fake/0-2"]
    with pytest.raises(ValueError, match="rule 'overlap > 0.5', not 3dmatch with 'overlap > 0.3'"):
        ThreeDMatch(root, pair_list=own).pair_list()


def test_sharded_pairs_cover_the_first_n_once(tmp_path):
    ds = ThreeDMatch(make_3dmatch(tmp_path / "3dm", overlaps="0 1 0.6\n1 2 0.5\n0 2 0.4\n2 1 0.7\n"))
    names = lambda it: [p.name for p in it]  # noqa: E731
    first3 = names(ds.pairs(n=3))
    assert len(first3) == 3 and len(ds) == 4
    assert sorted(names(ds.pairs(n=3, shard="0/2")) + names(ds.pairs(n=3, shard="1/2"))) == sorted(first3)


def test_missing_root_and_files_name_the_path_and_the_layout(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"(?s)missing 3dmatch root folder: .*nowhere.*expected layout:.*overlap.txt"):
        ThreeDMatch(tmp_path / "nowhere")
    root = make_3dmatch(tmp_path / "3dm")
    (root / "7-scenes-fake" / "query" / "1_pose.txt").unlink()
    ds = ThreeDMatch(root)
    with pytest.raises(FileNotFoundError, match=r"(?s)missing pose file: .*1_pose.txt.*expected layout"):
        ds.pair(ds.pair_list()[0])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no <scene>/query/ folder"):
        ThreeDMatch(tmp_path / "empty").pair_list()


def test_official_layout_with_separate_colour_and_depth_cameras(tmp_path):
    """ScanNet's official FreeReg data: a larger colour image than depth, other intrinsics."""
    K_rgb, K_dpt = cameras.intrinsics(72, 72, 52.0, 31.0), cameras.intrinsics(36, 36, 23.5, 17.5)
    q = tmp_path / "sn" / "scene0000_00" / "query"
    for k, T in enumerate(POSES[:2]):
        write_rgb(q / f"{k}.color.png", (72, 96), k)
        write_depth(q / f"{k}.depth.png", render(K_dpt, T, (36, 48)))
        np.savetxt(q / f"{k}_pose.txt", T)
    (q / "overlap.txt").write_text("0 1 0.5\n")
    ds = FreeRegScenes(tmp_path / "sn", "scannet", K_rgb, K_dpt, (72, 96), (36, 48), voxel=0.03)
    pair = ds.pair(ds.pair_list()[0])
    assert pair.depth_gt.shape == (72, 96) and pair.depth_size == (36, 48)
    # The resampled true depth of the colour image equals a direct rendering (up to pixels
    # whose nearest depth pixel sees across an edge).
    truth, seen = render(K_rgb, POSES[0], (72, 96)), pair.depth_gt > 0
    assert seen.mean() > 0.85  # the colour camera sees a little wider: its border has no depth
    # (off-centre principal point: resizing the depth map instead would be ~0.2 m off)
    assert np.median(np.abs(pair.depth_gt - truth)[seen]) < 0.02
    assert_convention(pair, coverage=0.15)
    with pytest.raises(ValueError, match=r"is 96 x 72, expected 640 x 480 for 3dmatch"):
        ThreeDMatch(tmp_path / "sn").pair(ds.pair_list()[0])


# --------------------------------------------------------------------------------------
# ScanNet export layout.

def make_scannet(root, scene="scene0707_00", frames=None):
    """A ScanNet export of ``frames`` (frame number -> pose; default: 0, 10, 20, 30 and 40,
    whose pose is lost tracking, all -inf). Returns the root and the colour / depth intrinsics."""
    s = root / scene
    K_col, K_dep = cameras.intrinsics(72, 72, 52.0, 31.0), cameras.intrinsics(36, 36, 23.5, 17.5)
    for sub in ("intrinsic", "pose"):
        (s / sub).mkdir(parents=True)
    for name, K in (("color", K_col), ("depth", K_dep)):
        M = np.eye(4)
        M[:3, :3] = K
        np.savetxt(s / "intrinsic" / f"intrinsic_{name}.txt", M)
    if frames is None:
        frames = {0: POSES[0], 10: POSES[1], 20: POSES[2], 30: POSES[3], 40: np.full((4, 4), -np.inf)}
    for f, T in frames.items():
        # The depth of a frame with a lost pose is rendered from POSES[1].
        write_rgb(s / "color" / f"{f}.jpg", (72, 96), f)
        write_depth(s / "depth" / f"{f}.png", render(K_dep, T if np.isfinite(T).all() else POSES[1], (36, 48)))
        np.savetxt(s / "pose" / f"{f}.txt", T)
    return root, K_col, K_dep


def test_scannet_export_overlaps_pairs_and_pose_convention(tmp_path):
    root, K_col, K_dep = make_scannet(tmp_path / "scannet")
    ds = ScanNet(root, frame_step=1, max_gap=20)
    entries = ds.pair_list()
    # 40 has an invalid pose; 30 looks away; pairs at most 20 frames apart.
    assert [(e.image_frame, e.cloud_frame) for e in entries] == [("0", "10"), ("0", "20"), ("10", "20")]
    assert all(0.3 < e.score <= 1 for e in entries)
    assert ds.pair_list_path.name == "freereg_pairs_overlap0.3_step1_gap20.txt"
    pair = ds.pair(entries[0])
    assert pair.image.shape == (72, 96, 3) and pair.depth_size == (36, 48)
    np.testing.assert_allclose(pair.K_image, K_col)
    np.testing.assert_allclose(pair.K_depth, K_dep)
    seen = pair.depth_gt > 0
    assert seen.mean() > 0.85 and np.median(np.abs(pair.depth_gt - render(K_col, POSES[0], (72, 96)))[seen]) < 0.02
    assert_convention(pair, coverage=0.15)


def test_frame_overlap_is_one_for_the_same_view_and_zero_looking_away():
    K = cameras.intrinsics(36, 36, 23.5, 17.5)
    d0, d3 = render(K, POSES[0], (36, 48)), render(K, POSES[3], (36, 48))
    assert frame_overlap(d0, d0, K, np.eye(4)) == 1.0
    assert frame_overlap(d0, d3, K, cameras.invert(POSES[0]) @ POSES[3]) == 0.0
    assert frame_overlap(d0, np.zeros_like(d0), K, np.eye(4)) == 0.0


# --------------------------------------------------------------------------------------
# KITTI raw drive.

def _calib_line(key, values):
    return f"{key}: " + " ".join(repr(float(v)) for v in np.ravel(values))


def test_kitti_calibration_oxts_poses_crop_and_pose_convention(tmp_path):
    root, date, drive = tmp_path / "kitti", "2011_09_26", "2011_09_26_drive_0002_sync"
    d = root / date / drive
    # Calibration, chosen; KITTI defines camera 2 from the Velodyne as [I | t2] R_rect [R | T].
    K = cameras.intrinsics(60.0, 60.0, 39.5, 170.0)
    t2 = np.array([0.06, 0.001, 0.002])
    R_rect = cameras.rotation_about([0, 1, 0], 0.01)
    T_cam0_velo = cameras.make_pose(np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0.0]]) @ cameras.rotation_about([0, 0, 1], 0.02),
                                    [0.004, -0.076, -0.27])
    T_velo_imu = cameras.make_pose(cameras.rotation_about([0, 0, 1], 0.01), [-0.81, 0.32, -0.80])
    (root / date).mkdir(parents=True)
    (root / date / "calib_cam_to_cam.txt").write_text("\n".join([
        "calib_time: 09-Jan-2012 13:57:47", _calib_line("R_rect_00", R_rect),
        _calib_line("P_rect_02", np.c_[K, K @ t2])]) + "\n")
    (root / date / "calib_velo_to_cam.txt").write_text("\n".join([
        "calib_time: 15-Mar-2012 11:37:16", _calib_line("R", T_cam0_velo[:3, :3]),
        _calib_line("T", T_cam0_velo[:3, 3]), "delta_f: 0 0"]) + "\n")
    (root / date / "calib_imu_to_velo.txt").write_text("\n".join([
        _calib_line("R", T_velo_imu[:3, :3]), _calib_line("T", T_velo_imu[:3, 3])]) + "\n")
    T_cam2_velo = cameras.make_pose(np.eye(3), t2) @ cameras.make_pose(R_rect, np.zeros(3)) @ T_cam0_velo
    # A wall 20 m ahead; three frames along the world x axis (lat 0: the Mercator y is 0).
    yy, zz = np.meshgrid(np.arange(-15, 15, 0.08), np.arange(-4, 8, 0.08))
    wall = np.stack([np.full(yy.size, 20.0), yy.ravel(), zz.ravel()], axis=1)
    motion = [(0.0, 0.0, 0.0), (3.0, 0.2, 0.05), (15.0, 0.1, -0.03)]  # x (m), alt (m), yaw (rad)
    T_world_velo = []
    for k, (x, alt, yaw) in enumerate(motion):
        name = f"{k:010d}"
        T_world_imu = cameras.make_pose(cameras.rotation_about([0, 0, 1], yaw), [x, 0.0, alt])
        T_world_velo.append(T_world_imu @ cameras.invert(T_velo_imu))
        oxts = [0.0, np.degrees(x / 6378137.0), alt, 0.0, 0.0, yaw] + [0.0] * 24
        (d / "oxts" / "data").mkdir(parents=True, exist_ok=True)
        (d / "oxts" / "data" / f"{name}.txt").write_text(" ".join(repr(float(v)) for v in oxts) + "\n")
        scan = cameras.transform(cameras.invert(T_world_velo[-1]), wall)
        (d / "velodyne_points" / "data").mkdir(parents=True, exist_ok=True)
        np.c_[scan, np.zeros(len(scan))].astype(np.float32).tofile(d / "velodyne_points" / "data" / f"{name}.bin")
        write_rgb(d / "image_02" / "data" / f"{name}.png", (190, 80), k)

    ds = KittiDC(root, frame_step=1)
    entries = ds.pair_list()
    assert [(e.scene, e.image_frame, e.cloud_frame) for e in entries] == [(f"{date}/{drive}", "0000000000", "0000000001")]
    assert entries[0].score == pytest.approx(np.linalg.norm(T_world_velo[0][:3, 3] - T_world_velo[1][:3, 3]), abs=1e-5)
    pair = ds.pair(entries[0])
    assert pair.image.shape == (40, 80, 3) and pair.depth_size == (40, 80)
    np.testing.assert_allclose(pair.K_image, K - [[0, 0, 0], [0, 0, 150], [0, 0, 0]])
    expected = T_cam2_velo @ cameras.invert(T_world_velo[0]) @ T_world_velo[1]
    np.testing.assert_allclose(pair.T_cam_pc, expected, atol=1e-6)
    np.testing.assert_allclose(pair.T_pc_sensor, cameras.invert(T_cam2_velo), atol=1e-9)
    assert (pair.depth_gt > 0).mean() > 0.9  # the densified LiDAR depth, as the official evaluation
    assert_convention(pair, coverage=0.3, tol=0.05)


# --------------------------------------------------------------------------------------
# The official demo.

def make_demo(root, rgb_size=(72, 96), dpt_size=(36, 48)):
    """The official demo layout with an intrinsics.json; returns (root, K_rgb, K_dpt, points)."""
    (h, w), (hd, wd) = rgb_size, dpt_size
    K_rgb = cameras.intrinsics(0.75 * w, 0.75 * w, 0.54 * w, 0.43 * h)
    K_dpt = cameras.intrinsics(0.75 * wd, 0.75 * wd, 0.49 * wd, 0.486 * hd)
    T_world_cam, T_world_sensor = POSES[0], POSES[1]
    points, _ = cameras.backproject(render(K_dpt, T_world_sensor, dpt_size), K_dpt)  # sensor frame
    (root / "just_for_eval").mkdir(parents=True)
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
    (root / "target_pc.ply").write_text(header + "\n".join(" ".join(repr(float(v)) for v in p) for p in points) + "\n")
    write_rgb(root / "source_rgb.png", rgb_size, 0)
    write_depth(root / "just_for_eval" / "source_rgb.gtd.png", render(K_rgb, T_world_cam, rgb_size))
    np.savetxt(root / "just_for_eval" / "rgb2pc.gt.pose.txt", cameras.invert(T_world_sensor) @ T_world_cam)
    (root / "intrinsics.json").write_text(json.dumps({
        "rgb_intrinsic": K_rgb.tolist(), "dpt_intrinsic": K_dpt.tolist(), "rgb_size": [w, h], "dpt_size": [wd, hd]}))
    return root, K_rgb, K_dpt, points


def test_demo_pair_inverts_the_rgb_to_cloud_pose(tmp_path):
    root, K_rgb, K_dpt, points = make_demo(tmp_path / "demo")
    T_world_cam, T_world_sensor = POSES[0], POSES[1]
    pair = load_demo_pair(root)
    assert [p.name for p in registry.open_dataset("demo", root).pairs()] == [pair.name]
    np.testing.assert_allclose(pair.points, points, atol=1e-12)
    np.testing.assert_allclose(pair.T_cam_pc, cameras.invert(T_world_cam) @ T_world_sensor, atol=1e-9)
    assert pair.depth_size == (36, 48) and pair.depth_gt.shape == (72, 96)
    assert_convention(pair, coverage=0.15)
    (root / "intrinsics.json").unlink()  # the demo's own cameras expect a 1296 x 968 image
    with pytest.raises(ValueError, match="is 96 x 72, but rgb_size is 1296 x 968"):
        load_demo_pair(root)


def test_open_dataset_by_name(tmp_path):
    assert isinstance(registry.open_dataset("3DMatch", make_3dmatch(tmp_path / "3dm")), ThreeDMatch)
    official = registry.open_dataset("scannet", tmp_path / "3dm")  # <scene>/query/: the official data
    # The official code's depth-side cloud is the back-projection of the depth map: no 3 cm voxel grid.
    assert isinstance(official, FreeRegScenes) and official.dataset == "scannet" and official.voxel is None
    root, _, _ = make_scannet(tmp_path / "export")
    assert isinstance(registry.open_dataset("scannet", root, frame_step=1), ScanNet)
    with pytest.raises(ValueError, match="unknown dataset 'nyu'"):
        registry.open_dataset("nyu", tmp_path)


def test_ply_reader_handles_binary_extra_properties_and_refuses_garbage(tmp_path):
    from freereg_lib.data.datasets.demo import read_ply_points

    pts = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    rec = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    rec["x"], rec["y"], rec["z"], rec["red"] = pts[:, 0], pts[:, 1], pts[:, 2], 7
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    (tmp_path / "b.ply").write_bytes(header.encode() + rec.tobytes())
    np.testing.assert_array_equal(read_ply_points(tmp_path / "b.ply"), pts.astype(np.float64))
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                                      "property float y\nproperty float z\nend_header\n1 2 oops\n")
    with pytest.raises(ValueError, match="cannot read the vertices of .*bad.ply"):
        read_ply_points(tmp_path / "bad.ply")
    (tmp_path / "short.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                        "property float y\nproperty float z\nend_header\n1 2 3\n")
    with pytest.raises(ValueError, match="expected 3 vertices, read 1"):
        read_ply_points(tmp_path / "short.ply")
