"""The depth handling, solvers and evaluation of the pipeline pinned to the official code
(WHU-USI3DV/FreeReg; docs/fidelity.md), each on a small hand-made case."""
import numpy as np
import pytest
from conftest import outlier_problem

from freereg_lib import config_for, pipeline
from freereg_lib.config import FreeRegConfig
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras, densify, metrics, pose, projection

K = cameras.intrinsics(20.0, 20.0, 15.5, 11.5)


def _step(h=10, w=10, col=5, near=1.0, far=2.0):
    d = np.full((h, w), near)
    d[:, col:] = far
    return d


def test_edge_filter_is_the_official_uncentred_6x6_window():
    # Window rows/cols [i-3, i+3): a pixel is dropped when its window reaches across the step
    # at column 5 (columns 3..7) and in the first 3 rows / columns, which the loop skips.
    out = projection.edge_filter(_step(), 0.2)
    kept = np.zeros((10, 10), bool)
    kept[3:, 8:] = True
    assert np.array_equal(out > 0, kept)
    assert np.all(out[kept] == 2.0)
    # The comparison is strict ("range < max_range" keeps): a range of exactly 1 m is dropped.
    assert not (projection.edge_filter(_step(), 1.0)[3:, 3:8] > 0).any()
    assert (projection.edge_filter(_step(), 1.0001)[3:, 3:] > 0).all()


def test_edge_filter_counts_holes_as_depth_zero():
    d = np.full((10, 10), 1.0)
    d[6, 6] = 0.0  # a hole: its 6 x 6 neighbourhood spans 1 m
    out = projection.edge_filter(d, 0.2)
    assert not (out[4:10, 4:10] > 0).any() and out[3, 3] == 1.0 and out[9, 3] == 1.0


def _sensor_pair(sensor_depth: np.ndarray) -> Pair:
    h, w = sensor_depth.shape
    pts, _ = cameras.backproject(sensor_depth, K)
    img = np.zeros((h, w, 3), np.uint8)
    return Pair(image=img, K_image=K, points=pts, K_depth=K.copy(), depth_size=(h, w), T_pc_sensor=np.eye(4),
                T_cam_pc=np.eye(4), depth_gt=sensor_depth.copy(), sensor_depth=sensor_depth, name="sensor")


def _holey_depth(seed=0):
    rng = np.random.default_rng(seed)
    d = rng.uniform(1.0, 3.0, size=(24, 32)).round(3)
    d[rng.random(d.shape) < 0.3] = 0.0  # holes, as 3DMatch's raw depth keeps them
    d[2:6, 2:9] = 0.0
    return d


def test_3dmatch_depth_map_is_the_raw_sensor_depth_bit_for_bit():
    d = _holey_depth()
    cfg = config_for("3dmatch")
    assert cfg.densify == "none"
    view = pipeline.depth_view(_sensor_pair(d), cfg)
    assert view.dense.tobytes() == d.tobytes() and view.raw.tobytes() == d.tobytes()


def test_scannet_densifies_the_sensor_depth_with_fill_in_fast():
    d = _holey_depth()
    view = pipeline.depth_view(_sensor_pair(d), config_for("scannet"))
    assert np.array_equal(view.raw, d)
    # Densified, then read back from the official uint16 PNG (cfg.dense_png): millimetres, truncated.
    expected = densify.png_round_trip(densify.fill_in_fast(d, max_depth=15.0), 1000.0)
    expected[(expected <= 0.01) | (expected >= 15.0)] = 0.0
    assert np.array_equal(view.dense, expected)
    assert (view.dense[d == 0] > 0).mean() > 0.9  # the holes are filled


def test_no_edge_filter_on_the_projected_cloud():
    # A cloud with a 1 m step seen by its own camera: every pixel comes back, the edge included.
    d = _step(24, 32, col=16)
    pts, _ = cameras.backproject(d, K)
    pair = _sensor_pair(d)
    pair.sensor_depth = None
    pair.points = pts
    view = pipeline.depth_view(pair, FreeRegConfig(densify="none", cloud_projection="round"))
    assert np.allclose(view.raw, d)
    # The official projection (truncation of K X / (z + 1e-5)) puts a pixel centre's point on the
    # pixel up and to the left: the map moves by one pixel, the step edge is still all there.
    view = pipeline.depth_view(pair, FreeRegConfig(densify="none"))
    assert np.allclose(view.raw[:-1, :-1], d[1:, 1:]) and (view.raw[:-1, :-1] > 0).all()


