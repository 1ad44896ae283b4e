"""Register your own image to your own point cloud: the front door (issue 18).

::

    freereg register IMAGE CLOUD --K fx fy cx cy [--depth-K ... --depth-size W H --depth-pose FILE]
    freereg register --demo FOLDER            # the official demo layout (data/demo/)

or, as functions: :func:`load_inputs` (files -> a :class:`~freereg_lib.pair.Pair`),
:func:`register` (a pair -> a :class:`Registration`), :func:`write_outputs`.

Conventions (the README's "Your own data"):

* ``T_cam_pc`` maps points of the cloud's frame into the image camera (``x_cam = R x_pc + t``);
  its inverse ``T_pc_cam`` is **the pose of the camera in the cloud's frame** (where the camera
  is and where it looks, in the cloud's coordinates). The official demo's
  ``rgb2pc.gt.pose.txt`` is a ``T_pc_cam``.
* The cloud is in metres. Kabsch-RANSAC estimates a similarity (monocular depth has a scale
  error); the pose written is its rigid part, the scale is reported.

**The depth camera.** FreeReg compares the image with the cloud *rendered as a depth map* on a
depth camera. A cloud that came from a depth sensor is rendered from that sensor (the paper's
setting; the official demo's cloud is in its sensor's frame, so that camera is the identity).
A cloud with no sensor (a map, a LiDAR scan, a reconstruction) gets **virtual** depth cameras
(:func:`virtual_cameras`): the origin of the cloud's frame when the cloud lies in front of it,
a rough pose of the image camera when one is given, and a ring of views around the cloud's
vertical axis, from its centre and from behind it. Each candidate runs the whole chain and the
one whose pose has the most RANSAC inliers (with a plausible scale) is kept: no ground truth is
used. The kept pose is then *refined*: the cloud is rendered again from the estimated camera
pose (the view that best resembles the image) and registered once more; the refined pose
replaces the first when it has more inliers.

**Registered or not.** Without ground truth nobody can say for sure; the verdict is a
plausibility check: the solver found a pose, with at least ``min_inliers`` inliers making up
at least ``min_inlier_ratio`` of the matches, and (Kabsch) a scale within
``[1 / max_scale, max_scale]``. With a ground-truth pose the rotation / translation errors and
the paper's (20 deg, 0.5 m) verdict are printed as well.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import cameras, metrics, pipeline
from .config import FreeRegConfig, config_for
from .pair import Pair

# Thresholds of the plausibility verdict (no ground truth; the module docstring), per solver,
# measured on real frames (python -m freereg_lib.verdict_measure; docs/your_data.md): no pose
# within (5 deg, 0.1 m) of the truth may be called FAILED. PnP-RANSAC's inliers (10 px) are
# fewer than Kabsch's (0.2 m): right PnP poses came with 12 inliers (7 %), Kabsch's with 24.
MIN_INLIERS = {"kabsch": 22, "pnp": 12}
MIN_INLIER_RATIO = {"kabsch": 0.15, "pnp": 0.07}
MAX_SCALE = 1.3  # Kabsch's similarity: wrong poses on real frames came with scales 1.33 and 0.73


def verdict_thresholds(solver: str, min_inliers=None, min_ratio=None, max_scale=None) -> tuple[int, float, float]:
    """``(min_inliers, min_inlier_ratio, max_scale)`` of the verdict for ``solver``: the values
    given, else the module's, which are per solver (PnP's inliers are within 10 px, Kabsch's
    within 0.2 m: their counts differ)."""
    return (MIN_INLIERS[solver] if min_inliers is None else int(min_inliers),
            MIN_INLIER_RATIO[solver] if min_ratio is None else float(min_ratio),
            MAX_SCALE if max_scale is None else float(max_scale))


# Largest plausible extent (bounding-box diagonal, m) of a cloud: beyond, it looks like millimetres.
MAX_EXTENT_M = {False: 200.0, True: 20_000.0}  # indoor, outdoor
VIRTUAL_MAX_WIDTH = 640  # virtual depth cameras render at most this wide (the image's intrinsics, scaled)


from .inputs_check import InputError  # noqa: E402,F401 - defined with the checks that raise it


@dataclass
class DepthCamera:
    """A depth camera to render the cloud on: intrinsics ``K``, ``size = (H, W)``, its pose
    ``T_pc_sensor`` in the cloud's frame; ``name`` and ``why`` say where it came from."""

    name: str
    K: np.ndarray
    size: tuple[int, int]
    T_pc_sensor: np.ndarray
    why: str = ""
    virtual: bool = True


