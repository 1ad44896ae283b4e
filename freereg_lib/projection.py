"""Point cloud -> depth map on a sensor pose, with z-buffering (the nearest point wins)."""
from __future__ import annotations

import numpy as np

from . import cameras


def project_to_depth(
    points: np.ndarray,
    K: np.ndarray,
    T_sensor_pc: np.ndarray,
    size: tuple[int, int],
    depth_min: float = 0.0,
    depth_max: float = np.inf,
) -> tuple[np.ndarray, np.ndarray]:
    """Render ``points (N, 3)`` of frame ``pc`` into a depth map seen from a sensor.

    Each point lands on its nearest pixel; where several land on one pixel the nearest
    (smallest z) wins. Points outside ``(depth_min, depth_max)`` are dropped.

    Returns ``depth (H, W) float64`` (0 = no point) and ``index (H, W) int64``, the row of
    ``points`` that won each pixel (-1 = none).
    """
    H, W = size
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    uv, z = cameras.project(cameras.transform(T_sensor_pc, pts), K)
    u = np.rint(uv[:, 0])
    v = np.rint(uv[:, 1])
    keep = (z > max(depth_min, 0.0)) & (z < depth_max) & np.isfinite(u) & np.isfinite(v)
    keep &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
    rows = np.nonzero(keep)[0]
    flat = v[rows].astype(np.int64) * W + u[rows].astype(np.int64)
    # Sort by pixel, then depth: the first entry of each pixel run is its nearest point.
    order = np.lexsort((z[rows], flat))
    flat, rows = flat[order], rows[order]
    first = np.ones(len(flat), dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    depth = np.zeros(H * W, dtype=np.float64)
    index = np.full(H * W, -1, dtype=np.int64)
    depth[flat[first]] = z[rows[first]]
    index[flat[first]] = rows[first]
    return depth.reshape(H, W), index.reshape(H, W)


def edge_filter(depth: np.ndarray, max_range: float) -> np.ndarray:
    """Zero pixels whose 3 x 3 neighbourhood spans more than ``max_range`` metres of depth.

    Projected clouds leak background points through foreground edges; the official code
    removes them this way. Empty neighbours are ignored. Returns a filtered copy.
    """
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    valid = d > 0
    kernel = np.ones((3, 3), np.uint8)
    dmax = cv2.dilate(np.where(valid, d, 0).astype(np.float32), kernel)
    dmin = -cv2.dilate(np.where(valid, -d, -np.inf).astype(np.float32), kernel)
    out = np.asarray(depth, dtype=np.float64).copy()
    out[valid & ((dmax - dmin) > max_range)] = 0.0
    return out
