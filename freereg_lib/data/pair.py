"""The ``Pair``: one image-to-point-cloud registration problem with its ground truth.

Every data source (synthetic scenes, the embedded ICL sample, dataset loaders) yields
``Pair`` objects, and every pipeline step reads them.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from freereg_lib.geometry import cameras


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
        depth_frame_gt: ``(H_d, W_d) float64`` true depth of the depth camera's frame, for
            evaluation only (0 = none), when the cloud is a sample of a denser truth (synthetic
            rooms: the cloud is a subsample of it). Evaluation then lifts depth-side keypoints
            with it, as the official code lifts them with the depth frame's own ``dpt_gtd``;
            None: with ``sensor_depth``, else with the projected cloud, whose holes make the
            matches on them unevaluable.
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
    depth_frame_gt: np.ndarray | None = None
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
        that do not fit their image (:func:`~freereg_lib.geometry.cameras.check_intrinsics`: a
        non-positive focal length, normalised intrinsics, a principal point outside the image
        or at the centre of another resolution), a ``depth_size`` given as ``(W, H)``, a pose
        that is not rigid (:func:`~freereg_lib.geometry.cameras.check_pose`), a camera thousands of
        cloud sizes away from the cloud (a translation in millimetres), a ``depth_gt`` or
        ``sensor_depth`` / ``depth_frame_gt`` of another size, without one valid pixel, or in other units than the
        cloud (its median more than 50 x or less than 1/50 of the median depth of the cloud
        seen from the depth camera: millimetres vs metres), id maps of the wrong size, and a
        ``depth_gt`` that ``T_cam_pc`` does not lift onto the cloud where a fault named by
        :func:`geometry_fault` (which says what it cannot tell) would.

        Poses off orthonormal by up to 1e-2 (rotations written with few digits) are replaced
        *in this pair* by their nearest rigid pose, with a warning above 1e-4.
        :func:`freereg_lib.pipeline.compute_features` calls it first, so inside a benchmark a
        bad pair becomes a recorded failure.
        """

        def fail(msg: str):
            raise ValueError(f"pair {self.name}: {msg}")

        def checked(check, *args, **kw):
            try:
                return check(*args, **kw)
            except ValueError as exc:
                msg = str(exc)
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
            ok = len(size) == 2 and min(size) > 0 and all(  # integers by type: numpy refuses (480.0, 640.0)
                isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in self.depth_size)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            fail(f"depth_size must be (H_d, W_d), two positive integers, got {self.depth_size!r}")
        if np.shape(self.K_depth) == (3, 3):
            checked(cameras.check_size_order, self.K_depth, size, "depth_size", "K_depth")
        checked(cameras.check_intrinsics, self.K_depth, size, "K_depth")
        for name in ("T_pc_sensor", "T_cam_pc"):
            given = getattr(self, name)
            T = checked(cameras.check_pose, given, name, warn=False)
            if not np.array_equal(T, given):  # re-orthonormalised
                ortho = cameras.orthonormality(np.asarray(given, dtype=np.float64)[:3, :3])
                if ortho > cameras.ORTHO_WARN:
                    warnings.warn(f"pair {self.name}: {name}'s R is orthonormal only to {ortho:.1e} (max |R^T R - I|, "
                                  f"above {cameras.ORTHO_WARN:g}); replaced by the nearest rotation (SVD)",
                                  RuntimeWarning, stacklevel=2)
                setattr(self, name, T)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        across = float(np.linalg.norm(hi - lo))
        for name, centre in (("T_cam_pc", cameras.invert(self.T_cam_pc)[:3, 3]), ("T_pc_sensor", self.T_pc_sensor[:3, 3])):
            away = float(np.linalg.norm(np.maximum(0, np.maximum(lo - centre, centre - hi))))
            if away > 10 * across + 100:
                fail(f"{name} puts its camera {away:.4g} m from the point cloud, which is {across:.3g} m across: "
                     "its translation looks like millimetres (divide t by 1000), or it belongs to another cloud")
        ref = None  # median depth of the cloud seen from the depth camera, for the units of depth maps
        for name, shape in (("depth_gt", (H, W)), ("sensor_depth", size), ("depth_frame_gt", size)):
            d = getattr(self, name)
            if d is None:
                continue
            d = np.asarray(d)
            if d.shape != shape:
                fail(f"{name} must be {'(H, W)' if name == 'depth_gt' else '(H_d, W_d)'} = {shape} like "
                     f"{'the image' if name == 'depth_gt' else 'depth_size'}, got shape {d.shape}")
            valid = np.isfinite(d) & (d > 0)
            if not valid.any():
                if name == "depth_gt":
                    fail("depth_gt has no valid pixel (all zero: no true depth anywhere); pass depth_gt=None "
                         "when the image has no ground-truth depth (the pair can then be registered, not scored)")
                if name == "depth_frame_gt":
                    fail("depth_frame_gt has no valid pixel (all zero); pass depth_frame_gt=None to score the "
                         "depth side with the projected cloud")
                fail("sensor_depth has no valid pixel (all zero); pass sensor_depth=None to project the cloud instead")
            if ref is None:
                ref = self._cloud_median_depth(pts, size)
            median = float(np.median(d[valid]))
            if ref > 0 and not 1 / 50 <= median / ref <= 50:
                fail(f"{name}'s median {median:.4g} is {median / ref:.3g} x the median depth {ref:.4g} m of the "
                     f"point cloud seen from the depth camera: {_units_hint(name, median / ref)}")
        if self.depth_gt is not None and self.meta.get("has_gt", True):
            cause = geometry_fault(self)
            if cause:
                fail(cause)
        if self.image_ids is not None and np.shape(self.image_ids) != (H, W):
            fail(f"image_ids must be (H, W) = {(H, W)} like the image, got shape {np.shape(self.image_ids)}")
        if self.point_ids is not None and np.shape(self.point_ids) != (len(pts),):
            fail(f"point_ids must be (N,) = ({len(pts)},) like points, got shape {np.shape(self.point_ids)}")
        return self

    def _cloud_median_depth(self, pts: np.ndarray, size: tuple[int, int]) -> float:
        """Median z of the cloud points inside the depth camera's view (at most ~50k of them); 0 when none."""

        sub = pts[:: max(1, len(pts) // 50_000)]
        uv, z = cameras.project(cameras.transform(cameras.invert(self.T_pc_sensor), sub), self.K_depth)
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < size[1] - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < size[0] - 0.5)
        return float(np.median(z[inside])) if inside.any() else 0.0

    def drop_nonfinite_points(self) -> "Pair":
        """A copy without the points that hold NaN or inf (and their ``point_ids``); warns with the count."""
        keep = np.isfinite(np.asarray(self.points, dtype=np.float64)).all(axis=1)
        if keep.all():
            return self
        warnings.warn(f"pair {self.name}: dropped {int((~keep).sum())} of {len(keep)} points that are NaN or inf",
                      RuntimeWarning, stacklevel=2)
        ids = None if self.point_ids is None else np.asarray(self.point_ids)[keep]
        return dataclasses.replace(self, points=np.asarray(self.points)[keep], point_ids=ids)


def _units_hint(name: str, ratio: float) -> str:
    k = int(np.round(np.log10(ratio)))
    if k >= 3:
        return (f"{name} looks like millimetres where the cloud is in metres (a depth PNG read with the wrong "
                f"depth_scale); divide it by {10.0 ** k:g}")
    if k <= -3:
        return (f"{name} looks like metres divided by {10.0 ** -k:g} once too often, or the cloud is in "
                "millimetres; both must be in metres")
    return f"they differ by a factor ~{10.0 ** k:g}: one of them is in other units than metres"


# The image's true depth lifted with T_cam_pc must land on the cloud. Below SUSPECT_ON of its pixels
# within ON_CLOUD spacings, a cause is a fault when it lands at least ALT_ON and clearly more
# (ALT_GAIN x, or twice and 25 points more); with none, when the cloud seen with T_cam_pc covers
# COVER_ON of the pixels and agrees with depth_gt at under AGREE_MIN (another view's pose or depth:
# 26-52 % on ICL, good pairs 90-98 %, landing 50-95 %; the good synthetic test pair k = 60: 57 %).
ON_CLOUD, FEW_ON, ALT_ON, ALT_GAIN = 3.0, 0.1, 0.2, 3.0
SUSPECT_ON, COVER_ON, AGREE_MIN, SEEN_BLOCK = 0.5, 0.5, 0.55, 4
DEPTH_FAULTS = ((2.0, "depth_gt is half the truth: 2 mm PNG units read as millimetres? (doubled, it lands)"),
                (0.5, "depth_gt is twice the truth: a depth_scale half too small? (halved, it lands)"),
                (1 / 3, "depth_gt is 3 x the truth (divided by 3, it lands)"),
                (3.0, "depth_gt is a third of the truth (x3, it lands)"),
                (0.2, "depth_gt is 5 x the truth: 0.2 mm PNG units read as millimetres? (divided by 5, it lands)"),
                (0.1, "depth_gt is 10 x the truth: a depth_scale ten times too small? (divided by 10, it lands)"),
                (10.0, "depth_gt is a tenth of the truth: a depth_scale ten times too large? (x10, it lands)"))
_CONSISTENT: dict = {}  # pairs already found consistent, by a fingerprint (validate runs per candidate camera)


def geometry_fault(pair: "Pair", max_points: int = 50_000, max_pixels: int = 3000) -> str:
    """``""`` when ``pair.depth_gt`` lifted with ``pair.T_cam_pc`` lands on ``pair.points`` (its pixels
    within ``ON_CLOUD`` x the cloud's spacing of a point), or when nothing explains why not; else one
    line naming the cause and the numbers compared: an inverted pose, a transposed rotation, a depth
    in other units (the standard factors, or the median ratio of the cloud's depth seen with
    ``T_cam_pc`` to ``depth_gt``: x1.2, x4 ...), or another view's pose or depth (a mirrored depth).
    It cannot tell a fault the pair's own data reproduce (a cloud back-projected from the same
    wrongly scaled depth PNG, the 3DMatch layout), a nearby view's pose that still sees the same
    surfaces, a depth off by a few per cent, nor a pair whose image sees little of the cloud."""
    D = np.asarray(pair.depth_gt, dtype=np.float64)
    T = np.asarray(pair.T_cam_pc, dtype=np.float64)
    pts = np.asarray(pair.points, dtype=np.float64)
    key = (pts.shape, float(pts[0].sum() + pts[-1].sum()), D.shape, float(np.nansum(D[:: 7, :: 7])), T.tobytes(),
           np.asarray(pair.K_image, dtype=np.float64).tobytes())
    if key in _CONSISTENT:
        return ""
    v, u = np.nonzero(np.isfinite(D) & (D > 0))
    if len(v) < 50:
        return ""
    pick = np.linspace(0, len(v) - 1, min(max_pixels, len(v))).astype(np.int64)
    uv, z = np.stack([u[pick], v[pick]], axis=1).astype(np.float64), D[v[pick], u[pick]]
    cloud = pts[:: max(1, len(pts) // max_points)]
    tree = cKDTree(cloud)
    spacing = max(float(np.median(tree.query(cloud[:: max(1, len(cloud) // 2000)], k=2)[0][:, 1])), 1e-9)

    def landing(T_cam_pc, factor=1.0):  # a bounded search: far pixels cost most, and only the share is needed
        p = cameras.transform(cameras.invert(T_cam_pc), cameras.lift(uv, z * factor, pair.K_image))
        return float(np.mean(tree.query(p, distance_upper_bound=1.01 * ON_CLOUD * spacing)[0] <= ON_CLOUD * spacing)), p

    def consistent() -> str:
        if len(_CONSISTENT) > 256:
            _CONSISTENT.clear()
        _CONSISTENT[key] = True
        return ""

    on, p0 = landing(T)
    if on >= SUSPECT_ON:
        return consistent()
    transposed = np.block([[T[:3, :3].T, T[:3, 3:]], [T[3:, :3], T[3:, 3:]]])
    alts = [("T_cam_pc looks inverted (its inverse lands it: T_pc_cam given for T_cam_pc?)", landing(cameras.invert(T))),
            ("T_cam_pc's rotation looks transposed (R.T with the same translation lands it)", landing(transposed))]
    alts += [(why, landing(T, f)) for f, why in DEPTH_FAULTS]
    # The cloud's nearest depth per SEEN_BLOCK-pixel block (a subsampled cloud leaves most pixels empty).
    (H, W), b = D.shape, SEEN_BLOCK
    uvc, zc = cameras.project(cameras.transform(T, cloud), pair.K_image)
    with np.errstate(invalid="ignore"):
        ok = (zc > 1e-6) & (uvc[:, 0] >= 0) & (uvc[:, 0] < W) & (uvc[:, 1] >= 0) & (uvc[:, 1] < H)
    near = np.full(-(-H // b) * -(-W // b), np.inf)
    np.minimum.at(near, (uvc[ok, 1] // b).astype(np.int64) * -(-W // b) + (uvc[ok, 0] // b).astype(np.int64), zc[ok])
    seen = np.where(np.isfinite(near), near, 0.0)[(v[pick] // b) * -(-W // b) + u[pick] // b]
    both = seen > 0
    cover = float(np.mean(both))
    if both.sum() >= 50:
        ratio = float(np.median(seen[both] / z[both]))  # what depth_gt must be multiplied by
        standard = any(abs(np.log(ratio / f)) < 0.05 for f, _ in DEPTH_FAULTS)
        if abs(np.log(ratio)) > 0.05 and not standard and np.isfinite(ratio):
            alts.append((f"depth_gt is {1 / ratio:.2g} x the truth (x{ratio:.3g}, the median ratio of the cloud's "
                         f"depth seen with T_cam_pc to it, it lands)", landing(T, ratio)))
    why, (alt_on, alt_p) = max(alts, key=lambda a: a[1][0])
    head = (f"depth_gt lifted with T_cam_pc does not land on the point cloud: {on:.1%} of its pixels within "
            f"{ON_CLOUD:g} x the cloud's spacing {spacing:.3g} m of a point (median distance {np.median(tree.query(p0)[0]):.3g} m)")
    if alt_on >= max(ALT_ON, min(ALT_GAIN * on, on + max(0.25, on))):
        return f"{head}; {why}: then {alt_on:.1%} (median {np.median(tree.query(alt_p)[0]):.3g} m)"
    agree = float(np.mean(np.abs(seen[both] / z[both] - 1) < 0.1)) if both.any() else 1.0
    if cover >= COVER_ON and agree < AGREE_MIN:
        return (f"{head}; T_cam_pc puts the cloud in front of {cover:.0%} of them and its depth agrees with "
                f"depth_gt (within 10 %) at only {agree:.0%} of those (a consistent pair: 90 % or more): depth_gt "
                "or T_cam_pc looks like another view's (another pair's pose or depth, or a mirrored depth map)")
    return consistent()


class UnreadablePair:
    """Stands in for a pair whose files could not be read, so a benchmark goes on.

    Loaders yield it (see :func:`load_or_record`) instead of raising in the middle of a run;
    ``name`` and ``error`` are set, and :meth:`Pair.validate` or any other field re-raises the
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
