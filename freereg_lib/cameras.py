"""Cameras and SE(3): intrinsics, rigid transforms, projection and back-projection.

Conventions (the whole library follows them):

* A pose ``T_a_b`` is a ``(4, 4) float64`` array that maps points from frame ``b`` into
  frame ``a``: ``x_a = T_a_b @ x_b``. So ``T_a_c = T_a_b @ T_b_c`` and
  ``T_b_a = invert(T_a_b)``.
* Camera frames are OpenCV's: x right, y down, z forward; pixel ``(u, v)`` = (column, row),
  pixel centres at integer coordinates.
* Depth is the camera z coordinate in metres; ``0`` means "no measurement".

This module owns every projection and back-projection in the library.
"""
from __future__ import annotations

import numpy as np


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The pinhole matrix ``K``, ``(3, 3) float64``."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` for an image resized by ``(sx, sy)`` (pixel centres stay at integer coordinates)."""
    K2 = np.asarray(K, dtype=np.float64).copy()
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K2[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K2[1, 2] + 0.5) * sy - 0.5
    return K2


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(4, 4)`` pose from rotation ``(3, 3)`` and translation ``(3,)``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid ``(4, 4)`` pose, computed as ``[R^T, -R^T t]``."""
    R, t = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ t)


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T (4, 4)`` to ``points (N, 3)``; returns ``(N, 3) float64``."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def is_rigid(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True when ``T`` is a proper rigid transform (orthonormal R, det +1, last row 0 0 0 1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (
        np.allclose(R.T @ R, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
        and np.allclose(T[3], [0, 0, 0, 1], atol=atol)
    )


def check_pose(T: np.ndarray, name: str = "T", atol: float = 1e-4) -> np.ndarray:
    """``T`` as ``(4, 4) float64`` when it is a rigid transform (:func:`is_rigid` at ``atol``).

    Otherwise a ``ValueError`` names ``name``, what was expected and what is wrong (a
    reflection, a scale, a transposed matrix, a bad last row).
    """
    arr = np.asarray(T)
    if arr.shape != (4, 4) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name} must be a (4, 4) pose [[R, t], [0, 0, 0, 1]], got shape {arr.shape} {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite entries (NaN or inf): {arr.tolist()}")
    if is_rigid(arr, atol):
        return arr
    R = arr[:3, :3]
    det = float(np.linalg.det(R))
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    if not np.allclose(arr[3, :3], 0, atol=atol) and is_rigid(arr.T, atol):
        hint = "; it looks transposed: pass T.T"
    elif not np.allclose(arr[3], [0, 0, 0, 1], atol=atol):
        hint = f"; its last row is {arr[3].tolist()}, expected [0, 0, 0, 1]"
    elif det < 0:
        hint = "; det(R) < 0 is a reflection (an axis flipped, or a left-handed frame)"
    elif np.allclose(R.T @ R, np.eye(3) * abs(det) ** (2 / 3), rtol=1e-3, atol=atol):
        hint = f"; R carries a scale of {abs(det) ** (1 / 3):.4g} (a similarity): divide it out"
    else:
        hint = ""
    raise ValueError(
        f"{name} is not a rigid transform: expected [[R, t], [0, 0, 0, 1]] with R orthonormal and "
        f"det(R) = +1, got max |R^T R - I| = {ortho:.3g}, det(R) = {det:.6g}{hint}"
    )


def check_intrinsics(K: np.ndarray, size: tuple[int, int] | None = None, name: str = "K") -> np.ndarray:
    """``K`` as ``(3, 3) float64`` when it is a pinhole matrix that fits an image of ``size = (H, W)``.

    Checks: finite, last row ``[0, 0, 1]``, focal lengths ``fx, fy > 0``, and (with ``size``)
    the principal point inside the image (``-0.5 <= cx <= W - 0.5``, likewise ``cy``).
    Otherwise a ``ValueError`` names ``name`` and what was expected.
    """
    arr = np.asarray(K)
    if arr.shape != (3, 3) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name} must be a (3, 3) intrinsics matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "
                         f"got shape {arr.shape} {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite entries (NaN or inf): {arr.tolist()}")
    if not np.allclose(arr[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"{name} must have the last row [0, 0, 1], got {arr[2].tolist()}")
    fx, fy, cx, cy = arr[0, 0], arr[1, 1], arr[0, 2], arr[1, 2]
    if not (fx > 0 and fy > 0):
        raise ValueError(f"{name} has focal lengths fx = {fx:g}, fy = {fy:g} px; both must be > 0")
    if size is not None:
        H, W = size
        if not (-0.5 <= cx <= W - 0.5 and -0.5 <= cy <= H - 0.5):
            raise ValueError(
                f"{name}'s principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside its {W} x {H} (W x H) "
                f"image; expected 0 <= cx < {W} and 0 <= cy < {H}. Were the intrinsics made for another "
                "resolution (see cameras.scale_intrinsics), or are they normalised instead of in pixels?"
            )
    return arr


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation ``(3, 3)`` about ``axis (3,)`` by ``angle_rad``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * Kx + (1 - np.cos(angle_rad)) * Kx @ Kx


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` of an OpenCV camera at ``eye`` looking at ``target`` (world z up)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking straight along ``up``
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def pixel_grid(height: int, width: int) -> np.ndarray:
    """All pixel coordinates ``(H, W, 2) float64`` as ``(u, v)``."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([u, v], axis=-1)