class _FixedMono:
    """A backend with a given monocular depth map and no diffusion."""

    def __init__(self, mono):
        self.mono = mono

    def mono_depth(self, image, depth_gt=None):
        return self.mono


def test_geometric_clouds_are_the_depth_map_and_the_edge_filtered_mono_depth(monkeypatch):
    from freereg_lib.features import geometric

    d = _holey_depth()
    pair = _sensor_pair(d)
    pair.points = np.vstack([pair.points, [[50.0, 50.0, 50.0]]])  # a stored cloud wider than the view
    mono = _step(24, 32, col=16, near=1.5, far=2.5)
    seen = []

    def fake(cloud, cfg, camera_location=None, at=None, backend=None):
        seen.append(np.asarray(cloud))
        return np.asarray(cloud)[:1], np.ones((1, 4))

    monkeypatch.setattr(geometric, "geometric_features", fake)
    cfg = config_for("scannet", keypoint_grid=(8, 8))
    feats = pipeline.compute_features(pair, _FixedMono(mono), cfg, diffusion=False, geometric=True)
    img_cloud, dep_cloud = seen
    expect_img, _ = cameras.backproject(projection.edge_filter(mono, 0.2), K)
    assert np.array_equal(img_cloud, expect_img)
    assert len(img_cloud) == (projection.edge_filter(mono, 0.2) > 0).sum() < mono.size
    expect_dep, _ = cameras.backproject(feats.view.dense, K)
    assert np.array_equal(dep_cloud, expect_dep)


def test_geometric_features_see_the_depth_side_in_its_camera_frame_whatever_the_clouds_frame(monkeypatch):
    # The official code back-projects the depth map with extrinsic = eye(4): FCGF, which is not
    # rotation invariant, sees the depth side in the depth camera's frame, never the cloud's.
    # A feature that is the point's own coordinates tells the frames apart.
    from freereg_lib.features import geometric

    def coordinates(cloud, cfg, camera_location=None, at=None, backend=None):
        cloud = np.asarray(cloud)
        return cloud, cloud.copy()

    monkeypatch.setattr(geometric, "geometric_features", coordinates)
    d = _holey_depth()
    cfg = config_for("scannet", keypoint_grid=(8, 8))
    mono = np.full(d.shape, 2.0)
    results = []
    for angle in (0.0, 0.7):  # the same scene, its cloud stored in two frames
        c, s_ = np.cos(angle), np.sin(angle)
        G = np.array([[c, 0, s_, 1.0], [0, 1, 0, -2.0], [-s_, 0, c, 0.5], [0, 0, 0, 1]])
        pair = _sensor_pair(d)
        pair.points = cameras.transform(G, pair.points)
        pair.T_pc_sensor, pair.T_cam_pc = G, cameras.invert(G)
        results.append(pipeline.compute_features(pair, _FixedMono(mono), cfg, diffusion=False, geometric=True))
    for feats in results:
        lifted = cameras.lift(feats.uv_depth, cameras.nearest_sample(feats.view.dense, feats.uv_depth), K)
        np.testing.assert_allclose(feats.geo_depth, lifted, atol=1e-9)  # camera frame, not G's
    np.testing.assert_allclose(results[0].geo_depth, results[1].geo_depth, atol=1e-9)
    assert not np.allclose(results[0].pts_depth, results[1].pts_depth)  # the keypoints stay in the cloud's frame


