"""Tests of the synthetic scenes: determinism, the Pair contract, the pose convention (the
image's true depth agrees with the point cloud), overlap control and the LiDAR's sparsity."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from freereg_lib.data.pair import Pair
from freereg_lib.data.synthetic import (
    CLASS_NAMES,
    DEFAULT_IMAGE_SIZE,
    LIDAR_ELEVATIONS_DEG,
    MAX_POINTS,
    make_pair,
    make_pairs,
    overlap_ratio,
)
from freereg_lib.geometry.cameras import invert, is_rigid, project, transform

KINDS = ("indoor", "outdoor")
# Small images keep the tests that only need the machinery fast.
TINY = (60, 80)


@pytest.fixture(scope="module")
def pairs() -> dict[str, Pair]:
    return {kind: make_pair(kind, seed=0) for kind in KINDS}


def _zbuffer(points_cam: np.ndarray, values: np.ndarray, K: np.ndarray,
             size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point's depth ``(H, W)`` (inf where none) and its ``values`` (-1 where none)."""
    H, W = size
    uv, z = project(points_cam, K)
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        ok = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    flat = (v[ok] * W + u[ok]).astype(np.int64)
    order = np.argsort(-z[ok], kind="stable")  # far first, so the nearest is written last
    depth = np.full(H * W, np.inf)
    val = np.full(H * W, -1, dtype=np.int64)
    depth[flat[order]] = z[ok][order]
    val[flat[order]] = values[ok][order]
    return depth.reshape(H, W), val.reshape(H, W)


def _assert_same(a: Pair, b: Pair) -> None:
    for f in dataclasses.fields(Pair):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), f.name
        elif f.name != "meta":
            assert x == y, f.name
    assert a.meta["overlap"] == b.meta["overlap"]


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_gives_identical_pairs(pairs, kind):
    _assert_same(pairs[kind], make_pair(kind, seed=0))


@pytest.mark.parametrize("kind", KINDS)
def test_different_seeds_differ(pairs, kind):
    a, b = pairs[kind], make_pair(kind, seed=1)
    assert a.name != b.name
    assert not np.array_equal(a.image, b.image)
    assert not np.allclose(a.T_cam_pc, b.T_cam_pc)
    assert a.points.shape != b.points.shape or not np.array_equal(a.points, b.points)


@pytest.mark.parametrize("kind", KINDS)
def test_fields_shapes_and_dtypes(pairs, kind):
    p = pairs[kind]
    H, W = DEFAULT_IMAGE_SIZE[kind]
    assert p.image.shape == (H, W, 3) and p.image.dtype == np.uint8
    assert p.depth_gt.shape == (H, W) and p.depth_gt.dtype == np.float64
    assert p.image_ids.shape == (H, W) and p.image_ids.dtype == np.int32
    N = len(p.points)
    assert 1000 < N <= MAX_POINTS
    assert p.points.shape == (N, 3) and p.points.dtype == np.float64
    assert p.point_ids.shape == (N,) and p.point_ids.dtype == np.int32
    assert np.all(np.isfinite(p.points))
    for K in (p.K_image, p.K_depth):
        assert K.shape == (3, 3) and K.dtype == np.float64
        assert K[0, 2] == pytest.approx((W - 1) / 2) and K[1, 2] == pytest.approx((H - 1) / 2)
    assert p.depth_size == (H, W) and all(isinstance(x, int) for x in p.depth_size)
    assert is_rigid(p.T_cam_pc) and is_rigid(p.T_pc_sensor)
    assert p.name == f"synthetic-{kind}/seed0000"
    assert p.meta["kind"] == kind and p.meta["seed"] == 0
    assert p.meta["overlap_range"] == (0.3, 0.8)
    # Ids: known classes, 0 exactly where the image has no depth.
    assert set(np.unique(p.image_ids)) <= set(CLASS_NAMES)
    assert set(np.unique(p.point_ids)) <= set(CLASS_NAMES) - {0}
    assert np.array_equal(p.image_ids == 0, p.depth_gt == 0)


