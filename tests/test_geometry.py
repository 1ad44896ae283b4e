"""Cameras, projection, densification, keypoints and mutual nearest neighbours."""
import numpy as np
import pytest
from conftest import random_pose

from freereg_lib.features import matching
from freereg_lib.geometry import cameras, densify, keypoints, projection


def test_invert_and_compose(rng):
    T = random_pose(rng)
    assert np.allclose(T @ cameras.invert(T), np.eye(4), atol=1e-12)
    assert cameras.is_rigid(T)
    bad = T.copy()
    bad[:3, :3] *= 1.1
    assert not cameras.is_rigid(bad)


def test_project_backproject_round_trip(rng):
    K = cameras.intrinsics(500.0, 510.0, 320.0, 240.0)
    uv = rng.uniform([0, 0], [639, 479], size=(200, 2))
    z = rng.uniform(0.5, 8.0, size=200)
    pts = cameras.lift(uv, z, K)
    uv2, z2 = cameras.project(pts, K)
    assert np.allclose(uv2, uv, atol=1e-9)
    assert np.allclose(z2, z, atol=1e-12)


def test_project_known_point():
    K = cameras.intrinsics(100.0, 100.0, 50.0, 40.0)
    uv, z = cameras.project(np.array([[1.0, -0.5, 2.0], [0.0, 0.0, -1.0]]), K)
    assert np.allclose(uv[0], [100.0, 15.0])
    assert z[0] == 2.0
    assert np.all(np.isnan(uv[1]))


def test_backproject_depth_map_round_trip():
    K = cameras.intrinsics(50.0, 50.0, 15.5, 11.5)
    depth = np.full((24, 32), 2.0)
    depth[5, 7] = 0.0
    pts, uv = cameras.backproject(depth, K)
    assert len(pts) == 24 * 32 - 1
    rendered, index = projection.project_to_depth(pts, K, np.eye(4), (24, 32))
    assert np.allclose(rendered, depth)
    assert index[5, 7] == -1


def test_project_to_depth_zbuffer_nearest_wins():
    K = cameras.intrinsics(10.0, 10.0, 2.0, 2.0)
    pts = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.1, 0.0, 1.0]])
    depth, index = projection.project_to_depth(pts, K, np.eye(4), (5, 5))
    assert depth[2, 2] == 1.0 and index[2, 2] == 1
    assert depth[2, 3] == 1.0 and index[2, 3] == 3
    assert np.count_nonzero(depth) == 2


def test_project_to_depth_uses_sensor_pose(rng):
    K = cameras.intrinsics(40.0, 40.0, 19.5, 14.5)
    depth = rng.uniform(1.0, 3.0, size=(30, 40))
    pts_cam, _ = cameras.backproject(depth, K)
    T_world_cam = random_pose(rng)
    pts_world = cameras.transform(T_world_cam, pts_cam)
    rendered, _ = projection.project_to_depth(pts_world, K, cameras.invert(T_world_cam), (30, 40))
    assert np.allclose(rendered, depth)


def test_depth_range_drops_points():
    K = cameras.intrinsics(10.0, 10.0, 2.0, 2.0)
    pts = np.array([[0.0, 0.0, 0.005], [0.0, 0.0, 20.0]])
    depth, _ = projection.project_to_depth(pts, K, np.eye(4), (5, 5), 0.01, 10.0)
    assert not depth.any()


def _plane_depth(h=120, w=160):
    K = cameras.intrinsics(120.0, 120.0, w / 2 - 0.5, h / 2 - 0.5)
    # A tilted plane z = 2 + 0.2 x seen by the camera: depth is a smooth function of pixels.
    uv = cameras.pixel_grid(h, w).reshape(-1, 2)
    x_over_z = (uv[:, 0] - K[0, 2]) / K[0, 0]
    z = 2.0 / (1.0 - 0.2 * x_over_z)
    return z.reshape(h, w)


@pytest.mark.parametrize("method", ["fast", "multiscale"])
def test_densify_fills_punched_hole_within_1cm(method):
    truth = _plane_depth()
    sparse = truth.copy()
    sparse[50:60, 70:82] = 0.0
    filled = densify.densify(sparse, method)
    hole = filled[50:60, 70:82]
    assert np.all(hole > 0)
    assert np.max(np.abs(hole - truth[50:60, 70:82])) < 0.01


def test_densify_fills_sparse_scan():
    truth = _plane_depth()
    sparse = np.zeros_like(truth)
    sparse[::4, ::3] = truth[::4, ::3]
    filled = densify.fill_in_fast(sparse)
    inner = (slice(8, -8), slice(8, -8))
    assert np.all(filled[inner] > 0)
    assert np.median(np.abs(filled[inner] - truth[inner])) < 0.01


def test_densify_rejects_bad_method():
    with pytest.raises(ValueError, match="unknown densify method"):
        densify.densify(np.zeros((4, 4)), "magic")


def test_diamond_kernel_7():
    k = densify.DIAMOND_KERNEL_7
    assert k.shape == (7, 7) and k.sum() == 25 and k[0, 3] == 1 and k[0, 2] == 0


def test_grid_keypoints_official_rule():
    kp = keypoints.grid_keypoints((480, 640), (32, 44))
    assert kp.shape == (1408, 2)
    assert tuple(kp[0]) == (7.0, 7.0)
    assert tuple(kp[-1]) == (43 * 14 + 7.0, 31 * 15 + 7.0)


def test_bilinear_sample_exact():
    img = np.array([[0.0, 1.0], [2.0, 3.0]])
    out = cameras.bilinear_sample(img, np.array([[0.5, 0.5], [1.0, 0.0], [0.25, 1.0]]))
    assert np.allclose(out, [1.5, 1.0, 2.25])


def test_mutual_nn_hand_made():
    a = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    b = np.array([[0.0, 0.9], [0.1, 0.0], [4.0, 4.0], [4.5, 4.5]])
    ia, ib = matching.mutual_nn(a, b)
    # a0<->b1, a2<->b0, a3<->b3 are mutual; a1 -> b1 but b1 -> a0.
    assert ia.tolist() == [0, 2, 3] and ib.tolist() == [1, 0, 3]


def test_mutual_nn_chunked_equals_unchunked(rng):
    a = rng.normal(size=(700, 16))
    b = a[rng.permutation(700)] + rng.normal(scale=0.01, size=(700, 16))
    full = matching.mutual_nn(a, b, chunk=100000)
    chunked = matching.mutual_nn(a, b, chunk=64)
    assert np.array_equal(full[0], chunked[0]) and np.array_equal(full[1], chunked[1])
    assert len(full[0]) == 700


def test_mutual_nn_empty_and_shape_errors():
    ia, ib = matching.mutual_nn(np.zeros((0, 3)), np.ones((4, 3)))
    assert len(ia) == 0 and len(ib) == 0
    with pytest.raises(ValueError, match="same C"):
        matching.mutual_nn(np.zeros((2, 3)), np.zeros((2, 4)))
