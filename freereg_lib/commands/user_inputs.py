"""The ``freereg register`` command's inputs: a user's own files as a :class:`~freereg_lib.data.pair.Pair`: reading and checking them.

:func:`load_inputs` reads an image and a point cloud (with the intrinsics, optional depth
sensor pose, depth PNG and ground-truth pose) and :func:`load_demo` the official demo layout;
each refuses bad input with one :class:`~freereg_lib.pipeline.register.InputError` line
that names the file or flag and what was expected.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from freereg_lib.data.datasets.common import INVALID_DEPTH, read_depth, read_points, read_pose_txt, read_rgb
from freereg_lib.data.datasets.demo import DEMO_CAMERAS, load_demo_pair, read_cameras
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras
from freereg_lib.commands import inputs_check as IC
from freereg_lib.commands.process_io import nearest_existing, write_fault
from freereg_lib.pipeline.register import InputError, _one_line

# Largest plausible extent (bounding-box diagonal, m) of a cloud: beyond, it looks like millimetres.
MAX_EXTENT_M = {False: 200.0, True: 20_000.0}  # indoor, outdoor


def read_intrinsics(path: str | Path) -> np.ndarray:
    """``K (3, 3)`` from a file: a 3 x 3 text matrix, four numbers ``fx fy cx cy``, or JSON with
    ``fx, fy, cx, cy`` (the ICL sample's ``intrinsics.json``), ``K`` / ``intrinsic_matrix``
    (3 x 3) or the official demo's ``rgb_intrinsic``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing intrinsics file: {path}")
    text = path.read_text(errors="replace")
    try:
        if path.suffix.lower() == ".json":
            d = json.loads(text)
            if all(k in d for k in ("fx", "fy", "cx", "cy")):
                return cameras.intrinsics(d["fx"], d["fy"], d["cx"], d["cy"])
            for key in ("K", "intrinsic_matrix", "rgb_intrinsic"):
                if key in d:
                    K = np.asarray(d[key], dtype=np.float64)
                    return K.reshape(3, 3).T if key == "intrinsic_matrix" else K.reshape(3, 3)  # Open3D: column-major
            raise InputError(f"{path}: no intrinsics found; expected the keys fx, fy, cx, cy (pixels), "
                             "or K (3 x 3), or rgb_intrinsic")
        vals = np.asarray(text.replace(",", " ").split(), dtype=np.float64)
    except (ValueError, TypeError, AttributeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"cannot read intrinsics from {path}: expected fx fy cx cy, a 3 x 3 matrix or JSON "
                         f"({str(exc).splitlines()[0]})") from None
    if vals.size == 4:
        return cameras.intrinsics(*vals)
    if vals.size == 9:
        return vals.reshape(3, 3)
    raise InputError(f"{path} holds {vals.size} numbers; expected 4 (fx fy cx cy) or 9 (a 3 x 3 matrix)")


def output_fault(out: Path) -> str:
    """Why the outputs cannot be written into the folder ``out`` ("" when they can): its nearest
    existing folder refuses a file (a read-only mount, ``/proc``). Checked before the registration
    runs, which takes minutes on a CPU; the outputs were lost after it."""
    if not nearest_existing(Path(out)).is_dir():
        return ""  # a file in the way: the caller names it
    why = write_fault(Path(out))
    return f"{out}: {why}; give --out a folder you can write" if why else ""


def failure_hint(pair: Pair, scale: float | None, K_flag: str, depth_flag: str | None) -> str:
    """The line ``freereg register`` prints under a FAILED result: the inputs that fail this way when
    they are wrong, the intrinsics first (named with the field of view they give), and what a Kabsch
    similarity's ``scale`` far from 1 says (the image side ``1 / scale`` times too near or far: a
    focal length or a depth unit off by that factor)."""
    H, W = pair.image_size
    fx, fy = float(pair.K_image[0, 0]), float(pair.K_image[1, 1])
    fov = (2 * np.degrees(np.arctan(W / (2 * fx))), 2 * np.degrees(np.arctan(H / (2 * fy))))
    line = (f"check: the intrinsics {K_flag} (fx {fx:.1f}, fy {fy:.1f}: a {fov[0]:.0f} x {fov[1]:.0f} deg field of view "
            f"for {W} x {H})" + (f" and the depth units {depth_flag}" if depth_flag else "")
            + ": a wrong focal length or depth unit fails this way")
    holes = 0.0 if pair.depth_gt is None else float(np.mean(~(np.asarray(pair.depth_gt) > 0)))
    if holes > 0.05:
        line += (f"; the image depth has none at {100 * holes:.0f} % of its pixels (0 or 65535): with --backend "
                 "stub, whose monocular depth is made from it, their keypoints get no 3D point and no match")
    if scale is not None and np.isfinite(scale) and scale > 0 and not 0.8 <= scale <= 1.25:
        factor = 1 / scale if scale < 1 else scale
        line += (f"; the scale {scale:.2f} makes the image side {factor:.1f}x {'smaller' if scale < 1 else 'larger'} "
                 "than the cloud: a focal length or a depth unit off by about that factor")
    return line


def _invalid_depth_note(path) -> str:
    """A line counting the pixels of the depth PNG ``path`` that hold 65535, a depth sensor's "no
    reading" (read as no depth, as 0 is; the official depth masks, (0.01, 10) m indoors, drop the
    65.535 m it would read as), or "" when none does."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    n = int(np.count_nonzero(raw == INVALID_DEPTH)) if raw is not None else 0
    return (f"--image-depth {path}: {n} of {raw.size} pixels ({100 * n / raw.size:.2g} %) hold {INVALID_DEPTH}, a "
            "depth sensor's 'no reading': read as no depth, as 0 is" if n else "")


def read_pose(path: str | Path | None, what: str) -> np.ndarray | None:
    """A 4 x 4 rigid pose from a text file (``identity`` gives the identity), checked."""
    if path is None:
        return None
    if str(path).lower() == "identity":
        return np.eye(4)

    try:
        return read_pose_txt(path)
    except (OSError, ValueError) as exc:
        raise InputError(f"{what}: {_one_line(exc)}") from None


def check_cloud_units(points: np.ndarray, outdoor: bool = False, where: str = "the point cloud") -> None:
    """Refuse a cloud whose extent says it is not in metres (millimetres, most often)."""
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)
    extent = float(np.linalg.norm(hi - lo))
    limit = MAX_EXTENT_M[bool(outdoor)]
    if extent > limit:
        raise InputError(
            f"{where} is {extent:.4g} units across (98 % of its points), more than the {limit:g} m an "
            f"{'outdoor' if outdoor else 'indoor'} scene spans: it looks like millimetres; pass --cloud-scale 0.001"
            + ("" if outdoor else " (or --outdoor for a large outdoor map)"))


def load_inputs(
    image: str | Path,
    cloud: str | Path,
    K: np.ndarray | list | None,
    depth_K: np.ndarray | list | None = None,
    depth_size: tuple[int, int] | None = None,
    depth_pose: np.ndarray | None = None,
    gt_T_cam_pc: np.ndarray | None = None,
    image_depth: str | Path | None = None,
    depth_scale: float = 1000.0,
    cloud_scale: float = 1.0,
    outdoor: bool = False,
) -> Pair:
    """The pair of an image file and a cloud file (``.ply``, ``.pcd``, ``.npy``, ``.xyz``/``.txt``/``.pts``).

    ``K``: the image intrinsics (3 x 3, or ``fx, fy, cx, cy``; pixels). The depth camera, when
    the cloud has one: ``depth_pose`` (``T_pc_sensor``, the sensor's pose in the cloud's frame;
    the identity when the cloud is in its sensor's frame), ``depth_K`` and ``depth_size`` ``(H,
    W)`` (default: the image's). Without ``depth_pose`` the pair has ``meta["depth_camera"] =
    False`` and :func:`register` places virtual cameras. ``gt_T_cam_pc`` (ground truth) and
    ``image_depth`` (the image's true depth, a 16-bit PNG of ``depth_scale`` per metre) are for
    scoring; the stub backend also makes its stand-in monocular depth from ``image_depth``.

    Every bad input raises :class:`InputError` with one line naming it.
    """

    cloud_scale = IC.positive(cloud_scale, "--cloud-scale", "the cloud's coordinates are multiplied by it")
    depth_scale = IC.positive(depth_scale, "--depth-scale", "the depth PNG's value per metre")
    img = _read(read_rgb, image, "image")  # as stored: an EXIF orientation is not applied (inputs_check)
    H, W = img.shape[:2]
    if K is None:
        raise InputError("missing image intrinsics: give --K fx fy cx cy (pixels) or --intrinsics FILE")
    try:
        K_raw = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        K_raw = np.zeros(0)  # _as_K names it
    if K_raw.size in (4, 9):  # the order first: a swapped cx, cy may also fall outside the image
        IC.principal_point_order(cameras.intrinsics(*K_raw.ravel()) if K_raw.size == 4 else K_raw.reshape(3, 3),
                                 (H, W), "--K")
    K_img = _as_K(K, (H, W), f"the image intrinsics K for {Path(image).name} ({W} x {H})")
    pts = _read(_read_cloud, cloud, "point cloud")
    IC.float32_precision(pts, f"the point cloud {cloud}")
    if cloud_scale != 1.0:
        pts = pts * float(cloud_scale)
    check_cloud_units(pts, outdoor, f"the point cloud {cloud}")
    has_camera = depth_pose is not None
    if depth_K is not None and depth_size is None:
        raise InputError("--depth-K needs --depth-size W H (the depth camera's image size)")
    if depth_size is not None:
        IC.depth_size_fits((H, W), depth_size, depth_K)
    size = tuple(int(v) for v in depth_size) if depth_size is not None else (H, W)
    K_dep = _as_K(depth_K, size, "the depth camera intrinsics (--depth-K)") if depth_K is not None else K_img.copy()
    if depth_K is None and depth_size is not None:
        K_dep = cameras.scale_intrinsics(K_img, size[1] / W, size[0] / H)
    depth_gt, invalid_note = None, ""
    if image_depth is not None:
        depth_gt = _read(lambda p: read_depth(p, depth_scale, INVALID_DEPTH, (0.05, 200.0) if outdoor else (0.1, 20.0)),
                         image_depth, "image depth")
        if depth_gt.shape != (H, W):
            raise InputError(f"{image_depth} is {depth_gt.shape[1]} x {depth_gt.shape[0]}; the image is {W} x {H}")
        invalid_note = _invalid_depth_note(image_depth)
    has_gt = gt_T_cam_pc is not None
    if has_camera:
        IC.pose_sees_cloud(cameras.invert(np.asarray(depth_pose, dtype=np.float64)), pts, K_dep, size,
                           "--depth-pose (the sensor's pose in the cloud's frame, T_pc_sensor)",
                           "T_sensor_pc (its inverse) as --depth-pose")
    if has_gt:
        IC.pose_sees_cloud(np.asarray(gt_T_cam_pc, dtype=np.float64), pts, K_img, (H, W),
                           "the ground-truth pose (as T_cam_pc)", "--gt-T-cam-pc for --gt-T-pc-cam, or the reverse")
        if depth_gt is not None:
            IC.depth_units_against_cloud(depth_gt, pts, K_img, np.asarray(gt_T_cam_pc, dtype=np.float64),
                                         depth_scale, f"--image-depth {image_depth}")
    if gt_T_cam_pc is None:  # a placeholder the pair needs: the camera at the cloud's centre
        gt_T_cam_pc = cameras.make_pose(np.eye(3), -np.median(pts, axis=0))
    # The checks above read the files as given; the models get square pixels (inputs_check). A
    # depth camera that is the image's own (no --depth-K, no --depth-size) is resampled with it.
    img, K_sq, depth_gt, square_note = IC.square_pixels(img, K_img, depth_gt, "--K / --intrinsics")
    if depth_K is None and depth_size is None:
        K_dep, size = K_sq.copy(), tuple(img.shape[:2])
    K_img = K_sq
    pair = Pair(
        image=img, K_image=K_img, points=pts, K_depth=K_dep, depth_size=size,
        T_pc_sensor=np.asarray(depth_pose, dtype=np.float64) if has_camera else np.eye(4),
        T_cam_pc=np.asarray(gt_T_cam_pc, dtype=np.float64), depth_gt=depth_gt,
        name=f"{Path(image).stem}-{Path(cloud).stem}",
        meta={"dataset": "files", "outdoor": bool(outdoor), "depth_camera": has_camera, "has_gt": has_gt,
              "image_path": str(image), "cloud_path": str(cloud),
              "notes": [n for n in [IC.exif_note(image), square_note, invalid_note] if n],
              **({"resampled_from": (H, W)} if square_note else {})},
    )
    try:
        pair.validate()
    except ValueError as exc:
        raise InputError(_one_line(exc)) from None
    return pair


def load_demo(root: str | Path) -> Pair:
    """The official demo layout (:mod:`freereg_lib.data.datasets.demo`) with its depth camera (the
    identity: the cloud is in its sensor's frame) and its ground truth."""

    try:
        pair = load_demo_pair(root)
    except (OSError, ValueError) as exc:
        raise InputError(_one_line(exc)) from None

    IC.pose_sees_cloud(pair.T_cam_pc, pair.points, pair.K_image, pair.image_size,
                       f"{Path(root) / 'just_for_eval' / 'rgb2pc.gt.pose.txt'} (inverted, as T_cam_pc)",
                       "T_cam_pc where the demo layout wants the RGB camera's pose in the cloud's frame")
    if pair.depth_gt is not None:

        intr = Path(root) / "intrinsics.json"
        scale = float((read_cameras(intr) if intr.is_file() else DEMO_CAMERAS)["dpt_scale"])
        IC.depth_units_against_cloud(pair.depth_gt, pair.points, pair.K_image, pair.T_cam_pc, scale,
                                     str(Path(root) / "just_for_eval" / "source_rgb.gtd.png"),
                                     f"dpt_scale (in {intr.name})")
    image_path = Path(root) / "source_rgb.png"
    pair.meta.update(depth_camera=True, has_gt=True, image_path=str(image_path),
                     cloud_path=str(Path(root) / "target_pc.ply"), notes=[n for n in [IC.exif_note(image_path)] if n])
    return pair


def _read(reader: Callable, path, what: str):
    try:
        return reader(path)
    except FileNotFoundError:
        raise InputError(f"missing {what} file: {path}") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the {what} {path}: {_one_line(exc)}") from None


def _read_cloud(path) -> np.ndarray:
    """``.pcd`` through Open3D (checked), everything else through ``datasets.common.read_points``."""


    path = Path(path)
    if path.suffix.lower() != ".pcd":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # dropped NaN points: the count is not worth a traceback
            return read_points(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    import open3d as o3d

    head = path.read_bytes()[:2048]
    if b"DATA" not in head or b"POINTS" not in head:
        raise ValueError("not a PCD file (no POINTS / DATA header)")
    pts = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise ValueError("it holds no point (an empty point cloud)")
    return pts


def _as_K(K, size, name: str) -> np.ndarray:
    arr = np.asarray(K, dtype=np.float64)
    if arr.size == 4:
        arr = cameras.intrinsics(*arr.ravel())
    try:
        return cameras.check_intrinsics(arr.reshape(3, 3) if arr.size == 9 else arr, size, name)
    except ValueError as exc:
        raise InputError(_one_line(exc)) from None