def test_indoor_default_intrinsics_and_camera_height(pairs):
    p = pairs["indoor"]
    assert p.K_image[0, 0] == pytest.approx(525.0) and p.K_image[1, 1] == pytest.approx(525.0)
    assert 1.2 <= invert(p.T_cam_pc)[2, 3] <= 1.8
    assert np.all(p.depth_gt > 0)  # a closed room: every pixel sees a surface


def test_outdoor_has_sky_and_a_street_camera(pairs):
    p = pairs["outdoor"]
    sky = p.depth_gt == 0
    assert 0.01 < sky.mean() < 0.6
    assert sky[: p.image.shape[0] // 2].mean() > sky[p.image.shape[0] // 2:].mean()
    assert invert(p.T_cam_pc)[2, 3] == pytest.approx(1.65)


@pytest.mark.parametrize("kind,max_median_m", [("indoor", 0.01), ("outdoor", 0.05)])
def test_true_depth_agrees_with_point_cloud(pairs, kind, max_median_m):
    """Pins the pose convention: ``T_cam_pc`` takes the cloud onto the image's depth.

    Outdoors the LiDAR hits the ground at grazing angles, where rounding a point to its
    pixel alone changes depth by centimetres, hence the looser bound.
    """
    p = pairs[kind]
    zbuf, ids = _zbuffer(transform(p.T_cam_pc, p.points), p.point_ids, p.K_image, p.image_size)
    both = np.isfinite(zbuf) & (p.depth_gt > 0)
    assert both.sum() > 2000
    err = np.abs(zbuf[both] - p.depth_gt[both])
    assert np.median(err) < max_median_m
    # Where depths agree the class ids agree as well.
    close = both & (np.abs(zbuf - p.depth_gt) < 0.05)
    assert np.mean(ids[close] == p.image_ids[close]) > 0.98


def test_wrong_pose_breaks_depth_agreement(pairs):
    """The agreement test above can fail: the inverse pose does not pass it."""
    p = pairs["indoor"]
    zbuf, _ = _zbuffer(transform(invert(p.T_cam_pc), p.points), p.point_ids, p.K_image,
                       p.image_size)
    both = np.isfinite(zbuf) & (p.depth_gt > 0)
    assert both.sum() == 0 or np.median(np.abs(zbuf[both] - p.depth_gt[both])) > 0.05


@pytest.mark.parametrize("kind", KINDS)
def test_overlap_within_default_range(pairs, kind):
    p = pairs[kind]
    ratio = overlap_ratio(p)
    assert 0.3 <= ratio <= 0.8
    assert ratio == p.meta["overlap"]


@pytest.mark.parametrize("kind,rng", [("indoor", (0.6, 0.75)), ("indoor", (0.1, 0.3)),
                                      ("outdoor", (0.2, 0.4))])
def test_overlap_within_requested_range(kind, rng):
    p = make_pair(kind, seed=2, overlap=rng, image_size=(120, 160 if kind == "indoor" else 416))
    assert rng[0] <= overlap_ratio(p) <= rng[1]


def test_overlap_ratio_drops_when_the_cloud_moves(pairs):
    p = pairs["indoor"]
    moved = dataclasses.replace(p, points=p.points + np.array([0.0, 0.0, 0.5]))
    assert overlap_ratio(moved) < 0.5 * overlap_ratio(p)
    empty = dataclasses.replace(p, points=np.zeros((0, 3)), point_ids=np.zeros(0, np.int32))
    assert overlap_ratio(empty) == 0.0


def test_outdoor_cloud_is_a_sparse_lidar_scan(pairs):
    p = pairs["outdoor"]
    H, W = p.depth_size
    zbuf, _ = _zbuffer(transform(invert(p.T_pc_sensor), p.points), p.point_ids, p.K_depth,
                       p.depth_size)
    assert np.isfinite(zbuf).mean() < 0.30
    # The points lie on the LiDAR's rings: elevations within its fan, seen from its centre.
    rel = transform(invert(p.meta["T_pc_lidar"]), p.points)
    el = np.degrees(np.arctan2(rel[:, 2], np.linalg.norm(rel[:, :2], axis=1)))
    assert el.max() < LIDAR_ELEVATIONS_DEG[0] + 0.01
    assert el.min() > LIDAR_ELEVATIONS_DEG[-1] - 0.01
    rings = np.sort(el)
    assert 1 + np.count_nonzero(np.diff(rings) > 0.1) <= 64
    # The depth camera sits at the LiDAR.
    assert np.allclose(p.T_pc_sensor[:3, 3], p.meta["T_pc_lidar"][:3, 3])


def test_indoor_cloud_is_dense_in_its_depth_view(pairs):
    p = pairs["indoor"]
    zbuf, _ = _zbuffer(transform(invert(p.T_pc_sensor), p.points), p.point_ids, p.K_depth,
                       p.depth_size)
    assert np.isfinite(zbuf).mean() > 0.15


@pytest.mark.parametrize("kind", KINDS)
def test_image_is_a_render_not_a_label_map(pairs, kind):
    p = pairs[kind]
    n_colours = len(np.unique(p.image.reshape(-1, 3), axis=0))
    n_classes = len(np.unique(p.image_ids))
    assert n_colours > 50 * n_classes
    # Within one class the colour varies (texture, shading).
    cls = np.bincount(p.image_ids.ravel()).argmax()
    assert p.image[p.image_ids == cls].std(axis=0).min() > 3.0


def test_image_size_argument():
    p = make_pair("outdoor", seed=0, image_size=TINY)
    assert p.image.shape == (*TINY, 3) and p.depth_size == TINY
    assert p.K_image[0, 2] == pytest.approx((TINY[1] - 1) / 2)


def test_make_pairs_derives_one_seed_per_pair():
    ps = make_pairs(2, "indoor", seed=0, image_size=TINY)
    assert [p.name for p in ps] == ["synthetic-indoor/seed0000", "synthetic-indoor/seed0001"]
    _assert_same(ps[1], make_pair("indoor", seed=1, image_size=TINY))
    other = make_pairs(1, "indoor", seed=1, image_size=TINY)[0]
    assert other.meta["seed"] not in (0, 1)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="kind"):
        make_pair("underwater")
    with pytest.raises(ValueError, match="overlap"):
        make_pair("indoor", overlap=(0.8, 0.3))
    with pytest.raises(RuntimeError, match=r"\[0\.97, 1\.0\]"):
        make_pair("outdoor", seed=0, overlap=(0.97, 1.0), image_size=(32, 104))
    with pytest.raises(ValueError, match="depth_gt"):
        overlap_ratio(dataclasses.replace(make_pair("indoor", image_size=TINY), depth_gt=None))