def test_evaluation_lifts_the_depth_side_with_its_true_depth():
    d = np.full((24, 32), 2.0)
    d[:, :4] = 0.0  # a hole in the depth frame's true depth
    pair = _sensor_pair(d)
    uv_dep = np.array([[10.0, 10.0], [20.0, 5.0], [30.0, 20.0], [1.0, 8.0]])
    # The features' depth-side points came from a densified map 0.5 m off: evaluation must not use them.
    feats = pipeline.PairFeatures(
        uv_image=uv_dep.copy(), pts_image=np.zeros((3, 3)), uv_depth=uv_dep,
        pts_depth=cameras.lift(uv_dep, np.full(4, 2.5), K), diff_image=None, diff_depth=None, geo_image=None,
        geo_depth=None, mono_depth=d, view=pipeline.DepthView(d, np.full_like(d, 2.5), np.full(d.shape, -1), None))
    m = pipeline.Matches(np.arange(4), np.arange(4))
    res = pose.PoseResult(np.eye(4), True, "pnp")
    scores = pipeline.evaluate(pair, feats, m, res, FreeRegConfig(densify="none"))  # 3DMatch: the raw map
    assert scores["IN"] == 3 and scores["IR"] == 1.0  # the hole's match is not evaluable
    assert scores["n_evaluable"] == 3
    # A dataset that densifies and has no truth file is scored on its densified map (official dpt_gtd).
    dense = pipeline.evaluate(pair, feats, m, res, FreeRegConfig(densify="fast"))
    assert dense["n_evaluable"] == 3 and dense["IN"] == 0  # 0.5 m off: no match within 0.3 m


