"""Depth densification in the style of IP-Basic (Ku et al., CRV 2018), with OpenCV morphology.

The algorithm works on inverted depth so that closing and dilation favour near surfaces:
valid depth d becomes ``max_depth - d``, empty pixels stay 0, and the result is inverted
back. ``fill_in_fast`` is what FreeReg uses indoors, ``fill_in_multiscale`` on KITTI.
Unlike the official copy, remaining holes stay 0 (no measurement) instead of 255 m.
"""
from __future__ import annotations

import cv2
import numpy as np

FULL_KERNEL_3 = np.ones((3, 3), np.uint8)
FULL_KERNEL_5 = np.ones((5, 5), np.uint8)
FULL_KERNEL_7 = np.ones((7, 7), np.uint8)
FULL_KERNEL_31 = np.ones((31, 31), np.uint8)
CROSS_KERNEL_3 = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
CROSS_KERNEL_5 = np.array(
    [[0, 0, 1, 0, 0], [0, 0, 1, 0, 0], [1, 1, 1, 1, 1], [0, 0, 1, 0, 0], [0, 0, 1, 0, 0]], np.uint8
)
DIAMOND_KERNEL_5 = np.array(
    [[0, 0, 1, 0, 0], [0, 1, 1, 1, 0], [1, 1, 1, 1, 1], [0, 1, 1, 1, 0], [0, 0, 1, 0, 0]], np.uint8
)
CROSS_KERNEL_7 = np.zeros((7, 7), np.uint8)
CROSS_KERNEL_7[3, :] = 1
CROSS_KERNEL_7[:, 3] = 1
DIAMOND_KERNEL_7 = (np.abs(np.arange(7)[:, None] - 3) + np.abs(np.arange(7)[None, :] - 3) <= 3).astype(
    np.uint8
)


def _invert(depth: np.ndarray, max_depth: float) -> np.ndarray:
    out = np.zeros_like(depth, dtype=np.float32)
    valid = depth > 0
    out[valid] = max_depth - depth[valid]
    return out


def _check(depth: np.ndarray) -> np.ndarray:
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth must be a (H, W) map, got shape {d.shape}")
    return np.where(np.isfinite(d), d, 0.0).astype(np.float32)


def fill_in_fast(
    depth: np.ndarray,
    max_depth: float = 100.0,
    custom_kernel: np.ndarray = DIAMOND_KERNEL_7,
    extrapolate: bool = False,
    blur_type: str = "bilateral",
) -> np.ndarray:
    """Fast densification of a sparse ``(H, W)`` depth map in metres; returns ``(H, W) float64``.

    Dilate with ``custom_kernel``, close small holes, fill the rest with a 7 x 7 dilation,
    optionally extend the top rows, then blur. Pixels that stay empty are 0.
    """
    d = _invert(_check(depth), max_depth)
    d = cv2.dilate(d, custom_kernel)
    d = cv2.morphologyEx(d, cv2.MORPH_CLOSE, FULL_KERNEL_5)
    empty = d < 0.1
    dilated = cv2.dilate(d, FULL_KERNEL_7)
    d[empty] = dilated[empty]
    if extrapolate:
        top_rows = np.argmax(d > 0.1, axis=0)
        for col, row in enumerate(top_rows):
            d[:row, col] = d[row, col]
        empty = d < 0.1
        dilated = cv2.dilate(d, FULL_KERNEL_31)
        d[empty] = dilated[empty]
    d = cv2.medianBlur(d, 5)
    if blur_type == "bilateral":
        d = cv2.bilateralFilter(d, 5, 1.5, 2.0)
    elif blur_type == "gaussian":
        valid = d > 0.1
        blurred = cv2.GaussianBlur(d, (5, 5), 0)
        d[valid] = blurred[valid]
    out = np.zeros_like(d, dtype=np.float64)
    valid = d > 0.1
    out[valid] = max_depth - d[valid]
    return out


