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


def edge_filter(depth: np.ndarray, max_range: float, half_window: int = 3) -> np.ndarray:
    """The official edge filter: pixels near a depth discontinuity are zeroed.

    Pixel ``(i, j)`` of ``depth (H, W)`` in metres is kept when ``i >= half_window``,
    ``j >= half_window`` and the depth range over rows ``[i - w, i + w)`` and columns
    ``[j - w, j + w)`` (``w = half_window``; a 6 x 6 window, not centred) is below
    ``max_range``, exactly as the official ``proj_depth(filter_edge=True)`` loop; holes (0)
    count as depth 0 there. FreeReg applies it to the monocular depth map before its
    back-projection for geometric features (0.2 m indoors, 1.0 m on KITTI), where
    ZoeDepth smears depth across object boundaries. Returns a filtered float64 copy.
    """
    from scipy import ndimage

    d = np.asarray(depth, dtype=np.float64)
    size = 2 * int(half_window)
    # An even window of ``size`` covers offsets -w .. w-1; 'nearest' padding repeats a
    # pixel that is already inside the window, so clipped borders read as the loop's slices.
    dmax = ndimage.maximum_filter(d, size=size, mode="nearest")
    dmin = ndimage.minimum_filter(d, size=size, mode="nearest")
    keep = (dmax - dmin) < max_range
    keep[:half_window, :] = False
    keep[:, :half_window] = False
    return np.where(keep, d, 0.0)
