"""Coarse-to-fine pixel-to-point matching, the appendix's protocol of Table 5 (RGBD-Scenes-v2).

Coarse: mutual k-nearest neighbours on the diffusion descriptors between coarse keypoints
(a pair is kept when each side is among the other's ``k`` nearest; ``k = 3`` as 2D3D-MATR's
coarse matcher). Fine: around each coarse match an image patch (keypoints within
``radius_px`` pixels of its pixel) and a cloud patch (within ``radius_m`` metres of its
point) are matched on the geometric descriptors by nearest neighbours, mutual within the
patch as 2D3D-MATR's fine matcher. Patches overlap, so a pair found twice is kept once.

It reads FreeReg's keypoints and descriptors (:class:`freereg_lib.pipeline.PairFeatures`) and
sits with the tools rather than in :mod:`freereg_lib.features`: only the appendix's protocol uses
it, and the method's packages are kept under a fixed size (the layer test checks a cap).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(len(a), len(b))`` squared Euclidean distances."""
    return (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T


def mutual_knn(fa: np.ndarray, fb: np.ndarray, k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` with ``b_j`` among the ``k`` nearest of ``a_i`` and ``a_i`` among the
    ``k`` nearest of ``b_j``; ``fa (N, C)``, ``fb (M, C)``; two ``(K,) int64``, sorted by ``i``."""
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    if len(fa) == 0 or len(fb) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d = _sqdist(np.asarray(fa, np.float64), np.asarray(fb, np.float64))
    # stable argsort: ties go to the lower index, as mutual_nn's argmin
    in_a = np.zeros(d.shape, bool)
    np.put_along_axis(in_a, np.argsort(d, 1, kind="stable")[:, :k], True, 1)
    in_b = np.zeros(d.shape, bool)
    np.put_along_axis(in_b, np.argsort(d, 0, kind="stable")[:k, :], True, 0)
    i, j = np.nonzero(in_a & in_b)
    return i.astype(np.int64), j.astype(np.int64)


def coarse_to_fine(diff_img: np.ndarray, geo_img: np.ndarray, uv_img: np.ndarray,
                   diff_pc: np.ndarray, geo_pc: np.ndarray, xyz_pc: np.ndarray,
                   coarse_img: np.ndarray | None = None, coarse_pc: np.ndarray | None = None,
                   k: int = 3, radius_px: float = 30.0, radius_m: float = 0.15,
                   mutual: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-to-point matches ``(idx_img (K,) int64, idx_pc (K,) int64)``, sorted, unique.

    Image side: ``diff_img (N, Cd)``, ``geo_img (N, Cg)`` at pixels ``uv_img (N, 2)``; cloud
    side: ``diff_pc (M, Cd)``, ``geo_pc (M, Cg)`` at points ``xyz_pc (M, 3)`` metres.
    ``coarse_img`` / ``coarse_pc``: indices of the coarse keypoints (default: all). A patch
    radius of 0 keeps the coarse matches alone (a keypoint's patch is itself).
    """
    if radius_px < 0 or radius_m < 0:
        raise ValueError(f"patch radii must be >= 0, got radius_px={radius_px}, radius_m={radius_m}")
    ci = np.arange(len(uv_img)) if coarse_img is None else np.asarray(coarse_img, np.int64)
    cp = np.arange(len(xyz_pc)) if coarse_pc is None else np.asarray(coarse_pc, np.int64)
    a, b = mutual_knn(np.asarray(diff_img)[ci], np.asarray(diff_pc)[cp], k)
    tree_img, tree_pc = cKDTree(np.asarray(uv_img, np.float64)), cKDTree(np.asarray(xyz_pc, np.float64))
    g_img, g_pc = np.asarray(geo_img, np.float64), np.asarray(geo_pc, np.float64)
    out = set()
    for i, j in zip(ci[a], cp[b]):
        p = np.asarray(sorted(tree_img.query_ball_point(uv_img[i], radius_px)), np.int64)
        q = np.asarray(sorted(tree_pc.query_ball_point(xyz_pc[j], radius_m)), np.int64)
        d = _sqdist(g_img[p], g_pc[q])
        nn = d.argmin(1)
        keep = d.argmin(0)[nn] == np.arange(len(p)) if mutual else np.ones(len(p), bool)
        out.update(zip(p[keep].tolist(), q[nn[keep]].tolist()))
    pairs = np.asarray(sorted(out), np.int64).reshape(-1, 2)
    return pairs[:, 0], pairs[:, 1]