def fill_in_multiscale(
    depth: np.ndarray,
    max_depth: float = 100.0,
    dilation_kernel_far: np.ndarray = CROSS_KERNEL_3,
    dilation_kernel_med: np.ndarray = CROSS_KERNEL_5,
    dilation_kernel_near: np.ndarray = CROSS_KERNEL_7,
    extrapolate: bool = False,
    blur_type: str = "bilateral",
) -> np.ndarray:
    """IP-Basic's multi-scale densification (default settings); returns ``(H, W) float64``.

    Near (< 15 m), medium (15-30 m) and far (> 30 m) points are dilated with their own
    kernels so near surfaces win, then holes are closed and filled at growing scales,
    the empty sky region above the top measurement is left empty, and the map is blurred
    where it was not measured.
    """
    d0 = _check(depth)
    d = d0.copy()
    valid = d > 0.1
    d[valid] = max_depth - d[valid]

    near = valid & (d0 <= 15.0)
    med = valid & (d0 > 15.0) & (d0 <= 30.0)
    far = valid & (d0 > 30.0)
    dilated_far = cv2.dilate(np.where(far, d, 0).astype(np.float32), dilation_kernel_far)
    dilated_med = cv2.dilate(np.where(med, d, 0).astype(np.float32), dilation_kernel_med)
    dilated_near = cv2.dilate(np.where(near, d, 0).astype(np.float32), dilation_kernel_near)
    # Near dilation overrides medium overrides far: nearer surfaces occlude.
    d[dilated_far > 0.1] = dilated_far[dilated_far > 0.1]
    d[dilated_med > 0.1] = dilated_med[dilated_med > 0.1]
    d[dilated_near > 0.1] = dilated_near[dilated_near > 0.1]

    d = cv2.morphologyEx(d, cv2.MORPH_CLOSE, FULL_KERNEL_5)
    valid = d > 0.1
    blurred = cv2.medianBlur(d, 5)
    d[valid] = blurred[valid]

    # Pixels above the top measurement of each column are sky: keep them empty.
    top_mask = np.ones(d.shape, dtype=bool)
    if extrapolate:
        top_rows = np.argmax(d > 0.1, axis=0)
        for col, row in enumerate(top_rows):
            d[:row, col] = d[row, col]
    else:
        top_rows = np.argmax(d > 0.1, axis=0)
        has_any = (d > 0.1).any(axis=0)
        rows = np.arange(d.shape[0])[:, None]
        top_mask = (rows >= top_rows[None, :]) & has_any[None, :]

    empty = (d < 0.1) & top_mask
    dilated = cv2.dilate(d, FULL_KERNEL_7)
    d[empty] = dilated[empty]
    for _ in range(6):
        empty = (d < 0.1) & top_mask
        dilated = cv2.dilate(d, FULL_KERNEL_5)
        d[empty] = dilated[empty]
    empty = (d < 0.1) & top_mask
    dilated = cv2.dilate(d, FULL_KERNEL_31)
    d[empty] = dilated[empty]
    if extrapolate:
        empty = d < 0.1
        dilated = cv2.dilate(d, FULL_KERNEL_31)
        d[empty] = dilated[empty]

    measured = d0 > 0.1
    if blur_type == "gaussian":
        blurred = cv2.GaussianBlur(d, (5, 5), 0)
    else:
        blurred = cv2.bilateralFilter(d, 5, 0.5, 2.0)
    fill = (d > 0.1) & ~measured
    d[fill] = blurred[fill]

    out = np.zeros(d.shape, dtype=np.float64)
    valid = d > 0.1
    out[valid] = max_depth - d[valid]
    return out


def densify(depth: np.ndarray, method: str = "fast", max_depth: float = 100.0) -> np.ndarray:
    """Dispatch on ``method``: ``"fast"``, ``"multiscale"`` or ``"none"`` (a float64 copy)."""
    if method == "fast":
        return fill_in_fast(depth, max_depth=max_depth)
    if method == "multiscale":
        return fill_in_multiscale(depth, max_depth=max_depth)
    if method == "none":
        return np.asarray(depth, dtype=np.float64).copy()
    raise ValueError(f"unknown densify method {method!r}; expected 'fast', 'multiscale' or 'none'")
