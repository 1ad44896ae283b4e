"""Register your own image to your own point cloud: the pair, the depth camera, the verdict.

::

    freereg register IMAGE CLOUD --K fx fy cx cy [--depth-K ... --depth-size W H --depth-pose FILE]
    freereg register --demo FOLDER            # the official demo layout (data/demo/)

or, as functions: :func:`freereg_lib.commands.user_inputs.load_inputs` (files -> a :class:`~freereg_lib.data.pair.Pair`),
:func:`register` (a pair -> a :class:`Registration`), and
:func:`freereg_lib.report.registration.write_outputs` (the pose, the matches and the overlay as
files). Reading and checking the user's files is :mod:`freereg_lib.commands.user_inputs`.

Conventions (the README's "Your own data"):

* ``T_cam_pc`` maps points of the cloud's frame into the image camera (``x_cam = R x_pc + t``);
  its inverse ``T_pc_cam`` is **the pose of the camera in the cloud's frame** (where the camera
  is and where it looks, in the cloud's coordinates). The official demo's
  ``rgb2pc.gt.pose.txt`` is a ``T_pc_cam``.
* The cloud is in metres. Kabsch-RANSAC estimates a similarity (monocular depth has a scale
  error); the pose written is its rigid part, the scale is reported.

**The depth camera.** The cloud is rendered as a depth map from its sensor when it has one,
else from virtual cameras (:func:`virtual_cameras`); each candidate runs the whole chain, the pose
with the most RANSAC inliers (a plausible scale) is kept, then refined from the estimated pose.

**Registered or not** without ground truth: a plausibility check, :mod:`freereg_lib.pipeline.verdict`
(the inliers against a per-run null of shuffled matches). With a ground-truth pose RE / TE and the
paper's (20 deg, 0.5 m) verdict are printed as well.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.data.pair import Pair
from freereg_lib.features.baseline import METHOD as BASELINE
from freereg_lib.features.matching import Matches
from freereg_lib.geometry import cameras, metrics, pose
from freereg_lib.models import get_backend
from freereg_lib.pipeline import steps, verdict

class InputError(ValueError):
    """A user input that cannot be registered; its message is one line naming the input."""


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


VIRTUAL_MAX_WIDTH = 640  # virtual depth cameras render at most this wide (the image's intrinsics, scaled)


# Clouds far from their frame's origin (UTM, a map) are solved re-centred, for float precision.
RECENTRE_BEYOND_M = 1000.0  # clouds whose centre is farther than this from their origin are re-centred


def recentre_offset(points: np.ndarray) -> np.ndarray | None:
    """The offset (the cloud's median, rounded to the metre) to subtract before solving when the
    cloud lies farther than ``RECENTRE_BEYOND_M`` from its frame's origin, else ``None``."""
    c = np.median(np.asarray(points, dtype=np.float64)[:: max(1, len(points) // 100_000)], axis=0)
    if not np.all(np.isfinite(c)) or float(np.linalg.norm(c)) <= RECENTRE_BEYOND_M:
        return None
    return np.round(c)


def shift_pose(T_x_pc: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``T_x_pc`` for the cloud frame moved by ``-offset`` (points ``p - offset``): maps the
    shifted cloud frame as ``T_x_pc`` mapped the original one."""
    return np.asarray(T_x_pc, dtype=np.float64) @ cameras.make_pose(np.eye(3), offset)


def unshift_pose(T_x_pcs: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The inverse of :func:`shift_pose`: a pose of the shifted frame back in the original one."""
    return np.asarray(T_x_pcs, dtype=np.float64) @ cameras.make_pose(np.eye(3), -np.asarray(offset))


def shift_frame(T_pc_x: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """A pose in the cloud's frame (``T_pc_sensor``, ``T_pc_cam``) in the frame moved by ``-offset``."""
    return cameras.make_pose(np.eye(3), -np.asarray(offset)) @ np.asarray(T_pc_x, dtype=np.float64)


def unshift_frame(T_pcs_x: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The inverse of :func:`shift_frame`."""
    return cameras.make_pose(np.eye(3), np.asarray(offset)) @ np.asarray(T_pcs_x, dtype=np.float64)


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
    feats: steps.PairFeatures | None = None
    matches: Matches | None = None
    pose: object = None
    errors: dict = field(default_factory=dict)  # RE, TE (and IR, IN with the image's true depth)
    seconds: float = 0.0
    null_inliers: list = field(default_factory=list)  # the verdict's shuffles: the solver's inliers by chance

    @property
    def T_pc_cam(self) -> np.ndarray:
        return cameras.invert(self.T_cam_pc)

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / self.n_matches if self.n_matches else 0.0


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
    """Candidate depth cameras for a cloud with no sensor pose, with the image's intrinsics (at
    most ``max_width`` px wide): ``origin`` (the cloud frame's origin looking along +z, as the
    demo's identity extrinsic; when 5 % of the points are in view and ``with_origin``), ``rough``
    (the given ``T_pc_cam``), ``centre/yaw<deg>`` (at the centroid, looking horizontally every
    ``360 / n_yaw`` degrees) and ``behind/yaw<deg>`` (the same, pulled back by the cloud's
    horizontal radius of gyration)."""
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

    if method not in steps.METHODS or method == BASELINE:  # the baseline is for benchmarks, not a registration
        raise InputError(f"unknown method {method!r}; expected one of {[m for m in steps.METHODS if m != BASELINE]}")
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
    min_support: float | None = None,
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

    The steps: re-centre a far cloud (``_recentred``), choose the method and the depth cameras
    (``_candidates``), run the chain on each (``_Attempt``), keep the best and refine it,
    then the verdict (``_registration``).
    """
    say = log or (lambda s: None)
    t0 = time.perf_counter()
    if int(n_yaw) < 1:
        raise InputError(f"--views must be >= 1 (virtual camera directions around the up axis), got {n_yaw}")
    for note in pair.meta.get("notes", []):
        say(note)
    original = pair
    pair, rough_T_pc_cam, depth_cameras, offset = _recentred(pair, rough_T_pc_cam, depth_cameras, say)
    cfg = cfg or config_for("demo")
    if isinstance(backend, str):
        backend = get_backend(backend, cfg)
    method, why_method = choose_method(backend, pair, method)
    if solver not in ("kabsch", "pnp"):
        raise InputError(f"unknown solver {solver!r}; expected kabsch or pnp")
    thresholds = (verdict.MIN_SUPPORT[solver] if min_support is None else float(min_support),
                  verdict.MAX_SCALE if max_scale is None else float(max_scale))
    if getattr(backend, "name", "") == "stub" and pair.depth_gt is None:
        raise InputError("the stub backend makes its stand-in monocular depth from the image's true depth: give "
                         "--image-depth FILE, or use --backend tiny / real (ZoeDepth)")
    say(f"backend: {getattr(backend, 'label', backend)}")
    say(f"method: {why_method}; solver: {solver} (RANSAC iterations {cfg.ransac_iters}"
        + (f", Kabsch scoring {cfg.kabsch_scoring!r}" if solver == "kabsch" else "") + ")")
    cands = _candidates(pair, cfg, depth_cameras, rough_T_pc_cam, up, n_yaw, offset, say)
    attempt = _Attempt(pair, backend, cfg, method, solver, thresholds[1])
    runs = [attempt(cam) for cam in cands]
    best = _best(runs)
    if refine and len(cands) > 1 and best is not None and best.get("_res") is not None and best["_res"].success:
        cam0 = best["_cam"]
        ref = attempt(DepthCamera("refined", cam0.K, cam0.size, cameras.invert(best["_res"].T_cam_pc),
                                  f"at the pose estimated with {cam0.name} (the cloud seen as the image sees it)"))
        runs.append(ref)
        if ref["score"] > best["score"]:
            best = ref
    _say_candidates(runs, best, say)
    reg = _registration(best, runs, original, offset, cfg, method, solver, thresholds, backend,
                        time.perf_counter() - t0)
    say(reg.result)
    if reg.errors:
        e = reg.errors
        say(f"against the ground truth: RE {_fmt(e['RE'], '.2f')} deg, TE {_fmt(e['TE'], '.3f')} m: "
            f"{'registered' if e['registered_gt'] else 'not registered'} at ({cfg.rr_rot_deg:g} deg, "
            f"{cfg.rr_trans_m:g} m)" + (f"; IR {e['IR']:.3f}, IN {e['IN']}" if "IR" in e else ""))
    return reg


def _recentred(pair: Pair, rough_T_pc_cam, depth_cameras, say):
    """A cloud far from its frame's origin (UTM coordinates) is solved in re-centred coordinates
    and the pose restored after: a numerical safeguard (PnP loses degrees at 5,000 km). Returns
    ``(pair, rough_T_pc_cam, depth_cameras, offset)``, shifted when ``offset`` is not ``None``."""
    offset = recentre_offset(pair.points)
    if offset is not None and depth_cameras is None and pair.meta.get("depth_camera", True):
        offset = np.round(pair.T_pc_sensor[:3, 3])  # on its sensor: a cloud in its sensor's frame solves as at 0
    if offset is None:
        return pair, rough_T_pc_cam, depth_cameras, None
    say(f"the cloud lies {np.linalg.norm(offset):.4g} m from its frame's origin: solving in coordinates "
        f"re-centred on ({', '.join(f'{v:.0f}' for v in offset)}), the pose restored after")
    pair = dataclasses.replace(pair, points=pair.points - offset, T_pc_sensor=shift_frame(pair.T_pc_sensor, offset),
                               T_cam_pc=shift_pose(pair.T_cam_pc, offset))
    if rough_T_pc_cam is not None:
        rough_T_pc_cam = shift_frame(rough_T_pc_cam, offset)
    if isinstance(depth_cameras, (list, tuple)):
        depth_cameras = [dataclasses.replace(c, T_pc_sensor=shift_frame(c.T_pc_sensor, offset)) for c in depth_cameras]
    return pair, rough_T_pc_cam, depth_cameras, offset


def _candidates(pair: Pair, cfg: FreeRegConfig, depth_cameras, rough_T_pc_cam, up, n_yaw: int, offset,
                say) -> list[DepthCamera]:
    """The depth cameras to try: the pair's own, the virtual ones, or those given."""
    if depth_cameras is None:
        depth_cameras = "given" if pair.meta.get("depth_camera", True) else "virtual"
    if depth_cameras == "given":
        return [DepthCamera("given", np.asarray(pair.K_depth), tuple(pair.depth_size), pair.T_pc_sensor,
                            "the cloud's own depth camera (its sensor pose)", virtual=False)]
    if depth_cameras == "virtual":
        cands = virtual_cameras(pair.points, pair.K_image, pair.image_size, cfg, rough_T_pc_cam, up, n_yaw,
                                with_origin=offset is None)
        say(f"no depth camera given: trying {len(cands)} virtual depth cameras, keeping the one whose pose has "
            "the most RANSAC inliers")
        return cands
    return list(depth_cameras)


class _Attempt:
    """The chain on one candidate depth camera; the image's monocular depth and diffusion maps
    are computed once and shared by every candidate. Calling it returns the candidate's row."""

    def __init__(self, pair: Pair, backend, cfg: FreeRegConfig, method: str, solver: str, max_scale: float):
        self.pair, self.backend, self.cfg, self.solver, self.max_scale = pair, backend, cfg, solver, max_scale
        self.w = steps._weight(method, cfg)
        self.mono = np.asarray(backend.mono_depth(pair.image, depth_gt=pair.depth_gt), dtype=np.float64)
        self.maps_img = None

    def __call__(self, cam: DepthCamera) -> dict:
        pair, backend, cfg, w = self.pair, self.backend, self.cfg, self.w
        diffusion, geometric = w > 0, w < 1
        q = dataclasses.replace(pair, K_depth=cam.K, depth_size=tuple(cam.size), T_pc_sensor=cam.T_pc_sensor,
                                sensor_depth=pair.sensor_depth if not cam.virtual else None)
        row = {"camera": cam.name, "points_in_view": 0, "matches": 0, "inliers": 0, "scale": math.nan,
               "score": 0, "note": "", "_cam": cam}
        try:
            view = steps.depth_view(q, cfg)
            row["points_in_view"] = int(np.count_nonzero(view.raw))
            maps = None
            if diffusion:
                use_hints = getattr(backend, "uses_scene_hints", False)
                h_img, h_dep = steps.scene_hints(q, view) if use_hints else ({}, {})
                if self.maps_img is None:
                    self.maps_img = backend.diffusion_rgb_batch([q.image], [h_img], cfg.layers)[0]
                maps = (self.maps_img, backend.diffusion_depth_batch([view.hint_depth], [h_dep], cfg.layers)[0])
            feats = steps.compute_features(q, backend, cfg, diffusion, geometric, view=view, maps=maps,
                                           mono=self.mono)
            m = steps.match(feats, w, cfg.match_device)
            res = steps.solve(q, feats, m, cfg, self.solver)
        except ValueError as exc:
            row["note"] = _one_line(exc).replace(f"pair {pair.name}: ", "")[:160]
            return row
        row.update(matches=len(m), inliers=res.n_inliers, scale=res.scale, _q=q, _feats=feats, _m=m, _res=res)
        if not res.success:
            row["note"] = res.reason
        elif self.solver == "kabsch" and not 1 / self.max_scale <= res.scale <= self.max_scale:
            row["note"] = f"scale {res.scale:.2f} is implausible: not scored"
        else:
            row["score"] = res.n_inliers
        return row


def _best(runs: list[dict]) -> dict | None:
    """The candidate with the best score; when none is plausible, the one that got furthest."""
    best = max(runs, key=lambda r: r["score"]) if runs else None
    if best is not None and best["score"] == 0:
        best = max(runs, key=lambda r: (r["inliers"], r["matches"]))
    return best


def _say_candidates(runs: list[dict], best: dict, say) -> None:
    if len(runs) > 1:
        say("candidate depth cameras (score = RANSAC inliers of a pose with a plausible scale):")
        say(f"  {'camera':<16} {'points':>7} {'matches':>7} {'inliers':>7} {'scale':>6}  note")
        for r in runs:
            say(f"  {r['camera']:<16} {r['points_in_view']:>7} {r['matches']:>7} {r['inliers']:>7} "
                f"{_fmt(r['scale'], '.2f'):>6}  {'<- chosen ' if r is best else ''}{r['note']}")
    cam = best["_cam"]
    say(f"depth camera used: {cam.name}: {cam.why}")


def _registration(best: dict, runs: list[dict], original: Pair, offset, cfg: FreeRegConfig, method: str,
                  solver: str, thresholds: tuple[float, float], backend, seconds: float) -> Registration:
    """The chosen candidate as a :class:`Registration`: the verdict, the pose back in the cloud's
    own coordinates, and the errors against the ground truth when the pair has one."""
    cam, res = best["_cam"], best.get("_res")
    n_m, n_in = best["matches"], best["inliers"]
    scale = float(res.scale) if res is not None else math.nan
    nulls = (verdict.null_inliers(best["_q"], best["_feats"], best["_m"], cfg, solver)
             if res is not None and res.success else [])
    ok, why = verdict.decide(res, nulls, solver, cfg, *thresholds, note=best["note"])
    T = res.T_cam_pc if res is not None and res.success else np.full((4, 4), np.nan)
    q_out = best.get("_q", original)
    if offset is not None:  # back to the cloud's own coordinates
        T = unshift_pose(T, offset)
        cam = dataclasses.replace(cam, T_pc_sensor=unshift_frame(cam.T_pc_sensor, offset))
        q_out = dataclasses.replace(q_out, points=original.points, T_pc_sensor=cam.T_pc_sensor,
                                    T_cam_pc=original.T_cam_pc)
    errors: dict = {}
    if original.meta.get("has_gt", True):
        re, te = metrics.pose_errors(T, original.T_cam_pc) if res is not None and res.success else (math.nan, math.nan)
        errors = {"RE": re, "TE": te, "registered_gt": metrics.registered(re, te, cfg.rr_rot_deg, cfg.rr_trans_m)}
        if original.depth_gt is not None and best.get("_m") is not None:
            errors.update(_inliers_gt(best["_q"], best["_feats"], best["_m"], cfg, cam.virtual))
    result = (f"{'REGISTERED' if ok else 'FAILED'}: {why}; {n_in} inliers of {n_m} matches "
              f"({(n_in / n_m if n_m else 0):.0%})" + (f", scale {scale:.2f}" if solver == "kabsch" and res is not None
                                                      and res.success else ""))
    return Registration(T, ok, result, method, solver, getattr(backend, "label", str(backend)), n_m, n_in, scale, cam,
                        [{k: v for k, v in r.items() if not k.startswith("_")} | {"chosen": r is best} for r in runs],
                        q_out, best.get("_feats"), best.get("_m"), res, errors, seconds, nulls)


def _inliers_gt(q: Pair, feats, m, cfg: FreeRegConfig, virtual: bool) -> dict:
    """IR / IN with the image's true depth: :func:`steps.evaluate` on a sensor's camera; on a virtual
    one (a sparse raw view) the depth side lifted from the densified view, an approximation."""
    if not virtual:
        sc = steps.evaluate(q, feats, m, pose.PoseResult(np.eye(4), False, "none"), cfg)
        return {"IR": sc["IR"], "IN": sc["IN"]}
    correct, evaluable = metrics.correct_matches(
        feats.uv_image[m.idx_image], feats.pts_depth[m.idx_depth], q.depth_gt, q.K_image, q.T_cam_pc, cfg.tau_c,
        (cfg.depth_min, cfg.depth_max))
    ir, inn = metrics.inlier_stats(correct, evaluable)
    return {"IR": ir, "IN": inn}


def _fmt(v, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)