def project(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of camera-frame ``points_cam (N, 3)``.

    Returns ``uv (N, 2) float64`` and depth ``z (N,) float64``. Points with ``z <= 0`` get
    ``uv = nan``.
    """
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = p @ np.asarray(K, dtype=np.float64).T
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[z <= 0] = np.nan
    return uv, z


def lift(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project pixels ``uv (N, 2)`` with depths ``(N,)`` to camera points ``(N, 3)``."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(depth, dtype=np.float64).reshape(-1)
    K = np.asarray(K, dtype=np.float64)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * d
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * d
    return np.stack([x, y, d], axis=1)


def backproject(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every valid pixel of ``depth (H, W)`` as camera points.

    Returns ``points (M, 3) float64`` and their pixels ``uv (M, 2) float64``; pixels with
    depth 0 or non-finite depth are skipped.
    """
    depth = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    uv = np.stack([u, v], axis=1).astype(np.float64)
    return lift(uv, depth[valid], K), uv


def bilinear_sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample ``image (H, W)`` or ``(H, W, C)`` at float pixels ``uv (N, 2)`` bilinearly.

    Coordinates are clamped to the image. Returns ``(N,)`` or ``(N, C)`` float64.
    """
    img = np.asarray(image, dtype=np.float64)
    H, W = img.shape[:2]
    u = np.clip(np.asarray(uv, dtype=np.float64)[:, 0], 0, W - 1)
    v = np.clip(np.asarray(uv, dtype=np.float64)[:, 1], 0, H - 1)
    u0 = np.minimum(np.floor(u).astype(int), W - 2) if W > 1 else np.zeros_like(u, int)
    v0 = np.minimum(np.floor(v).astype(int), H - 2) if H > 1 else np.zeros_like(v, int)
    du, dv = u - u0, v - v0
    u1, v1 = np.minimum(u0 + 1, W - 1), np.minimum(v0 + 1, H - 1)
    if img.ndim == 3:
        du, dv = du[:, None], dv[:, None]
    return (
        img[v0, u0] * (1 - du) * (1 - dv)
        + img[v0, u1] * du * (1 - dv)
        + img[v1, u0] * (1 - du) * dv
        + img[v1, u1] * du * dv
    )


def nearest_sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest-pixel lookup of ``image`` at ``uv (N, 2)`` (clamped); keeps the dtype."""
    img = np.asarray(image)
    H, W = img.shape[:2]
    u = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
    return img[v, u]


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of ``R_gt^T R_est`` in degrees."""
    c = (np.trace(np.asarray(R_gt).T @ np.asarray(R_est)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