@dataclass
class Registration:
    """What :func:`register` found. ``T_cam_pc`` maps the cloud into the image camera;
    ``T_pc_cam`` (its inverse) is the camera's pose in the cloud's frame."""

    T_cam_pc: np.ndarray
    registered: bool
    result: str  # the one-line verdict
    method: str
    solver: str
    backend: str
    n_matches: int
    n_inliers: int
    scale: float
    camera: DepthCamera
    candidates: list[dict]
    pair: Pair
    feats: pipeline.PairFeatures | None = None
    matches: pipeline.Matches | None = None
    pose: object = None
    errors: dict = field(default_factory=dict)  # RE, TE (and IR, IN with the image's true depth)
    seconds: float = 0.0

    @property
    def T_pc_cam(self) -> np.ndarray:
        return cameras.invert(self.T_cam_pc)

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / self.n_matches if self.n_matches else 0.0


# --------------------------------------------------------------------------------------
# Reading the inputs.

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


def read_pose(path: str | Path | None, what: str) -> np.ndarray | None:
    """A 4 x 4 rigid pose from a text file (``identity`` gives the identity), checked."""
    if path is None:
        return None
    if str(path).lower() == "identity":
        return np.eye(4)
    from .datasets.common import read_pose_txt

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
    from . import inputs_check as IC
    from .datasets.common import read_depth, read_points, read_rgb

    cloud_scale = IC.positive(cloud_scale, "--cloud-scale", "the cloud's coordinates are multiplied by it")
    depth_scale = IC.positive(depth_scale, "--depth-scale", "the depth PNG's value per metre")
    img = _read(read_rgb, image, "image")  # as stored: an EXIF orientation is not applied (inputs_check)
    H, W = img.shape[:2]
    if K is None:
        raise InputError("missing image intrinsics: give --K fx fy cx cy (pixels) or --intrinsics FILE")
    K_img = _as_K(K, (H, W), f"the image intrinsics K for {Path(image).name} ({W} x {H})")
    pts = _read(_read_cloud, cloud, "point cloud")
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
    depth_gt = None
    if image_depth is not None:
        depth_gt = _read(lambda p: read_depth(p, depth_scale, 65535, (0.05, 200.0) if outdoor else (0.1, 20.0)),
                         image_depth, "image depth")
        if depth_gt.shape != (H, W):
            raise InputError(f"{image_depth} is {depth_gt.shape[1]} x {depth_gt.shape[0]}; the image is {W} x {H}")
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
    pair = Pair(
        image=img, K_image=K_img, points=pts, K_depth=K_dep, depth_size=size,
        T_pc_sensor=np.asarray(depth_pose, dtype=np.float64) if has_camera else np.eye(4),
        T_cam_pc=np.asarray(gt_T_cam_pc, dtype=np.float64), depth_gt=depth_gt,
        name=f"{Path(image).stem}-{Path(cloud).stem}",
        meta={"dataset": "files", "outdoor": bool(outdoor), "depth_camera": has_camera, "has_gt": has_gt,
              "image_path": str(image), "cloud_path": str(cloud), "notes": [n for n in [IC.exif_note(image)] if n]},
    )
    try:
        pair.validate()
    except ValueError as exc:
        raise InputError(_one_line(exc)) from None
    return pair