def test_open3d_scoring_makes_the_official_call(monkeypatch):
    """``kabsch_scoring="open3d"``: the official code's Open3D call under the installed Open3D,
    all 50k iterations (confidence 1.0: no early stop), ransac_n 4, no checker, every keypoint."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    calls = {}
    real_criteria, real_ransac = reg.RANSACConvergenceCriteria, reg.registration_ransac_based_on_correspondence

    def criteria(iters, conf):
        calls["criteria"] = (iters, conf)
        return real_criteria(10, conf)  # keep the test fast; the call's arguments are what is pinned

    def ransac(src, tgt, corres, dist, est, n, checkers, crit):
        calls["ransac"] = (len(src.points), len(tgt.points), len(corres), dist, n, len(checkers))
        return real_ransac(src, tgt, corres, dist, est, n, checkers, crit)

    monkeypatch.setattr(reg, "RANSACConvergenceCriteria", criteria)
    monkeypatch.setattr(reg, "registration_ransac_based_on_correspondence", ransac)
    pts_cam, pts_pc, _ = outlier_problem()
    feats = pipeline.PairFeatures(np.zeros((300, 2)), pts_cam, np.zeros((300, 2)), pts_pc, None, None, None, None,
                                  None, None)
    m = pipeline.Matches(np.arange(0, 300, 3), np.arange(0, 300, 3))
    pipeline.solve(None, feats, m, FreeRegConfig(kabsch_scoring="open3d"), "kabsch")
    assert calls["criteria"] == (50_000, 1.0)
    assert calls["ransac"] == (300, 300, 100, 0.2, 4, 0)


@pytest.mark.parametrize("scoring", ["official", "open3d"])
def test_kabsch_recovers_a_similarity_with_outliers(scoring):
    pts_cam, pts_pc, T = outlier_problem(scale=1.3, outliers=0.5)
    res = pose.kabsch_ransac(pts_cam, pts_pc, 0.2, 5000, scoring=scoring)
    re, te = metrics.pose_errors(res.T_cam_pc, T)
    assert res.success and re < 0.5 and te < 0.05 and abs(res.scale - 1.3) < 0.01


def test_only_the_official_scoring_resists_a_shrinking_similarity():
    """Wrong matches clustered on one spot of a dense patch: a current Open3D's nearest-neighbour
    fitness prefers the model that shrinks the whole image side into the patch; open3d 0.12's
    score, the fraction of the matches within the inlier distance, does not."""
    rng = np.random.default_rng(3)
    T = cameras.make_pose(cameras.rotation_about([0, 1, 0], 0.3), [0.5, 0.2, 1.0])
    n = 300
    pts_pc = rng.uniform([-3, -1, 1], [3, 1, 6], size=(n, 3))
    pts_cam = cameras.transform(T, pts_pc)
    clustered = np.arange(n) < 90
    pts_pc[clustered] = rng.normal(scale=0.05, size=(90, 3)) + [0, 0, 3]
    scattered = (np.arange(n) >= 90) & (np.arange(n) < 150)
    pts_pc[scattered] = rng.uniform([-3, -1, 1], [3, 1, 6], size=(60, 3))
    # The depth side's keypoints: the matched ones and an unmatched dense patch around the spot.
    cloud = np.vstack([pts_pc, rng.normal(scale=0.15, size=(400, 3)) + [0, 0, 3]])
    corres = np.stack([np.arange(n), np.arange(n)], axis=1)
    current = pose.kabsch_ransac(pts_cam, cloud, 0.2, 5000, corres=corres, scoring="open3d")
    assert not (current.success and metrics.registered(*metrics.pose_errors(current.T_cam_pc, T), 5, 0.1))
    assert not current.success or current.scale < 0.3  # shrunk, or refined into a reflection
    scored = pose.kabsch_ransac(pts_cam, cloud, 0.2, 5000, corres=corres, scoring="official")
    re, te = metrics.pose_errors(scored.T_cam_pc, T)
    assert scored.success and re < 0.5 and te < 0.05


def _multiscale_by_the_steps(depth, max_depth=100.0):
    """IP-Basic's fill_in_multiscale written out step by step with boolean indexing (as its
    paper and FACTS.md list the steps), to pin the library's np.copyto version bit for bit."""
    import cv2

    def cross(n):
        k = np.zeros((n, n), np.uint8)
        k[n // 2, :] = k[:, n // 2] = 1
        return k

    def full(n):
        return np.ones((n, n), np.uint8)

    d_in = depth.astype(np.float32)
    near = (d_in > 0.1) & (d_in <= 15.0)
    med = (d_in > 15.0) & (d_in <= 30.0)
    far = d_in > 30.0
    s1 = d_in.copy()
    s1[d_in > 0.1] = max_depth - s1[d_in > 0.1]
    dil = {k: cv2.dilate(s1 * m, cross(n)) for k, m, n in (("far", far, 3), ("med", med, 5), ("near", near, 7))}
    s2 = s1.copy()
    for k in ("far", "med", "near"):
        s2[dil[k] > 0.1] = dil[k][dil[k] > 0.1]
    s3 = cv2.morphologyEx(s2, cv2.MORPH_CLOSE, full(5))
    s4 = s3.copy()
    s4[s3 > 0.1] = cv2.medianBlur(s3, 5)[s3 > 0.1]

    def below_top(a):
        mask = np.ones(a.shape, bool)
        for c in range(a.shape[1]):
            mask[: np.argmax(a[:, c] > 0.1), c] = False
        return mask

    empty = ~(s4 > 0.1) & below_top(s4)
    s5 = s4.copy()
    s5[empty] = cv2.dilate(s4, full(9))[empty]
    top = below_top(s5)
    s7 = s5.copy()
    for _ in range(6):
        empty = (s7 < 0.1) & top
        s7[empty] = cv2.dilate(s7, full(5))[empty]
    valid = (s7 > 0.1) & top
    s7[valid] = cv2.medianBlur(s7, 5)[valid]
    s7[valid] = cv2.bilateralFilter(s7, 5, 0.5, 2.0)[valid]
    out = s7.copy()
    out[s7 > 0.1] = max_depth - out[s7 > 0.1]
    return out.astype(np.float64)


def test_fill_in_multiscale_is_ip_basic_step_by_step():
    # LiDAR-like rows at three ranges (near, medium, far bins), the top rows empty (sky).
    rng = np.random.default_rng(0)
    d = np.zeros((60, 90))
    for r in range(20, 60, 3):
        cols = rng.random(90) < 0.6
        d[r, cols] = rng.choice([5.0, 22.0, 45.0]) + rng.normal(scale=0.3, size=cols.sum())
    d[40:, 70:] = 0.0  # a large hole below the top measurement
    ours = densify.fill_in_multiscale(d, hole_value=0.0)  # IP-Basic's own ending: holes stay empty
    assert np.array_equal(ours, _multiscale_by_the_steps(d))
    assert not (ours[:18] > 0).any() and (ours[42:, 72:84] > 0).all()
    official = densify.fill_in_multiscale(d)  # the official copy writes 255 m into them
    assert (official[:18] == 255.0).all() and np.array_equal(official[ours > 0], ours[ours > 0])
