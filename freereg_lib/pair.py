"""The ``Pair``: one image-to-point-cloud registration problem with its ground truth.

Every data source (synthetic scenes, the embedded ICL sample, dataset loaders) yields
``Pair`` objects, and every pipeline step reads them.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Pair:
    """An RGB image, a point cloud, the depth view to project it on, and the true pose.

    Attributes:
        image: ``(H, W, 3) uint8`` RGB.
        K_image: ``(3, 3)`` intrinsics of the image.
        points: ``(N, 3) float64`` point cloud in its own frame ``pc``.
        K_depth: ``(3, 3)`` intrinsics of the virtual depth camera the cloud is projected on.
        depth_size: ``(H_d, W_d)`` of that depth map.
        T_pc_sensor: ``(4, 4)`` pose of the depth camera in the ``pc`` frame.
        T_cam_pc: ``(4, 4)`` ground truth, maps ``pc`` points into the image camera. This
            is what the solvers estimate.
        depth_gt: ``(H, W) float64`` true depth of the image (evaluation only; 0 = none).
        sensor_depth: ``(H_d, W_d) float64`` the depth frame's own sensor depth in metres
            (0 = hole), when the dataset has one (3DMatch, ScanNet, KITTI-DC). As in the
            official code it *is* the depth map (no projection round trip; densified per
            ``cfg.densify``), the depth-side cloud for geometric features is its
            back-projection, and evaluation lifts depth-side keypoints with it (the
            official ``dpt_gtd``). None: the cloud is projected on the depth camera instead.
        image_ids: ``(H, W) int32`` class ids of the image pixels (synthetic only).
        point_ids: ``(N,) int32`` class ids of the points (synthetic only).
        name: a short identifier, e.g. ``"icl/00010-00040"``.
        meta: free-form facts (dataset, scene, overlap, indoor/outdoor).
    """

    image: np.ndarray
    K_image: np.ndarray
    points: np.ndarray
    K_depth: np.ndarray
    depth_size: tuple[int, int]
    T_pc_sensor: np.ndarray
    T_cam_pc: np.ndarray
    depth_gt: np.ndarray | None = None
    sensor_depth: np.ndarray | None = None
    image_ids: np.ndarray | None = None
    point_ids: np.ndarray | None = None
    name: str = "pair"
    meta: dict = field(default_factory=dict)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.image.shape[0], self.image.shape[1]

    def validate(self) -> "Pair":
        """Check every field against the layout above; returns the pair itself.

        Raises ``ValueError`` naming the pair, the field and what was expected: an image that
        is not ``(H, W, 3) uint8``, an empty cloud or one with NaN / inf points, intrinsics
        with a non-positive focal length or a principal point outside their image, a pose
        that is not rigid, a ``depth_gt`` of another size or without one valid pixel, id maps
        of the wrong size. :func:`freereg_lib.pipeline.compute_features` calls it first, so
        inside a benchmark a bad pair becomes a recorded failure.
        """
        from . import cameras

        def fail(msg: str):
            raise ValueError(f"pair {self.name}: {msg}")

        def checked(check, *args):
            try:
                check(*args)
            except ValueError as exc:
                msg = str(exc)
            else:
                return
            fail(msg)

        img = np.asarray(self.image)
        if img.ndim != 3 or img.shape[2] != 3:
            hint = ""
            if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
                hint = "; a grayscale image: make it RGB with np.repeat(image.reshape(H, W, 1), 3, axis=2)"
            elif img.ndim == 3 and img.shape[2] == 4:
                hint = "; an RGBA image: drop alpha with image[..., :3]"
            fail(f"image must be an (H, W, 3) uint8 RGB array, got shape {img.shape}{hint}")
        if img.dtype != np.uint8:
            hint = ""
            if np.issubdtype(img.dtype, np.floating) and img.size and np.nanmax(img) <= 1.0:
                hint = "; values in [0, 1]: convert with (image * 255).round().astype(np.uint8)"
            fail(f"image must be uint8 RGB (0..255), got dtype {img.dtype}{hint}")
        H, W = img.shape[:2]
        if H == 0 or W == 0:
            fail(f"image is empty (shape {img.shape})")
        pts = np.asarray(self.points)
        if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
            fail(f"points must be an (N, 3) float array of x, y, z, got shape {pts.shape} {pts.dtype}")
        if len(pts) == 0:
            fail("the point cloud is empty (0 points); check the cloud file or the depth map it came from")
        bad = int(np.count_nonzero(~np.isfinite(pts).all(axis=1)))
        if bad:
            fail(f"{bad} of {len(pts)} points are not finite (NaN or inf); drop them with "
                 "pair = pair.drop_nonfinite_points()")
        checked(cameras.check_intrinsics, self.K_image, (H, W), "K_image")
        try:
            size = tuple(int(v) for v in self.depth_size)
            ok = len(size) == 2 and size == tuple(self.depth_size) and min(size) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            fail(f"depth_size must be (H_d, W_d), two positive integers, got {self.depth_size!r}")
        checked(cameras.check_intrinsics, self.K_depth, size, "K_depth")
        checked(cameras.check_pose, self.T_pc_sensor, "T_pc_sensor")
        checked(cameras.check_pose, self.T_cam_pc, "T_cam_pc")
        if self.depth_gt is not None:
            d = np.asarray(self.depth_gt)
            if d.shape != (H, W):
                fail(f"depth_gt must be (H, W) = {(H, W)} like the image, got shape {d.shape}")
            if not np.any(np.isfinite(d) & (d > 0)):
                fail("depth_gt has no valid pixel (all zero: no true depth anywhere); pass depth_gt=None "
                     "when the image has no ground-truth depth (the pair can then be registered, not scored)")
        if self.sensor_depth is not None:
            d = np.asarray(self.sensor_depth)
            if d.shape != size:
                fail(f"sensor_depth must be (H_d, W_d) = {size} like depth_size, got shape {d.shape}")
            if not np.any(np.isfinite(d) & (d > 0)):
                fail("sensor_depth has no valid pixel (all zero); pass sensor_depth=None to project the cloud instead")
        if self.image_ids is not None and np.shape(self.image_ids) != (H, W):
            fail(f"image_ids must be (H, W) = {(H, W)} like the image, got shape {np.shape(self.image_ids)}")
        if self.point_ids is not None and np.shape(self.point_ids) != (len(pts),):
            fail(f"point_ids must be (N,) = ({len(pts)},) like points, got shape {np.shape(self.point_ids)}")
        return self

    def drop_nonfinite_points(self) -> "Pair":
        """A copy without the points that hold NaN or inf (and their ``point_ids``); warns with the count."""
        keep = np.isfinite(np.asarray(self.points, dtype=np.float64)).all(axis=1)
        if keep.all():
            return self
        warnings.warn(f"pair {self.name}: dropped {int((~keep).sum())} of {len(keep)} points that are NaN or inf",
                      RuntimeWarning, stacklevel=2)
        ids = None if self.point_ids is None else np.asarray(self.point_ids)[keep]
        return dataclasses.replace(self, points=np.asarray(self.points)[keep], point_ids=ids)


class UnreadablePair:
    """Stands in for a pair whose files could not be read, so a benchmark goes on.

    Loaders yield it (see :func:`load_or_record`) instead of raising in the middle of a run;
    ``name`` and ``error`` are set, and :meth:`validate` or any other field re-raises the
    original error, so :func:`freereg_lib.pipeline.run_pair` records it as a failed pair
    (not registered) and code that uses the pair directly sees the original message.
    """

    def __init__(self, name: str, error: Exception):
        self.name = name
        self.error = error
        self.meta = {"unreadable": True}

    def validate(self):
        raise self.error

    def __getattr__(self, attr):
        if attr.startswith("_"):
            raise AttributeError(attr)
        raise self.error

    def __repr__(self) -> str:
        return f"UnreadablePair({self.name!r}, {type(self.error).__name__}: {self.error})"


def load_or_record(name: str, load, *args, **kw):
    """``load(*args, **kw)``, or an :class:`UnreadablePair` holding the error when it raises."""
    try:
        return load(*args, **kw)
    except Exception as exc:  # recorded per pair so a benchmark goes on
        return UnreadablePair(name, exc)
