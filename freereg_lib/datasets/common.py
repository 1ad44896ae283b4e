"""File readers shared by the loaders: RGB images, 16-bit depth PNGs, pose files, point clouds.

Every reader raises ``FileNotFoundError`` or ``ValueError`` naming the file and what was
expected, so a broken dataset tree is diagnosed at the first bad file.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np


def _exists(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"missing file: {path}")
    return path


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as ``(H, W, 3) uint8`` RGB."""
    path = _exists(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"cannot decode image {path} (expected a PNG or JPEG RGB image)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: str | Path, depth_scale: float = 1000.0) -> np.ndarray:
    """A 16-bit depth PNG as ``(H, W) float64`` metres (raw value / ``depth_scale``; 0 = none)."""
    path = _exists(path)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2:
        raise ValueError(f"cannot read {path} as a single-channel 16-bit depth PNG")
    if raw.dtype == np.uint8:
        raise ValueError(f"{path} is an 8-bit image, not a 16-bit depth PNG (depth in units of 1/{depth_scale:g} m); "
                         "an 8-bit picture of depth is a visualisation and has lost the metric values")
    return raw.astype(np.float64) / depth_scale


def read_pose_txt(path: str | Path) -> np.ndarray:
    """A 4 x 4 pose written as 4 rows of 4 numbers."""
    path = _exists(path)
    try:
        T = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"cannot read {path} as a 4 x 4 pose of numbers: {exc}") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{path} does not hold a finite 4 x 4 pose (got shape {T.shape})")
    return T


def read_redwood_log(path: str | Path) -> dict[int, np.ndarray]:
    """A Redwood ``.log`` trajectory: per entry a header ``id id id+1`` and a 4 x 4 pose.

    Returns ``{frame_id: T_world_cam}``.
    """
    path = _exists(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) % 5:
        raise ValueError(f"{path}: {len(lines)} non-empty lines, a .log file has 5 per pose")
    poses = {}
    for k in range(0, len(lines), 5):
        try:
            frame = int(lines[k][0])
            poses[frame] = np.array(lines[k + 1 : k + 5], dtype=np.float64)
        except ValueError as exc:
            raise ValueError(f"{path}, entry at non-empty line {k + 1}: expected a header 'id id id+1' and "
                             f"4 rows of 4 numbers ({exc})") from None
        if poses[frame].shape != (4, 4) or not np.all(np.isfinite(poses[frame])):
            raise ValueError(f"{path}, frame {frame}: expected 4 rows of 4 finite numbers")
    return poses


def read_points(path: str | Path, drop_nonfinite: bool = True) -> np.ndarray:
    """A point cloud file as ``(N, 3) float64``: ``.ply`` (ASCII or binary), ``.npy`` (an
    ``(N, 3)`` array, or ``(N, k >= 3)`` whose first three columns are x, y, z) or a text
    file ``.xyz`` / ``.txt`` / ``.pts`` (one point a line, x y z first).

    Points with NaN or inf are dropped with a warning naming the count (with
    ``drop_nonfinite=False`` they are kept, and :meth:`~freereg_lib.pair.Pair.validate`
    refuses them). A missing file raises ``FileNotFoundError``; an unreadable or empty one
    ``ValueError``, each naming the file.
    """
    path = _exists(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        from .demo import read_ply_points

        pts = read_ply_points(path)
    elif suffix in (".npy", ".xyz", ".txt", ".pts"):
        try:
            pts = np.load(path, allow_pickle=False) if suffix == ".npy" else np.loadtxt(path, ndmin=2)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"cannot read the points of {path}: {exc}") from None
        if pts.ndim != 2 or pts.shape[1] < 3 or not np.issubdtype(pts.dtype, np.number):
            raise ValueError(f"{path} holds an array of shape {pts.shape} {pts.dtype}; expected (N, 3) numbers "
                             "(or (N, k >= 3) with x, y, z first)")
        pts = np.asarray(pts[:, :3], dtype=np.float64)
    else:
        raise ValueError(f"{path}: unknown point cloud format {suffix!r}; expected .ply, .npy, .xyz, .txt or .pts")
    if len(pts) == 0:
        raise ValueError(f"{path} holds no point (an empty point cloud)")
    keep = np.isfinite(pts).all(axis=1)
    if drop_nonfinite and not keep.all():
        if not keep.any():
            raise ValueError(f"{path}: all {len(pts)} points are NaN or inf")
        warnings.warn(f"{path}: dropped {int((~keep).sum())} of {len(pts)} points that are NaN or inf",
                      RuntimeWarning, stacklevel=2)
        pts = pts[keep]
    return pts