def load_demo(root: str | Path) -> Pair:
    """The official demo layout (:mod:`freereg_lib.datasets.demo`) with its depth camera (the
    identity: the cloud is in its sensor's frame) and its ground truth."""
    from .datasets.demo import load_demo_pair

    try:
        pair = load_demo_pair(root)
    except (OSError, ValueError) as exc:
        raise InputError(_one_line(exc)) from None
    from . import inputs_check as IC

    IC.pose_sees_cloud(pair.T_cam_pc, pair.points, pair.K_image, pair.image_size,
                       f"{Path(root) / 'just_for_eval' / 'rgb2pc.gt.pose.txt'} (inverted, as T_cam_pc)",
                       "T_cam_pc where the demo layout wants the RGB camera's pose in the cloud's frame")
    if pair.depth_gt is not None:
        from .datasets.demo import DEMO_CAMERAS, read_cameras

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
    import warnings

    from .datasets.common import read_points

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


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


# --------------------------------------------------------------------------------------
# Virtual depth cameras.

def up_axis(points: np.ndarray) -> tuple[np.ndarray, str]:
    """The cloud's "up": its thinnest principal direction (floors, walls and ground make a cloud
    flat along the vertical), signed towards +z, -y (a camera frame's up) or +x, whichever
    coordinate axis it is nearest. Returns the unit vector and a description."""
    c = points - points.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov(c[:: max(1, len(c) // 20000)].T))
    u = vecs[:, 0]
    k = int(np.argmax(np.abs(u)))
    ref = {0: np.array([1.0, 0, 0]), 1: np.array([0, -1.0, 0]), 2: np.array([0, 0, 1.0])}[k]
    u = u if u @ ref >= 0 else -u
    name = {0: "+x", 1: "-y", 2: "+z"}[k]
    return u, f"the cloud's thinnest principal direction, nearest {name}"


def parse_up(up: str | None, points: np.ndarray) -> tuple[np.ndarray, str]:
    if up is None or up == "auto":
        return up_axis(points)
    axes = {"x": 0, "y": 1, "z": 2}
    s = up.strip().lower()
    sign = -1.0 if s.startswith("-") else 1.0
    if s.lstrip("+-") not in axes:
        raise InputError(f"--up {up!r}: expected one of x, y, z, -x, -y, -z or auto")
    v = np.zeros(3)
    v[axes[s.lstrip('+-')]] = sign
    return v, f"given ({up})"


def virtual_cameras(points: np.ndarray, K_image: np.ndarray, image_size: tuple[int, int], cfg: FreeRegConfig,
                    rough_T_pc_cam: np.ndarray | None = None, up: str | None = None, n_yaw: int = 8,
                    max_width: int = VIRTUAL_MAX_WIDTH, with_origin: bool = True) -> list[DepthCamera]:
    """Candidate depth cameras for a cloud with no sensor pose (module docstring).

    All use the image's intrinsics (scaled to at most ``max_width`` pixels wide). Candidates:
    ``origin`` (the cloud frame's origin, looking along +z, as the official demo's identity
    extrinsic) when at least 5 % of the points lie in its view; ``rough`` (the given rough
    pose of the image camera, ``T_pc_cam``); ``centre/yaw<deg>``: at the cloud's centroid
    looking horizontally (perpendicular to ``up``) every ``360 / n_yaw`` degrees; and
    ``behind/yaw<deg>``: the same directions from a point pulled back from the centroid by the
    cloud's horizontal radius of gyration, so that more of the cloud is in view.
    ``with_origin=False`` leaves ``origin`` out (a re-centred cloud's origin is no sensor's).
    """
    H, W = image_size
    s = min(1.0, max_width / W)
    K = cameras.scale_intrinsics(K_image, s, s) if s < 1 else np.asarray(K_image, dtype=np.float64).copy()
    size = (max(1, int(round(H * s))), max(1, int(round(W * s))))
    out: list[DepthCamera] = []
    pts = points[:: max(1, len(points) // 50000)]
    uv, z = cameras.project(pts, K)
    seen = (z > cfg.depth_min) & (z < cfg.depth_max)
    with np.errstate(invalid="ignore"):
        seen &= (uv[:, 0] >= 0) & (uv[:, 0] < size[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[0])
    if with_origin and seen.mean() >= 0.05:
        out.append(DepthCamera("origin", K, size, np.eye(4),
                               f"the cloud frame's origin ({seen.mean():.0%} of the points in view): the cloud "
                               "may be in its sensor's frame, as the official demo's"))
    if rough_T_pc_cam is not None:
        out.append(DepthCamera("rough", K, size, np.asarray(rough_T_pc_cam, dtype=np.float64),
                               "the rough pose of the image camera you gave"))
    u, how = parse_up(up, points)
    c = points.mean(axis=0)
    # Two horizontal axes: the cloud's main horizontal spread first.
    cen = pts - c
    flat = cen - np.outer(cen @ u, u)
    evals, vecs = np.linalg.eigh(np.cov(flat.T))
    a1 = vecs[:, 2] - (vecs[:, 2] @ u) * u
    a1 /= np.linalg.norm(a1)
    a2 = np.cross(u, a1)
    radius = float(np.sqrt(max(evals[1] + evals[2], 1e-12)))
    for where, back in (("centre", 0.0), ("behind", radius)):
        for k in range(n_yaw):
            ang = 2 * np.pi * k / n_yaw
            d = np.cos(ang) * a1 + np.sin(ang) * a2
            eye = c - back * d
            T = cameras.look_at(eye, eye + d, up=u)
            out.append(DepthCamera(f"{where}/yaw{round(np.degrees(ang)):d}", K, size, T,
                                   f"{'at' if back == 0 else f'{back:.2f} m behind'} the cloud's centroid, looking "
                                   f"horizontally at yaw {np.degrees(ang):.0f} deg (up: {how})"))
    return out


# --------------------------------------------------------------------------------------
# Registration.

def choose_method(backend, pair: Pair, method: str | None) -> tuple[str, str]:
    """The method to run and why: the stub makes diffusion features only for synthetic scenes
    (class ids), so on other data it runs FreeReg-G (geometric only)."""
    stub_blind = getattr(backend, "uses_scene_hints", False) and pair.image_ids is None
    if method is None:
        if stub_blind:
            return "FreeReg-G", ("the stub backend has diffusion features only for synthetic scenes: FreeReg-G "
                                 "(geometric features on monocular depth and on the cloud)")
        return "FreeReg", "FreeReg (diffusion + geometric features, w = 0.5)"
    from .baseline import METHOD as BASELINE

    if method not in pipeline.METHODS or method == BASELINE:  # the baseline is for benchmarks, not a registration
        raise InputError(f"unknown method {method!r}; expected one of {[m for m in pipeline.METHODS if m != BASELINE]}")
    if stub_blind and method != "FreeReg-G":
        raise InputError(f"the stub backend cannot run {method} on real images (its diffusion features need a "
                         "synthetic scene's class ids): use --method FreeReg-G, or --backend tiny / real")
    return method, method


def register(
    pair: Pair,
    backend,
    cfg: FreeRegConfig | None = None,
    method: str | None = None,
    solver: str = "kabsch",
    depth_cameras: list[DepthCamera] | str | None = None,
    refine: bool = True,
    rough_T_pc_cam: np.ndarray | None = None,
    up: str | None = None,
    n_yaw: int = 8,
    min_inliers: int | None = None,
    min_inlier_ratio: float | None = None,
    max_scale: float | None = None,
    log: Callable[[str], None] | None = print,
) -> Registration:
    """Register ``pair.image`` to ``pair.points``; returns a :class:`Registration`.

    ``backend``: a backend object or its name (``"stub"``, ``"tiny"``, ``"real"``).
    ``depth_cameras``: ``None`` uses the pair's own depth camera when it has one
    (``pair.meta["depth_camera"]``, true for dataset pairs) and virtual cameras otherwise;
    ``"virtual"`` forces the virtual ones (:func:`virtual_cameras`); or a list of
    :class:`DepthCamera`. With several candidates each one runs the chain and the best score
    (inliers of a pose with a plausible scale) wins; ``refine`` then renders the cloud from
    the estimated camera pose and registers again. ``log`` receives the progress lines.
    """
    import time

    from .backends import get_backend

    from . import inputs_check as IC

    say = log or (lambda s: None)
    t0 = time.perf_counter()
    if int(n_yaw) < 1:
        raise InputError(f"--views must be >= 1 (virtual camera directions around the up axis), got {n_yaw}")
    for note in pair.meta.get("notes", []):
        say(note)
    # A cloud far from its frame's origin (UTM coordinates) is solved in re-centred coordinates
    # and the pose restored after: a numerical safeguard (PnP loses degrees at 5,000 km).
    offset = IC.recentre_offset(pair.points)
    original = pair
    if offset is not None:
        say(f"the cloud lies {np.linalg.norm(offset):.4g} m from its frame's origin: solving in coordinates "
            f"re-centred on ({', '.join(f'{v:.0f}' for v in offset)}), the pose restored after")
        pair = dataclasses.replace(pair, points=pair.points - offset, T_pc_sensor=IC.shift_frame(pair.T_pc_sensor,
                                   offset), T_cam_pc=IC.shift_pose(pair.T_cam_pc, offset))
        if rough_T_pc_cam is not None:
            rough_T_pc_cam = IC.shift_frame(rough_T_pc_cam, offset)
        if isinstance(depth_cameras, (list, tuple)):
            depth_cameras = [dataclasses.replace(c, T_pc_sensor=IC.shift_frame(c.T_pc_sensor, offset))
                             for c in depth_cameras]
    cfg = cfg or config_for("demo")
    if isinstance(backend, str):
        backend = get_backend(backend, cfg)
    method, why_method = choose_method(backend, pair, method)
    if solver not in ("kabsch", "pnp"):
        raise InputError(f"unknown solver {solver!r}; expected kabsch or pnp")
    min_inliers, min_inlier_ratio, max_scale = verdict_thresholds(solver, min_inliers, min_inlier_ratio, max_scale)
    w = pipeline._weight(method, cfg)
    diffusion, geometric = w > 0, w < 1
    if getattr(backend, "name", "") == "stub" and pair.depth_gt is None:
        raise InputError("the stub backend makes its stand-in monocular depth from the image's true depth: give "
                         "--image-depth FILE, or use --backend tiny / real (ZoeDepth)")
    say(f"backend: {getattr(backend, 'label', backend)}")
    say(f"method: {why_method}; solver: {solver} (RANSAC iterations {cfg.ransac_iters}"
        + (f", Kabsch scoring {cfg.kabsch_scoring!r}" if solver == "kabsch" else "") + ")")

    if depth_cameras is None:
        depth_cameras = "given" if pair.meta.get("depth_camera", True) else "virtual"
    if depth_cameras == "given":
        cands = [DepthCamera("given", np.asarray(pair.K_depth), tuple(pair.depth_size), pair.T_pc_sensor,
                             "the cloud's own depth camera (its sensor pose)", virtual=False)]
    elif depth_cameras == "virtual":
        cands = virtual_cameras(pair.points, pair.K_image, pair.image_size, cfg, rough_T_pc_cam, up, n_yaw,
                                with_origin=offset is None)
        say(f"no depth camera given: trying {len(cands)} virtual depth cameras, keeping the one whose pose has "
            "the most RANSAC inliers")
    else:
        cands = list(depth_cameras)

    mono = np.asarray(backend.mono_depth(pair.image, depth_gt=pair.depth_gt), dtype=np.float64)
    maps_img = None
    runs: list[dict] = []

    def attempt(cam: DepthCamera) -> dict:
        nonlocal maps_img
        q = dataclasses.replace(pair, K_depth=cam.K, depth_size=tuple(cam.size), T_pc_sensor=cam.T_pc_sensor,
                                sensor_depth=pair.sensor_depth if not cam.virtual else None)
        row = {"camera": cam.name, "points_in_view": 0, "matches": 0, "inliers": 0, "scale": math.nan,
               "score": 0, "note": "", "_cam": cam}
        try:
            view = pipeline.depth_view(q, cfg)
            row["points_in_view"] = int(np.count_nonzero(view.raw))
            maps = None
            if diffusion:
                use_hints = getattr(backend, "uses_scene_hints", False)
                h_img, h_dep = pipeline.scene_hints(q, view) if use_hints else ({}, {})
                if maps_img is None:
                    maps_img = backend.diffusion_rgb_batch([q.image], [h_img], cfg.layers)[0]
                maps = (maps_img, backend.diffusion_depth_batch([view.hint_depth], [h_dep], cfg.layers)[0])
            feats = pipeline.compute_features(q, backend, cfg, diffusion, geometric, view=view, maps=maps, mono=mono)
            m = pipeline.match(feats, w, cfg.match_device)
            res = pipeline.solve(q, feats, m, cfg, solver)
        except ValueError as exc:
            row["note"] = _one_line(exc).replace(f"pair {pair.name}: ", "")[:160]
            return row
        row.update(matches=len(m), inliers=res.n_inliers, scale=res.scale, _q=q, _feats=feats, _m=m, _res=res)
        if not res.success:
            row["note"] = res.reason
        elif solver == "kabsch" and not 1 / max_scale <= res.scale <= max_scale:
            row["note"] = f"scale {res.scale:.2f} is implausible: not scored"
        else:
            row["score"] = res.n_inliers
        return row

    for cam in cands:
        runs.append(attempt(cam))
    best = max(runs, key=lambda r: r["score"]) if runs else None
    if best is not None and best["score"] == 0:  # nothing plausible: report the candidate that got furthest
        best = max(runs, key=lambda r: (r["inliers"], r["matches"]))
    if refine and len(cands) > 1 and best is not None and best.get("_res") is not None and best["_res"].success:
        cam0 = best["_cam"]
        T_est = cameras.invert(best["_res"].T_cam_pc)
        ref = attempt(DepthCamera("refined", cam0.K, cam0.size, T_est,
                                  f"at the pose estimated with {cam0.name} (the cloud seen as the image sees it)"))
        runs.append(ref)
        if ref["score"] > best["score"]:
            best = ref
    if len(runs) > 1:
        say("candidate depth cameras (score = RANSAC inliers of a pose with a plausible scale):")
        say(f"  {'camera':<16} {'points':>7} {'matches':>7} {'inliers':>7} {'scale':>6}  note")
        for r in runs:
            say(f"  {r['camera']:<16} {r['points_in_view']:>7} {r['matches']:>7} {r['inliers']:>7} "
                f"{_fmt(r['scale'], '.2f'):>6}  {'<- chosen ' if r is best else ''}{r['note']}")
    cam = best["_cam"]
    say(f"depth camera used: {cam.name}: {cam.why}")

    res = best.get("_res")
    n_m, n_in = best["matches"], best["inliers"]
    scale = float(res.scale) if res is not None else math.nan
    ok, why = _verdict(res, best, solver, min_inliers, min_inlier_ratio, max_scale)
    T = res.T_cam_pc if res is not None and res.success else np.full((4, 4), np.nan)
    q_out = best.get("_q", pair)
    if offset is not None:  # back to the cloud's own coordinates
        T = IC.unshift_pose(T, offset)
        cam = dataclasses.replace(cam, T_pc_sensor=IC.unshift_frame(cam.T_pc_sensor, offset))
        q_out = dataclasses.replace(q_out, points=original.points, T_pc_sensor=cam.T_pc_sensor,
                                    T_cam_pc=original.T_cam_pc)
    errors: dict = {}
    if pair.meta.get("has_gt", True):
        re, te = metrics.pose_errors(T, original.T_cam_pc) if res is not None and res.success else (math.nan, math.nan)
        errors = {"RE": re, "TE": te, "registered_gt": metrics.registered(re, te, cfg.rr_rot_deg, cfg.rr_trans_m)}
        if pair.depth_gt is not None and best.get("_m") is not None:
            errors.update(_inliers_gt(best["_q"], best["_feats"], best["_m"], cfg, cam.virtual))
    result = (f"{'REGISTERED' if ok else 'FAILED'}: {why}; {n_in} inliers of {n_m} matches "
              f"({(n_in / n_m if n_m else 0):.0%})" + (f", scale {scale:.2f}" if solver == "kabsch" and res is not None
                                                      and res.success else ""))
    reg = Registration(T, ok, result, method, solver, getattr(backend, "label", str(backend)), n_m, n_in, scale, cam,
                       [{k: v for k, v in r.items() if not k.startswith("_")} | {"chosen": r is best} for r in runs],
                       q_out, best.get("_feats"), best.get("_m"), res, errors,
                       time.perf_counter() - t0)
    say(result)
    if errors:
        say(f"against the ground truth: RE {_fmt(errors['RE'], '.2f')} deg, TE {_fmt(errors['TE'], '.3f')} m: "
            f"{'registered' if errors['registered_gt'] else 'not registered'} at ({cfg.rr_rot_deg:g} deg, "
            f"{cfg.rr_trans_m:g} m)" + (f"; IR {errors['IR']:.3f}, IN {errors['IN']}" if "IR" in errors else ""))
    return reg


def _inliers_gt(q: Pair, feats, m, cfg: FreeRegConfig, virtual: bool) -> dict:
    """IR / IN with the image's true depth. A sensor's depth camera: the official evaluation
    (:func:`pipeline.evaluate`). A virtual camera's raw view is the cloud's sparse projection,
    on which most keypoints have no depth, so the depth side is lifted from the densified view
    instead (the points the solver used): an approximation of the official rule."""
    if not virtual:
        sc = pipeline.evaluate(q, feats, m, pipeline.pose.PoseResult(np.eye(4), False, "none"), cfg)
        return {"IR": sc["IR"], "IN": sc["IN"]}
    correct, evaluable = metrics.correct_matches(
        feats.uv_image[m.idx_image], feats.pts_depth[m.idx_depth], q.depth_gt, q.K_image, q.T_cam_pc, cfg.tau_c,
        (cfg.depth_min, cfg.depth_max))
    ir, inn = metrics.inlier_stats(correct, evaluable)
    return {"IR": ir, "IN": inn}


def _verdict(res, row, solver, min_inliers, min_ratio, max_scale) -> tuple[bool, str]:
    if res is None:
        return False, f"no pose ({row['note']})"
    if not res.success:
        return False, f"the solver found no pose ({res.reason})"
    if solver == "kabsch" and not 1 / max_scale <= res.scale <= max_scale:
        return False, (f"the similarity's scale {res.scale:.2f} is outside [{1 / max_scale:.2g}, {max_scale:g}] "
                       "(it shrank or blew up the image side onto wrong matches)")
    ratio = res.n_inliers / row["matches"] if row["matches"] else 0.0
    if res.n_inliers < min_inliers:
        return False, f"too few inliers ({res.n_inliers} < {min_inliers})"
    if ratio < min_ratio:
        return False, f"inlier ratio {ratio:.0%} below {min_ratio:.0%}"
    return True, "a pose with enough inliers (a plausibility check, not a proof without ground truth)"


def _fmt(v, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


# --------------------------------------------------------------------------------------
# Outputs.

POSE_HEADER = {
    "T_cam_pc": "T_cam_pc: maps points of the cloud's frame into the image camera, x_cam = R x_pc + t (OpenCV camera: "
                "x right, y down, z forward)",
    "T_pc_cam": "T_pc_cam: the pose of the image camera in the cloud's frame (its inverse, T_cam_pc, maps the cloud "
                "into the camera)",
}


def overlay_image(reg: Registration, T_cam_pc: np.ndarray | None = None) -> np.ndarray:
    """The cloud projected onto the image with the estimated pose (or ``T_cam_pc``), coloured by
    depth, ``(H, W, 3)`` float RGB."""
    from . import plots, projection

    pair = reg.pair
    T = reg.T_cam_pc if T_cam_pc is None else T_cam_pc
    if not np.all(np.isfinite(T)):
        return np.asarray(pair.image, dtype=np.float64) / 255.0
    depth, _ = projection.project_to_depth(pair.points, pair.K_image, T, pair.image_size, 0.01)
    return plots.overlay_depth(pair.image, depth, alpha=0.6)


def overlay_figure(reg: Registration):
    """The image, the cloud drawn on it with the estimated pose, and with the true pose when known."""
    from . import plots

    images = [reg.pair.image, overlay_image(reg)]
    titles = ["image", f"cloud drawn with the estimated pose ({reg.result.split(':')[0]})"]
    if reg.errors:
        images.append(overlay_image(reg, reg.pair.T_cam_pc))
        titles.append(f"with the true pose (RE {_fmt(reg.errors['RE'], '.1f')} deg, TE {_fmt(reg.errors['TE'], '.2f')} m)")
    return plots.image_grid(images, titles, suptitle=f"{reg.pair.name} - {reg.backend}", cols=len(images),
                            width=6.0 * len(images))


def matches_figure(reg: Registration, max_lines: int = 200):
    """Image and depth view side by side with the matches: green the pose's inliers, red the rest."""
    from . import plots

    f, m = reg.feats, reg.matches
    if f is None or m is None:
        return None
    inl = np.zeros(len(m), dtype=bool)
    if reg.pose is not None and reg.pose.success:
        inl[np.asarray(reg.pose.inliers, dtype=np.int64)] = True
    return plots.draw_matches(
        reg.pair.image, plots.depth_image(f.view.dense), f.uv_image[m.idx_image], f.uv_depth[m.idx_depth], inl,
        title=f"{reg.method} + {reg.solver}: {len(m)} matches, {reg.n_inliers} inliers (green) - depth camera "
              f"{reg.camera.name} - {reg.backend}", max_lines=max_lines)


def write_outputs(reg: Registration, out_dir: str | Path) -> dict[str, Path]:
    """Write ``T_cam_pc.txt``, ``T_pc_cam.txt``, ``registration.json``, ``candidates.csv``,
    ``matches.png``, ``overlay.png`` into ``out_dir``; returns their paths."""
    import pandas as pd

    from . import plots

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, T in (("T_cam_pc", reg.T_cam_pc), ("T_pc_cam", reg.T_pc_cam)):
        paths[name] = out / f"{name}.txt"
        np.savetxt(paths[name], T, fmt="%.9f", header=POSE_HEADER[name] + ("" if reg.registered else
                                                                       "\nNOT REGISTERED: " + reg.result))
    cam = reg.camera
    doc = {
        "result": reg.result, "registered": reg.registered,
        "T_cam_pc": _json_matrix(reg.T_cam_pc), "T_pc_cam": _json_matrix(reg.T_pc_cam),
        "conventions": POSE_HEADER, "units": "metres (the cloud's units)",
        "method": reg.method, "solver": reg.solver, "backend": reg.backend,
        "n_matches": reg.n_matches, "n_inliers": reg.n_inliers, "inlier_ratio": reg.inlier_ratio,
        "scale": None if math.isnan(reg.scale) else reg.scale,
        "depth_camera": {"name": cam.name, "why": cam.why, "virtual": cam.virtual, "K": cam.K.tolist(),
                         "size_hw": list(cam.size), "T_pc_sensor": cam.T_pc_sensor.tolist()},
        "ground_truth": {k: (bool(v) if isinstance(v, (bool, np.bool_)) else (None if math.isnan(float(v)) else float(v)))
                         for k, v in reg.errors.items()},
        "seconds": reg.seconds,
        "inputs": {k: reg.pair.meta.get(k) for k in ("image_path", "cloud_path")},
    }
    paths["json"] = out / "registration.json"
    paths["json"].write_text(json.dumps(doc, indent=2) + "\n")
    paths["candidates"] = out / "candidates.csv"
    pd.DataFrame(reg.candidates).to_csv(paths["candidates"], index=False)
    fig = matches_figure(reg)
    if fig is not None:
        paths["matches"] = plots.save(fig, "matches", out)
        plots._plt().close(fig)
    fig = overlay_figure(reg)
    paths["overlay"] = plots.save(fig, "overlay", out)
    plots._plt().close(fig)
    return paths


def _json_matrix(T: np.ndarray):
    return [[None if not math.isfinite(v) else float(v) for v in row] for row in np.asarray(T)]


# --------------------------------------------------------------------------------------
# Writing a pair as files (the notebook's and the tests' inputs): freereg_lib.pair_files.

from .pair_files import downscale_pair, write_demo_layout, write_ply, write_user_files  # noqa: E402,F401