def test_class_names():
    assert CLASS_NAMES[0] == "none"
    assert len(set(CLASS_NAMES.values())) == len(CLASS_NAMES)
    assert {"floor", "wall", "road", "building", "car", "pole"} <= set(CLASS_NAMES.values())


def test_indoor_cloud_samples_the_depth_frame_truth(pairs):
    """The indoor cloud is a subsample of the depth camera's true frame: every point projects
    onto a pixel of ``depth_frame_gt`` at exactly its depth (the frame the evaluation lifts
    depth-side keypoints with); the LiDAR street has no such frame."""
    p = pairs["indoor"]
    gt = p.depth_frame_gt
    assert gt.shape == p.depth_size and (gt > 0).mean() > 0.95
    uv, z = project(transform(invert(p.T_pc_sensor), p.points), p.K_depth)
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    assert np.abs(uv - np.stack([u, v], 1)).max() < 1e-6
    np.testing.assert_allclose(gt[v, u], z, rtol=1e-9, atol=1e-9)
    assert len(p.points) < (gt > 0).sum()  # a sample: the frame has depth where the cloud has no point
    assert pairs["outdoor"].depth_frame_gt is None


def test_depth_frame_gt_of_the_wrong_size_is_named(pairs):
    p = pairs["indoor"]
    bad = dataclasses.replace(p, depth_frame_gt=p.depth_frame_gt[:-1])
    with pytest.raises(ValueError, match=r"depth_frame_gt must be \(H_d, W_d\)"):
        bad.validate()
    with pytest.raises(ValueError, match="depth_frame_gt has no valid pixel"):
        dataclasses.replace(p, depth_frame_gt=np.zeros_like(p.depth_frame_gt)).validate()
