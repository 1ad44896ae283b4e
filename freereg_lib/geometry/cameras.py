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

import warnings

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


# Rotations read from files are orthonormal only to the digits written: 7-Scenes / 3DMatch pose
# files to ~3e-4. Up to ORTHO_FIX a pose is replaced by its nearest rigid pose (above
# ORTHO_WARN with a warning); beyond it the matrix is no rotation and is refused.
ORTHO_SILENT = 1e-9
ORTHO_WARN = 1e-4
ORTHO_FIX = 1e-2


def orthonormality(R: np.ndarray) -> float:
    """``max |R^T R - I|`` of a ``(3, 3)`` matrix: 0 for a rotation."""
    R = np.asarray(R, dtype=np.float64)
    return float(np.abs(R.T @ R - np.eye(3)).max())


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``R (3, 3)`` in the Frobenius norm (``U V^T`` of its SVD).

    Meant for a rotation with rounding errors; a reflection (det < 0) is not turned into a
    rotation here (:func:`check_pose` refuses it).
    """
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    return U @ Vt


def check_pose(T: np.ndarray, name: str = "T", atol: float = ORTHO_WARN, fix_tol: float = ORTHO_FIX,
               max_translation: float | None = None, units_hint: str = "", warn: bool = True) -> np.ndarray:
    """``T`` as a rigid ``(4, 4) float64`` pose, re-orthonormalised when it is off by a little.

    * ``max |R^T R - I|`` up to ``fix_tol`` (default 1e-2): R is replaced by the nearest
      rotation (:func:`nearest_rotation`; unchanged when it is a rotation to 1e-9), with a
      ``RuntimeWarning`` naming ``name`` when the deviation exceeds ``atol`` (1e-4; none with
      ``warn=False``, for a reader that warns its own way). A pose
      that is rigid to ``atol`` comes back bit for bit unchanged up to 1e-9.
    * Refused with a ``ValueError`` that names ``name``, gives the real deviation and says
      what is wrong: a reflection, a scale (a similarity), a transposed matrix (the
      translation in the bottom row), a last row other than ``[0, 0, 0, 1]``, R farther than
      ``fix_tol`` from a rotation, or (with ``max_translation``, in metres) a translation
      longer than the dataset allows (millimetres read as metres; ``units_hint`` is appended).
    """
    arr = np.asarray(T)
    if arr.shape != (4, 4) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name} must be a (4, 4) pose [[R, t], [0, 0, 0, 1]], got shape {arr.shape} {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite entries (NaN or inf): {arr.tolist()}")
    R = arr[:3, :3]
    det = float(np.linalg.det(R))
    ortho = orthonormality(R)
    bottom_ok = np.allclose(arr[3], [0, 0, 0, 1], atol=atol)
    if bottom_ok and det > 0 and ortho <= fix_tol:
        out = arr
        if ortho > ORTHO_SILENT:
            out = arr.copy()
            out[:3, :3] = nearest_rotation(R)
            out[3] = [0.0, 0.0, 0.0, 1.0]
            if ortho > atol and warn:
                warnings.warn(f"{name}: R is orthonormal only to {ortho:.1e} (max |R^T R - I|, above {atol:g}); "
                              f"replaced by the nearest rotation (SVD), as poses written with few digits need",
                              RuntimeWarning, stacklevel=2)
        t = float(np.linalg.norm(out[:3, 3]))
        if max_translation is not None and t > max_translation:
            raise ValueError(
                f"{name}: the translation |t| = {t:.6g} is longer than the {max_translation:g} m this dataset "
                f"allows; it looks like millimetres read as metres (divide t by 1000){units_hint}")
        return out
    scale = abs(det) ** (1 / 3)
    residual = orthonormality(R / scale) if scale > 0 else np.inf
    rigid_T = (np.allclose(arr[:3, 3], 0, atol=atol) and abs(arr[3, 3] - 1) <= atol
               and not np.allclose(arr[3, :3], 0, atol=atol) and orthonormality(arr[:3, :3].T) <= fix_tol
               and np.linalg.det(arr[:3, :3]) > 0)
    if rigid_T:
        hint = ("; it looks transposed: pass T.T (the translation sits in the bottom row and the last column "
                "is [0, 0, 0, 1]; a pose file holds the rows [R | t] with 0 0 0 1 last)")
    elif not bottom_ok:
        hint = f"; its last row is {arr[3].tolist()}, expected [0, 0, 0, 1]"
    elif det < 0:
        hint = "; det(R) < 0 is a reflection (an axis flipped, or a left-handed frame)"
    elif abs(scale - 1) > fix_tol and residual <= fix_tol:
        hint = f"; R carries a scale of {scale:.4g} (a similarity): divide it out"
    else:
        hint = (f"; R is farther from a rotation than the {fix_tol:g} within which a pose is re-orthonormalised "
                "(a per-axis scale or a shear, or numbers lost when the pose was written)")
    raise ValueError(
        f"{name} is not a rigid transform: expected [[R, t], [0, 0, 0, 1]] with R orthonormal and "
        f"det(R) = +1, got max |R^T R - I| = {ortho:.3g}, det(R) = {det:.6g}{hint}"
    )


def check_intrinsics(K: np.ndarray, size: tuple[int, int] | None = None, name: str = "K") -> np.ndarray:
    """``K`` as ``(3, 3) float64`` when it is a pinhole matrix in pixels that fits an image of
    ``size = (H, W)``.

    Checks: finite, last row ``[0, 0, 1]``, focal lengths ``fx, fy > 0``; not normalised
    (``fx, fy < 2`` px, or with ``size`` of at least 32 px a principal point in ``[0, 1]``
    with ``fx, fy < 10``: "normalised intrinsics: multiply row 0 by W and row 1 by H"); with
    ``size`` the principal point inside the image (``-0.5 <= cx <= W - 0.5``, likewise
    ``cy``) and not at the centre of another resolution: when ``(2 cx + 1) / W`` and
    ``(2 cy + 1) / H`` agree on a factor ``s`` (within 15 %) outside ``[0.67, 1.5]``,
    ``K`` was made for an image ``s`` times this one (a crop that keeps one corner of a
    larger image looks the same and is refused too: rescale ``K`` or the image instead). A
    principal point off centre along one axis only (KITTI after its top crop) passes.
    Otherwise a ``ValueError`` names ``name``, what was expected and the likely cause.
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
    if arr[0, 1] != 0 or arr[1, 0] != 0:
        # project() multiplies by the whole K, lift() reads fx, fy, cx, cy only: a skewed K would be
        # used one way and not the other, so it is refused rather than half used.
        what = (f"a skew K[0, 1] = {arr[0, 1]:g}" if arr[0, 1] != 0 else "") + (
            f"{' and ' if arr[0, 1] != 0 else ''}K[1, 0] = {arr[1, 0]:g}" if arr[1, 0] != 0 else "")
        raise ValueError(f"{name} has {what}: only a zero-skew pinhole K [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] is "
                         "supported (lifting pixels to 3-D ignores skew while projection would use it); undistort / "
                         "rectify the image to a zero-skew camera first")
    values = f"fx = {fx:g}, fy = {fy:g}, cx = {cx:g}, cy = {cy:g}"
    big = size is not None and min(size) >= 32
    if (fx < 2 and fy < 2) or (big and 0 <= cx <= 1 and 0 <= cy <= 1 and fx < 10 and fy < 10):
        H, W = size if size is not None else ("H", "W")
        what = (f"for a {W} x {H} (W x H) image" if size is not None
                else "(a real camera has focal lengths of hundreds of pixels)")
        raise ValueError(f"{name} holds normalised intrinsics: multiply row 0 by W and row 1 by H "
                         f"(K[0] *= {W}; K[1] *= {H}); got {values} {what}")
    if size is not None:
        H, W = size
        # The image whose centre the principal point is: (2 cx + 1) x (2 cy + 1) pixels.
        sx, sy = (2 * cx + 1) / W, (2 * cy + 1) / H
        s = float(np.sqrt(abs(sx * sy)))
        other = sx > 0 and sy > 0 and abs(sx - sy) <= 0.15 * max(sx, sy) and not (1 / 1.5 <= s <= 1.5)
        hint = ""
        if other:
            hint = (f" K looks made for a {2 * cx + 1:.0f} x {2 * cy + 1:.0f} image (its principal point is at "
                    f"that image's centre), not this {W} x {H} one: rescale it with "
                    f"cameras.scale_intrinsics(K, {1 / sx:.4g}, {1 / sy:.4g}), or resize the image to match.")
        if not (-0.5 <= cx <= W - 0.5 and -0.5 <= cy <= H - 0.5):
            raise ValueError(
                f"{name}'s principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside its {W} x {H} (W x H) "
                f"image; expected 0 <= cx < {W} and 0 <= cy < {H}."
                + (hint or " Were the intrinsics made for another resolution (see cameras.scale_intrinsics)?")
            )
        if other:
            raise ValueError(f"{name}'s principal point (cx, cy) = ({cx:g}, {cy:g}) is far from the centre "
                             f"({(W - 1) / 2:g}, {(H - 1) / 2:g}) of its {W} x {H} (W x H) image.{hint}")
    return arr


