"""The coarse-to-fine matcher of the RGBD-Scenes-v2 protocol (Table 5) on hand-made features."""
from __future__ import annotations

import numpy as np
import pytest

from freereg_lib.training.coarse_to_fine import coarse_to_fine, mutual_knn


def _grid(n_side: int, step: float) -> np.ndarray:
    """``(n_side**2, 2)`` positions on a square grid, row-major."""
    v, u = np.meshgrid(np.arange(n_side) * step, np.arange(n_side) * step, indexing="ij")
    return np.stack([u.ravel(), v.ravel()], 1)


def test_mutual_knn_k1_is_mutual_nearest_neighbours():
    a = np.array([[0.0], [1.0], [5.0]])
    b = np.array([[0.1], [4.0], [10.0]])
    i, j = mutual_knn(a, b, k=1)
    # a0 <-> b0 mutual; a2's nearest is b1 and b1's nearest is a2; b2's nearest is a2 (taken)
    assert i.tolist() == [0, 2] and j.tolist() == [0, 1]


def test_mutual_knn_k2_adds_second_neighbours_both_ways():
    a = np.array([[0.0], [1.0]])
    b = np.array([[0.0], [1.0]])
    i, j = mutual_knn(a, b, k=2)
    assert list(zip(i.tolist(), j.tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    i, j = mutual_knn(a, b, k=1)
    assert list(zip(i.tolist(), j.tolist())) == [(0, 0), (1, 1)]


def test_mutual_knn_needs_k_at_least_one_and_handles_empty_sides():
    with pytest.raises(ValueError, match="k must be >= 1"):
        mutual_knn(np.eye(2), np.eye(2), k=0)
    i, j = mutual_knn(np.zeros((0, 3)), np.eye(3), k=3)
    assert i.size == 0 and j.size == 0


def _identity_case(n_side=4):
    n = n_side * n_side
    uv = _grid(n_side, 10.0)  # pixels 10 apart
    xyz = np.c_[_grid(n_side, 0.1), np.full(n, 2.0)]  # points 0.1 m apart
    eye = np.eye(n)
    return eye, eye, uv, eye, eye, xyz


def test_one_hot_features_recover_the_identity():
    d_i, g_i, uv, d_p, g_p, xyz = _identity_case()
    ia, ib = coarse_to_fine(d_i, g_i, uv, d_p, g_p, xyz, k=1, radius_px=15.0, radius_m=0.15)
    assert ia.tolist() == list(range(16)) and ib.tolist() == list(range(16))


def test_one_hot_geometry_fills_the_patches_around_sparse_coarse_keypoints():
    # Coarse keypoints: every other row and column of a 4 x 4 grid (indices 0, 2, 8, 10); each
    # patch (just over one grid step) holds a keypoint's 4-neighbours, and the one-hot geometric
    # features pair each pixel with its own point. The diagonal keypoints 5, 7, 13, 15 lie
    # 14 px / 0.14 m from every coarse keypoint, outside all patches.
    d_i, g_i, uv, d_p, g_p, xyz = _identity_case()
    coarse = np.array([0, 2, 8, 10])
    ia, ib = coarse_to_fine(d_i, g_i, uv, d_p, g_p, xyz, coarse, coarse, k=1, radius_px=10.5, radius_m=0.105)
    assert ia.tolist() == ib.tolist()
    assert ia.tolist() == sorted(set(range(16)) - {5, 7, 13, 15})


def test_a_zero_radius_returns_the_coarse_matches_alone():
    rng = np.random.default_rng(0)
    n = 25
    uv, xyz = _grid(5, 8.0), np.c_[_grid(5, 0.05), np.ones(n)]
    d_i, d_p = rng.normal(size=(n, 8)), rng.normal(size=(n, 8))
    g_i, g_p = rng.normal(size=(n, 4)), rng.normal(size=(n, 4))
    coarse_i, coarse_p = mutual_knn(d_i, d_p, k=2)
    ia, ib = coarse_to_fine(d_i, g_i, uv, d_p, g_p, xyz, k=2, radius_px=0.0, radius_m=0.0)
    assert sorted(zip(ia.tolist(), ib.tolist())) == sorted(zip(coarse_i.tolist(), coarse_p.tolist()))


def test_the_fine_step_reads_the_geometric_features_not_the_diffusion_ones():
    # Diffusion: one-hot identity. Geometry: pixel p looks like point (p + 1) % 4 inside one
    # patch that holds everything; the fine matches follow the geometry.
    n = 4
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    xyz = np.c_[uv * 0.01, np.ones(n)]
    perm = (np.arange(n) + 1) % n
    ia, ib = coarse_to_fine(np.eye(n), np.eye(n)[perm], uv, np.eye(n), np.eye(n), xyz,
                            coarse_img=[0], coarse_pc=[0], k=1, radius_px=5.0, radius_m=1.0)
    assert ia.tolist() == [0, 1, 2, 3] and ib.tolist() == perm.tolist()


def test_mutual_fine_matching_drops_a_one_sided_nearest_neighbour():
    # Two pixels both nearest to point 0 on the geometry: only the closer one is mutual.
    uv = np.array([[0.0, 0.0], [1.0, 0.0]])
    xyz = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0]])
    g_i = np.array([[1.0, 0.0], [0.9, 0.1]])
    g_p = np.array([[1.0, 0.0], [-1.0, 0.0]])
    d = np.eye(2)
    args = (d, g_i, uv, d, g_p, xyz, [0], [0])
    ia, ib = coarse_to_fine(*args, k=1, radius_px=5.0, radius_m=1.0, mutual=True)
    assert list(zip(ia.tolist(), ib.tolist())) == [(0, 0)]
    ia, ib = coarse_to_fine(*args, k=1, radius_px=5.0, radius_m=1.0, mutual=False)
    assert list(zip(ia.tolist(), ib.tolist())) == [(0, 0), (1, 0)]


def test_a_negative_radius_is_refused():
    d_i, g_i, uv, d_p, g_p, xyz = _identity_case(2)
    with pytest.raises(ValueError, match="patch radii must be >= 0"):
        coarse_to_fine(d_i, g_i, uv, d_p, g_p, xyz, radius_px=-1.0)
