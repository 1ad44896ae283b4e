"""Point cloud -> depth map on a sensor pose, with z-buffering (the nearest point wins)."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from freereg_lib.geometry import cameras

# The official proj_pc2dpt keeps points with z > 0.05 m (no far limit).
OFFICIAL_MIN_Z = 0.05


def project_to_depth(
    points: np.ndarray,
    K: np.ndarray,
    T_sensor_pc: np.ndarray,
    size: tuple[int, int],
    depth_min: float = 0.0,
    depth_max: float = np.inf,
    pixel: str = "round",
    snap: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Render ``points (N, 3)`` of frame ``pc`` into a depth map seen from a sensor.

    ``pixel="round"``: each point lands on its nearest pixel (``rint(K X / z)``); points
    outside ``(depth_min, depth_max)`` are dropped. ``pixel="official"``: the official
    ``proj_pc2dpt`` (demo and own data): pixel = int32 truncation of ``(K X)[:2] / (z + 1e-5)``,
    kept when ``0 <= u < W``, ``0 <= v < H`` and ``z > 0.05`` m, no far limit
    (``depth_min`` / ``depth_max`` are not used). ``snap > 0``: the sensor-frame coordinates are
    rounded to that grid first (``cfg.cloud_snap_m``). Measured on
    ICL frame 30 (20k points, ``parity`` fixture ``proj_pc2dpt/icl_identity``): rounding
    fills other pixels than the official code. Where several points land on one pixel the
    nearest (smallest z) wins.

    Returns ``depth (H, W) float64`` (0 = no point) and ``index (H, W) int64``, the row of
    ``points`` that won each pixel (-1 = none).
    """
    H, W = size
    if not (H > 0 and W > 0):
        raise ValueError(f"size must be (H, W) with both sides > 0, got {size!r}")
    pts = np.asarray(points, dtype=np.float64)
    if pts.size and pts.shape[-1] != 3:
        raise ValueError(f"points must be (N, 3) x, y, z, got shape {pts.shape}")
    cam = cameras.transform(T_sensor_pc, pts.reshape(-1, 3))
    cam = np.round(cam / snap) * snap if snap > 0 else cam
    if pixel == "official":
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = cam @ np.asarray(K, dtype=np.float64).T
            uv = uvw[:, :2] / (uvw[:, 2:3] + 1e-5)
        ok = (z > OFFICIAL_MIN_Z) & np.isfinite(uv).all(axis=1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        u = np.where(ok, np.trunc(np.where(ok, uv[:, 0], 0.0)), -1.0)
        v = np.where(ok, np.trunc(np.where(ok, uv[:, 1], 0.0)), -1.0)
        keep = ok
    elif pixel == "round":
        uv, z = cameras.project(cam, K)
        u = np.rint(uv[:, 0])
        v = np.rint(uv[:, 1])
        keep = (z > max(depth_min, 0.0)) & (z < depth_max) & np.isfinite(u) & np.isfinite(v)
    else:
        raise ValueError(f"pixel must be 'official' or 'round', got {pixel!r}")
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
    index = np.full(H * W, len(cam), dtype=np.int64)
    np.minimum.at(index, flat[win], rows[win])
    hit = index < len(cam)
    index[~hit] = -1
    depth = np.where(hit, zbuf, 0.0)
    return depth.reshape(H, W), index.reshape(H, W)


def edge_mask(depth: np.ndarray, max_range: float, half_window: int = 3, depth_unit: float = 1.0) -> np.ndarray:
    """``(H, W) bool``: the pixels the official 6 x 6 edge filter keeps.

    Pixel ``(i, j)`` is kept when ``i >= half_window``, ``j >= half_window`` and
    ``max - min`` of ``depth / depth_unit`` over rows ``[i - w, i + w)`` and columns
    ``[j - w, j + w)`` (clipped at the far borders; holes count as 0) is below
    ``max_range``, exactly as the loop in the official ``proj_depth(filter_edge=True)``;
    the arithmetic stays in the map's own float type, as there.
    """

    d = np.asarray(depth)
    if not np.issubdtype(d.dtype, np.floating):
        d = d.astype(np.float64)
    if depth_unit != 1:
        d = d / depth_unit
    size = 2 * int(half_window)
    # An even window of ``size`` covers offsets -w .. w-1; 'nearest' padding repeats a
    # pixel that is already inside the window, so clipped borders read as the loop's slices.
    dmax = ndimage.maximum_filter(d, size=size, mode="nearest")
    dmin = ndimage.minimum_filter(d, size=size, mode="nearest")
    keep = (dmax - dmin) < max_range
    keep[:half_window, :] = False
    keep[:, :half_window] = False
    return keep


def edge_filter(depth: np.ndarray, max_range: float, half_window: int = 3) -> np.ndarray:
    """The official edge filter: pixels near a depth discontinuity are zeroed.

    Pixel ``(i, j)`` of ``depth (H, W)`` in metres is kept where :func:`edge_mask` keeps
    it (a 6 x 6 window, not centred). FreeReg applies it to the monocular depth map before
    its back-projection for geometric features (0.2 m indoors, 1.0 m on KITTI), where
    ZoeDepth smears depth across object boundaries. Returns a filtered float64 copy.
    """
    d = np.asarray(depth, dtype=np.float64)
    return np.where(edge_mask(depth, max_range, half_window), d, 0.0)


def lift_depth_map(depth: np.ndarray, K: np.ndarray, extrinsic: np.ndarray | None = None,
                   depth_unit: float = 1.0, edge_m: float = 0.0, half_window: int = 3,
                   far: float | None = None, near: float | None = None):
    """The official ``proj_depth``: pixels of ``depth (H, W)`` lifted to points.

    Kept pixels (row-major order): with ``edge_m > 0`` those :func:`edge_mask` keeps, then
    raw depth ``< far * depth_unit`` and ``> near * depth_unit`` (strict; None: no test; a
    hole is dropped only by the near test, as there). Returns ``uv (N, 2) float64`` (u = column),
    ``d (N,)`` the raw depths and ``points (N, 3) = extrinsic @ lift(uv, d / depth_unit)``.
    """
    d = np.asarray(depth)
    if d.ndim > 2:
        d = d[:, :, 0]
    keep = np.ones(d.shape, bool)
    if edge_m > 0:
        keep &= edge_mask(d, edge_m, half_window, depth_unit)
    if far is not None:
        keep &= d < far * depth_unit
    if near is not None:
        keep &= d > near * depth_unit
    v, u = np.nonzero(keep)
    uv = np.stack([u, v], axis=1).astype(np.float64)
    z = d[keep].astype(np.float64)
    pts = cameras.lift(uv, z / depth_unit, K)
    if extrinsic is not None:
        pts = cameras.transform(np.asarray(extrinsic, dtype=np.float64), pts)
    return uv, z, pts


def feature_cloud(depth: np.ndarray, K: np.ndarray, cfg, monocular: bool) -> tuple[np.ndarray, np.ndarray]:
    """The cloud the official code hands FCGF (``spconv_feature_extract``) for a depth map in metres.

    :func:`lift_depth_map` with the edge filter ``cfg.edge_filter_m`` on a monocular map
    only (on the map as it is, before any range test), far ``cfg.cloud_far_m`` and near
    ``cfg.cloud_near_m`` (the official ``cfg.proj``: 10 / 0.01 m indoors, 80 / 0.5 m on
    KITTI), then the evaluation mask ``cfg.depth_min < d < cfg.depth_max``. So ScanNet's
    depth-side cloud ends at 10 m although its masks reach 15 m. Returns ``points (N, 3)``
    in the camera frame and their pixels ``uv (N, 2)``.
    """
    edge = float(cfg.edge_filter_m) if monocular else 0.0
    d = np.asarray(depth)
    if not np.issubdtype(d.dtype, np.floating):
        d = d.astype(np.float64)
    d = np.where(np.isfinite(d), d, 0.0).astype(d.dtype, copy=False)
    uv, z, pts = lift_depth_map(d, K, None, 1.0, edge, 3, cfg.cloud_far_m, cfg.cloud_near_m)
    keep = (z < cfg.depth_max) & (z > cfg.depth_min)
    return pts[keep], uv[keep]


def clip_to_range(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """A float64 copy of ``depth`` with values outside ``(lo, hi)`` (strict) set to 0: the
    official keypoint mask (``cfg.match.dpt_mask``) and evaluation mask."""
    d = np.asarray(depth, dtype=np.float64).copy()
    d[~((d > lo) & (d < hi))] = 0.0
    return d
