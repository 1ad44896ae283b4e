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
    if not (H > 0 and W > 0):
        raise ValueError(f"size must be (H, W) with both sides > 0, got {size!r}")
    pts = np.asarray(points, dtype=np.float64)
    if pts.size and pts.shape[-1] != 3:
        raise ValueError(f"points must be (N, 3) x, y, z, got shape {pts.shape}")
    pts = pts.reshape(-1, 3)
    uv, z = cameras.project(cameras.transform(T_sensor_pc, pts), K)
    u = np.rint(uv[:, 0])
    v = np.rint(uv[:, 1])
    keep = (z > max(depth_min, 0.0)) & (z < depth_max) & np.isfinite(u) & np.isfinite(v)
    keep &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
    rows = np.nonzero(keep)[0]
    flat = v[rows].astype(np.int64) * W + u[rows].astype(np.int64)
    # Z-buffer without sorting: each pixel's minimum depth by an unbuffered minimum, then
    # among the points at that exact depth the lowest row wins (what a stable sort by
    # pixel, then depth, picked). Bitwise the same result as the sort, ~5x faster.
    zr = z[rows]
    zbuf = np.full(H * W, np.inf)
    np.minimum.at(zbuf, flat, zr)
    win = zr == zbuf[flat]
    index = np.full(H * W, len(pts), dtype=np.int64)
    np.minimum.at(index, flat[win], rows[win])
    hit = index < len(pts)
    index[~hit] = -1
    depth = np.where(hit, zbuf, 0.0)
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
    # Window max and min over valid pixels (empty ones are 0 for the max, inf for the min).
    dmax = cv2.dilate(np.where(valid, d, np.float32(0.0)), kernel)
    dmin = cv2.erode(np.where(valid, d, np.float32(np.inf)), kernel)
    drop = valid & ((dmax - dmin) > max_range)
    return np.where(drop, 0.0, np.asarray(depth, dtype=np.float64))
