"""File readers shared by the loaders: RGB images, 16-bit depth PNGs, pose files.

Every reader raises ``FileNotFoundError`` or ``ValueError`` naming the file and what was
expected, so a broken dataset tree is diagnosed at the first bad file.
"""
from __future__ import annotations

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
    return raw.astype(np.float64) / depth_scale


def read_pose_txt(path: str | Path) -> np.ndarray:
    """A 4 x 4 pose written as 4 rows of 4 numbers."""
    path = _exists(path)
    T = np.loadtxt(path, dtype=np.float64)
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
        frame = int(lines[k][0])
        poses[frame] = np.array(lines[k + 1 : k + 5], dtype=np.float64)
    return poses
