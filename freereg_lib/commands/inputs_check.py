"""Geometry checks where one's own data enters (``freereg register``, :mod:`freereg_lib.pipeline.register`).

Each check raises :class:`InputError` (a ``ValueError``) with one line
naming the input and what was expected (docs/troubleshooting.md, "When something goes wrong"):

* :func:`positive`: ``--depth-scale``, ``--cloud-scale`` (0, negative, NaN or inf refused);
* :func:`depth_size_fits`: ``--depth-size W H`` against the depth camera's principal point
  (``--depth-K``) or, without one, against the image's aspect ratio (a depth camera given no
  intrinsics has the image's field of view); ``H W`` given for ``W H`` is named as such;
* :func:`principal_point_order`: ``--K fx fy cy cx`` (cx and cy swapped) and ``--K cx cy fx fy``
  named as such, before the intrinsics' range check;
* :func:`square_pixels`: an image whose pixels are not square (``fx != fy``, an anamorphic
  or squeezed frame) is resampled to square pixels, its intrinsics and its depth map with it:
  the learned models read an image as a square-pixel photo (ZoeDepth keeps the aspect ratio it
  is given, so a squeezed room comes back with squeezed depth);
* :func:`exif_orientation`: the EXIF orientation tag of a photo. Images are read **as their
  pixels are stored** (the tag is not applied, to the image or to its depth map), because
  intrinsics and depth maps describe the sensor's stored pixel grid; a photo whose tag asks for
  a rotation is said so in a note (:func:`exif_note`);
* :func:`depth_units_against_cloud`: with a ground-truth pose, the image's true depth against
  the cloud seen from that pose: a median ratio off by more than 25 % (2 mm units read as
  1 mm give 0.5; a depth off by 3-10x) is refused with the ``--depth-scale`` that fits;
* :func:`pose_sees_cloud`: a pose that shows almost none of the cloud while it puts most of
  the cloud behind the camera or its inverse shows it (an inverted ``T_cam_pc``, a ``T_pc_cam``
  given as ``T_cam_pc``);
* :func:`float32_precision`: a cloud stored in float32 (a ``float`` PLY, a float32 ``.npy``) so far
  from its origin that float32 keeps only centimetres or worse (0.5 m at 5,000 km) is refused;
* :func:`recentre_offset`: the offset that re-centres a cloud far from its origin (UTM
  coordinates, thousands of km) before solving; :func:`~freereg_lib.pipeline.register.register` applies
  it and restores the pose after, a numerical safeguard that changes nothing for clouds near
  their origin.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from freereg_lib.geometry import cameras
from freereg_lib.geometry.projection import project_to_depth
from freereg_lib.pipeline.register import InputError


def _error(msg: str) -> Exception:
    return InputError(msg)


# --------------------------------------------------------------------------------------
# Scales and sizes.

FLOAT32_STEP_MAX_M = 0.005  # a float32 cloud whose coordinates keep only steps coarser than this is refused


def float32_precision(points: np.ndarray, where: str) -> None:
    """Refuse a cloud whose every coordinate is a float32 value (a float32 file, read as float64)
    when float32 keeps only steps coarser than ``FLOAT32_STEP_MAX_M`` at its largest coordinate:
    its points have been moved by up to half that step (0.25 m at 5,000 km) and no re-centring
    brings them back. Doubles (float64) keep ~1e-9 m there."""
    pts = np.asarray(points, dtype=np.float64)
    big = float(np.max(np.abs(pts[np.isfinite(pts)]), initial=0.0))
    step = float(np.spacing(np.float32(big)))
    if step > FLOAT32_STEP_MAX_M and np.array_equal(pts.astype(np.float32).astype(np.float64), pts):
        raise _error(f"{where} is stored in float32 and lies {big:.4g} m from its origin, where float32 keeps "
                     f"only steps of {step:g} m: the points have been moved by up to {step / 2:g} m; write it "
                     "with float64 (double) coordinates, or subtract an offset before saving")

def positive(value, flag: str, what: str) -> float:
    """``value`` as a float when it is finite and > 0, else one line naming ``flag``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise _error(f"{flag} must be a positive number ({what}), got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise _error(f"{flag} must be a positive number ({what}), got {value!r}")
    return v


def depth_size_fits(image_hw: tuple[int, int], depth_hw: tuple[int, int], depth_K=None) -> None:
    """Refuse a depth camera size given as ``H W`` for ``W H`` (``depth_hw`` is ``(H, W)`` as
    parsed from ``--depth-size W H``), or one that does not fit its camera.

    With ``depth_K``: its principal point must sit near the centre of the size as given
    (:func:`~freereg_lib.geometry.cameras.check_size_order` catches the swap). Without: the depth camera
    takes the image's intrinsics scaled to its size, so its aspect ratio must be the image's
    (within 10 %); a swapped size, or another aspect, is refused (give ``--depth-K`` then).
    """
    Hd, Wd = (int(v) for v in depth_hw)
    if Hd < 1 or Wd < 1:
        raise _error(f"--depth-size W H must be two positive integers, got {Wd} {Hd}")
    if depth_K is not None:
        K = np.asarray(depth_K, dtype=np.float64)
        K = cameras.intrinsics(*K.ravel()) if K.size == 4 else K.reshape(3, 3)
        try:
            cameras.check_size_order(K, (Hd, Wd), "--depth-size", "--depth-K")
        except ValueError:
            if (Hd, Wd) == tuple(int(v) for v in image_hw):  # the image's size: the size is right, K is not
                principal_point_order(K, (Hd, Wd), "--depth-K")
            raise _error(f"--depth-size is W H (width first); you gave H W? --depth-size {Wd} {Hd} puts the depth "
                         f"image's centre at ({(Wd - 1) / 2:g}, {(Hd - 1) / 2:g}), far from --depth-K's principal "
                         f"point ({K[0, 2]:g}, {K[1, 2]:g}); --depth-size {Hd} {Wd} fits it (or --depth-K is "
                         f"fx fy cy cx: give {K[0, 0]:g} {K[1, 1]:g} {K[1, 2]:g} {K[0, 2]:g})") from None
        return
    H, W = image_hw
    a_img, a_dep = W / H, Wd / Hd
    if abs(a_dep - a_img) <= 0.1 * a_img:
        return
    swapped = abs(Hd / Wd - a_img) <= 0.1 * a_img
    raise _error(
        f"--depth-size {Wd} {Hd} (W H) has the aspect {a_dep:.3g}, the image {W} x {H} has {a_img:.3g}: "
        + (f"you gave H W? --depth-size {Hd} {Wd} fits the image" if swapped else
           "without --depth-K the depth camera takes the image's intrinsics scaled to its size, so its aspect "
           "must be the image's; give --depth-K fx fy cx cy for a depth camera of another field of view"))


def _off_centre(x: float, y: float, W: int, H: int) -> float:
    """How far ``(x, y)`` lies from the centre of a ``W x H`` image, in fractions of its sides (summed)."""
    return abs(x - (W - 1) / 2) / W + abs(y - (H - 1) / 2) / H


def principal_point_order(K: np.ndarray, image_hw: tuple[int, int], flag: str = "--K") -> None:
    """Refuse image intrinsics given in another order than ``fx fy cx cy``, naming ``flag``:

    * ``cx, cy`` given as ``cy, cx`` (``--K fx fy cy cx``): the principal point near the centre
      of the image turned (within 10 % of the sides together) and far from its centre as it is
      (over 20 %). Without this check the swap was blamed on ``--depth-size``, which the depth
      camera had taken from the image; on a wide image (``cx > H``) it was called a principal
      point "outside the image" made for another resolution. Square images pass;
    * ``cx cy fx fy``: ``fx, fy`` near the image's centre (within 10 %) and ``cx, cy`` far from
      it (over 20 %), for an image of at least 32 pixels.

    Runs before :func:`~freereg_lib.geometry.cameras.check_intrinsics` (whose range check would
    otherwise speak first)."""
    H, W = (int(v) for v in image_hw)
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not np.all(np.isfinite([fx, fy, cx, cy])):
        return  # check_intrinsics names non-finite entries
    given = _off_centre(cx, cy, W, H)
    if H != W and _off_centre(cy, cx, W, H) < 0.1 and given > 0.2:
        raise _error(f"{flag}: cx, cy look swapped: (cx, cy) = ({cx:g}, {cy:g}) is near the centre of a {H} x {W} "
                     f"(W x H) image, far from the centre ({(W - 1) / 2:g}, {(H - 1) / 2:g}) of this {W} x {H} one; "
                     f"the order is fx fy cx cy (cx along the width): {flag} {fx:g} {fy:g} {cy:g} {cx:g}")
    if min(H, W) >= 32 and _off_centre(fx, fy, W, H) < 0.1 and given > 0.2:
        raise _error(f"{flag}: the principal point looks given first: fx, fy = {fx:g}, {fy:g} lie near the centre "
                     f"({(W - 1) / 2:g}, {(H - 1) / 2:g}) of this {W} x {H} image and cx, cy = {cx:g}, {cy:g} far "
                     f"from it; the order is fx fy cx cy: {flag} {cx:g} {cy:g} {fx:g} {fy:g}")


# --------------------------------------------------------------------------------------
# Pixels that are not square.

SQUARE_TOLERANCE = 0.01  # |fx / fy - 1| up to this is square: calibrations of one camera differ by tenths of a %
MAX_PIXEL_ASPECT = 4.0   # fx / fy beyond this (or below its inverse) is no camera's: refused, not resampled


def square_pixels(image: np.ndarray, K: np.ndarray, depth: np.ndarray | None = None,
                  flag: str = "--K") -> tuple[np.ndarray, np.ndarray, np.ndarray | None, str]:
    """``(image, K, depth, note)`` with square pixels: unchanged (and ``note == ""``) when
    ``fx`` and ``fy`` agree within ``SQUARE_TOLERANCE``; otherwise the axis of the smaller
    focal length is upsampled (bilinear for the image, nearest for the depth map, whose
    edges must not blend) until ``fx = fy`` to the pixel, and ``K`` is scaled with it
    (:func:`~freereg_lib.geometry.cameras.scale_intrinsics`). The camera is the same, so the
    pose found on the resampled image is the pose of the image as given. ``fx / fy`` beyond
    ``MAX_PIXEL_ASPECT`` is refused, naming ``flag``: fx and fy were most likely mistyped."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy = float(K[0, 0]), float(K[1, 1])
    ratio = fx / fy
    if abs(ratio - 1.0) <= SQUARE_TOLERANCE:
        return image, K, depth, ""
    if not (1 / MAX_PIXEL_ASPECT <= ratio <= MAX_PIXEL_ASPECT):
        raise _error(f"{flag}: fx = {fx:g} and fy = {fy:g} px differ {max(ratio, 1 / ratio):.3g} times; expected "
                     f"about equal focal lengths (square pixels; up to {MAX_PIXEL_ASPECT:g} x is resampled): "
                     "check the order fx fy cx cy and that both are in pixels of this image")
    H, W = image.shape[:2]
    # Upsample, never shrink: the resampled image keeps every pixel's detail.
    w, h = (max(1, round(W / ratio)), H) if ratio < 1 else (W, max(1, round(H * ratio)))
    K2 = cameras.scale_intrinsics(K, w / W, h / H)
    image2 = cv2.resize(np.ascontiguousarray(image), (w, h), interpolation=cv2.INTER_LINEAR)
    depth2 = None if depth is None else cv2.resize(np.ascontiguousarray(depth), (w, h),
                                                   interpolation=cv2.INTER_NEAREST_EXACT)
    note = (f"note: the image's pixels are not square ({flag}: fx = {fx:g}, fy = {fy:g} px); it is resampled from "
            f"{W} x {H} to {w} x {h} (fx = {K2[0, 0]:.6g}, fy = {K2[1, 1]:.6g}, cx = {K2[0, 2]:.6g}, "
            f"cy = {K2[1, 2]:.6g}), as the models read images as square-pixel photos; the pose is the same camera's, "
            "the drawings show the resampled image")
    return image2, K2, depth2, note


# --------------------------------------------------------------------------------------
# EXIF orientation.

EXIF_ORIENTATION_TAG = 0x0112
_EXIF_MEANING = {2: "mirrored", 3: "rotated 180 deg", 4: "flipped upside down", 5: "mirrored and rotated 90 deg",
                 6: "rotated 90 deg clockwise", 7: "mirrored and rotated 270 deg", 8: "rotated 90 deg anticlockwise"}


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation tag of an image file (1 = as stored; 0 when the file has none)."""
    try:
        with Image.open(path) as im:
            return int(im.getexif().get(EXIF_ORIENTATION_TAG, 0) or 0)
    except Exception:
        return 0


def exif_note(path: str | Path) -> str:
    """A note when ``path`` asks viewers to rotate or mirror it, else ``""``: the companion uses
    the pixels as stored, for the image and its depth map alike."""
    tag = exif_orientation(path)
    if tag in (0, 1):
        return ""
    return (f"note: {Path(path).name} carries the EXIF orientation {tag} ({_EXIF_MEANING.get(tag, 'unknown')}); it is "
            "NOT applied: the image is used as its pixels are stored, like its depth map, and --K / --intrinsics "
            "must be the stored image's (a photo viewer shows it turned)")


# --------------------------------------------------------------------------------------
# Depth units against the cloud, and poses that look away from it.

DEPTH_RATIO_TOLERANCE = 1.25  # the image depth / cloud depth median ratio must lie in [1/1.25, 1.25]
MIN_DEPTH_COMPARED = 50       # pixels where both are known; fewer: not checked


def cloud_depth_in_image(points: np.ndarray, K: np.ndarray, T_cam_pc: np.ndarray, size: tuple[int, int],
                         max_points: int = 200_000) -> np.ndarray:
    """The cloud's z-buffered depth seen by the image camera at ``T_cam_pc`` (0 = no point)."""

    pts = points[:: max(1, len(points) // max_points)]
    depth, _ = project_to_depth(pts, K, T_cam_pc, size, 1e-6)
    return depth


def depth_units_against_cloud(depth_gt: np.ndarray, points: np.ndarray, K: np.ndarray, T_cam_pc: np.ndarray,
                              depth_scale: float, source: str = "--image-depth",
                              scale_flag: str = "--depth-scale") -> float | None:
    """The median ratio of the image's true depth to the cloud's depth at the same pixels (the
    cloud seen with the ground-truth pose); refused when it is off 1 by more than 25 %
    (``DEPTH_RATIO_TOLERANCE``), naming the ``--depth-scale`` that fits. ``None`` when fewer
    than ``MIN_DEPTH_COMPARED`` pixels have both."""
    cloud = cloud_depth_in_image(points, K, T_cam_pc, depth_gt.shape[:2])
    both = (cloud > 0) & (depth_gt > 0) & np.isfinite(depth_gt)
    if both.sum() < MIN_DEPTH_COMPARED:
        return None
    ratio = float(np.median(depth_gt[both] / cloud[both]))
    if 1 / DEPTH_RATIO_TOLERANCE <= ratio <= DEPTH_RATIO_TOLERANCE:
        return ratio
    raise _error(
        f"{source}: its depth is {ratio:.3g} x the cloud's depth at the same pixels (median over {int(both.sum())} "
        f"pixels, the cloud seen with the ground-truth pose); {scale_flag} {depth_scale:g} looks wrong, "
        f"{scale_flag} {depth_scale * ratio:.4g} fits (e.g. 500 for 2 mm units, 1000 for millimetres), "
        "or the cloud is not in metres (--cloud-scale)")


MIN_IN_VIEW = 0.05     # a pose that shows less than this share of the cloud in the image is refused when ...
MIN_IN_FRONT = 0.5     # ... it puts more than half of the cloud behind the camera, or ...
INVERSE_IN_VIEW = 0.2  # ... its inverse shows at least this share (the pose was given the wrong way round)


def pose_sees_cloud(T_cam_pc: np.ndarray, points: np.ndarray, K: np.ndarray, size: tuple[int, int], what: str,
                    inverse_name: str) -> None:
    """Refuse a pose (``T_cam_pc``: the cloud into a camera of intrinsics ``K``, image ``size =
    (H, W)``) that shows almost none of the cloud (under ``MIN_IN_VIEW`` of its points in the
    image) while it puts most of the cloud behind the camera (under ``MIN_IN_FRONT`` in front),
    or while its inverse shows a good part of it (``INVERSE_IN_VIEW``): an inverted pose, or
    ``inverse_name`` given for it. A pose that shows the cloud passes whatever its direction."""
    pts = np.asarray(points, dtype=np.float64)[:: max(1, len(points) // 50_000)]

    def shares(T):
        uv, z = cameras.project(cameras.transform(T, pts), K)
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < size[1] - 0.5) & (uv[:, 1] >= -0.5) \
                & (uv[:, 1] < size[0] - 0.5)
        return float(np.mean(z > 0)), float(np.mean(inside))

    front, view = shares(T_cam_pc)
    if view >= MIN_IN_VIEW:
        return
    _, inv_view = shares(cameras.invert(T_cam_pc))
    if front >= MIN_IN_FRONT and inv_view < INVERSE_IN_VIEW:
        return
    hint = (f"; its inverse shows {inv_view:.0%} of it: did you give {inverse_name}?" if inv_view >= INVERSE_IN_VIEW
            else "; check the pose's direction and the cloud's frame")
    raise _error(f"{what} puts {1 - front:.0%} of the cloud behind the camera and {view:.0%} of it in the "
                 f"{size[1]} x {size[0]} view{hint}")


# --------------------------------------------------------------------------------------
# Clouds far from their origin.