def check_size_order(K: np.ndarray, size: tuple[int, int], name: str = "depth_size", k_name: str = "K_depth") -> None:
    """Refuse an image size given as ``(W, H)`` where ``(H, W)`` is meant.

    With ``K``'s principal point near the centre of the swapped size (``cx ~ size[0] / 2``,
    ``cy ~ size[1] / 2``, within 10 % of the sides together) and not near the centre of the
    size as given (off by more than 20 %), a ``ValueError`` says "``name`` is (H, W); you gave
    (W, H)?". Square sizes and off-centre principal points (KITTI's crop) are left alone.
    """
    K = np.asarray(K, dtype=np.float64)
    a, b = (int(v) for v in size)
    if a == b or K.shape != (3, 3):
        return
    cx, cy = K[0, 2], K[1, 2]
    given = abs(cx - (b - 1) / 2) / b + abs(cy - (a - 1) / 2) / a
    swapped = abs(cx - (a - 1) / 2) / a + abs(cy - (b - 1) / 2) / b
    if swapped < 0.1 and given > 0.2:
        raise ValueError(f"{name} is (H, W); you gave (W, H)? {name} = {tuple(size)} puts the image centre at "
                         f"({(b - 1) / 2:g}, {(a - 1) / 2:g}), far from {k_name}'s principal point "
                         f"({cx:g}, {cy:g}); ({b}, {a}) fits it")


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


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)``, ``w >= 0``, of a ``(3, 3)`` rotation, by the
    eigenvector method the official ``r_eval.quaternion_from_matrix(isprecise=False)`` uses
    (robust to a rotation that is orthonormal only to the digits a pose file holds, and to a
    uniform scale)."""
    m = np.asarray(R, dtype=np.float64)[:3, :3]
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m
    Km = np.array([[m00 - m11 - m22, 0.0, 0.0, 0.0],
                   [m01 + m10, m11 - m00 - m22, 0.0, 0.0],
                   [m02 + m20, m12 + m21, m22 - m00 - m11, 0.0],
                   [m21 - m12, m02 - m20, m10 - m01, m00 + m11 + m22]]) / 3.0
    w, V = np.linalg.eigh(Km)  # the lower triangle is read
    q = V[[3, 0, 1, 2], np.argmax(w)]
    return -q if q[0] < 0 else q


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of ``R_gt^T R_est`` in degrees, as the official ``compute_R_diff``: from the two
    quaternions, ``arccos(1 - 2 max(1e-15, 1 - <q, q_gt>^2))`` (identical rotations give
    ~5e-6 deg, not 0)."""
    eps = 1e-15
    q = quaternion_from_matrix(R_est)
    q_gt = quaternion_from_matrix(R_gt)
    q = q / (np.linalg.norm(q) + eps)
    q_gt = q_gt / (np.linalg.norm(q_gt) + eps)
    loss = max(eps, 1.0 - float(np.sum(q * q_gt)) ** 2)
    return float(np.degrees(abs(np.arccos(1.0 - 2.0 * loss))))
