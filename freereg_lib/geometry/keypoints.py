"""Keypoint grids: one keypoint per cell of the layer-6 feature map, at cell centres."""
from __future__ import annotations

import numpy as np


def grid_keypoints(image_size: tuple[int, int], grid: tuple[int, int]) -> np.ndarray:
    """Uniform keypoints ``(gh * gw, 2) float64`` as ``(u, v)`` pixels, row-major.

    Follows the official rule ``v = i * int(H / gh) + int(int(H / gh) / 2)`` (likewise
    ``u``), so 640 x 480 with a 32 x 44 grid gives 1408 keypoints.
    """
    H, W = image_size
    gh, gw = grid
    if H < gh or W < gw:
        raise ValueError(f"image {H} x {W} is smaller than the keypoint grid {gh} x {gw}")
    sv, su = H // gh, W // gw
    v = np.arange(gh) * sv + sv // 2
    u = np.arange(gw) * su + su // 2
    vv, uu = np.meshgrid(v, u, indexing="ij")
    return np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
