"""The FreeReg chain for one pair, and over many pairs.

``depth_view`` -> ``compute_features`` -> ``match`` -> ``solve`` -> ``evaluate``; each step
is a function of arrays, so a notebook can stop between any two and draw. ``run_pair``
strings them together for several method / solver variants sharing one feature
extraction, and records a failed pair instead of raising, so a batch never loses its
finished results.
"""
from __future__ import annotations

import math
import traceback
from dataclasses import dataclass
from itertools import islice
from typing import Callable, Iterable

import numpy as np
import pandas as pd
from scipy import ndimage
from tqdm.auto import tqdm

from freereg_lib import features
from freereg_lib.config import FreeRegConfig
from freereg_lib.data.pair import Pair
from freereg_lib.features import baseline, matching
from freereg_lib.features import geometric as geo
from freereg_lib.features.matching import Matches  # noqa: F401 - the matches type lives with the matching; pipeline.Matches kept
from freereg_lib.geometry import cameras, densify, keypoints, metrics, pose, projection
from freereg_lib.models import resolve_device

# Method name -> fusion weight w of the diffusion part (None: the config's fusion_w; NaN: no
# feature at all, the position-only baseline of freereg_lib.features.baseline).
METHODS = {"FreeReg-D": 1.0, "FreeReg-G": 0.0, "FreeReg": None, baseline.METHOD: baseline.W}
DEFAULT_VARIANTS = (
    ("FreeReg-D", "pnp"),
    ("FreeReg-G", "kabsch"),
    ("FreeReg", "pnp"),
    ("FreeReg", "kabsch"),
)


@dataclass
class DepthView:
    """The point cloud seen from its depth camera.

    ``raw (H_d, W_d)``: the sensor depth or the projected cloud (0 = empty); ``dense``:
    after densification, depths outside ``(cfg.depth_min, cfg.depth_max)`` zeroed (the
    official keypoint mask); ``index (H_d, W_d) int64``: the point behind each raw pixel
    (-1 = none); ``ids``: class ids of the dense map (synthetic pairs only, else None);
    ``full``: the densified map before that mask, what the official depth PNG holds: the
    ControlNet hint is made from it, and it is the depth side's ground truth of a
    densified dataset without a truth file (:func:`evaluation_truth`).
    """

    raw: np.ndarray
    dense: np.ndarray
    index: np.ndarray
    ids: np.ndarray | None
    full: np.ndarray | None = None

    @property
    def hint_depth(self) -> np.ndarray:
        """The map the ControlNet hint is made from, ``full`` (the official PNG, unclipped)."""
        return self.dense if self.full is None else self.full


def depth_view(pair: Pair, cfg: FreeRegConfig) -> DepthView:
    """The depth map of the pair's depth camera, densified per ``cfg.densify``.

    As in the official code the map is the depth frame's own sensor depth when the pair has
    one (``pair.sensor_depth``: 3DMatch, ScanNet, KITTI-DC), used as it is; otherwise the
    cloud is projected on the depth camera (z-buffered, no edge filter; ``cfg.cloud_projection``
    "official": the official ``proj_pc2dpt``, pixels truncated, z > 0.05 m, no far limit). The
    map is densified as it is (``view.full``, the hint's input); depths outside
    ``(cfg.depth_min, cfg.depth_max)`` then become holes of ``view.dense``.

    Raises ``ValueError`` for a pair that fails :meth:`Pair.validate` or whose depth view is
    empty (the message counts where the points went).
    """
    pair.validate()
    if len(pair.points) == 0:
        raise ValueError(f"pair {pair.name}: the point cloud is empty")
    if pair.sensor_depth is not None:
        raw = np.asarray(pair.sensor_depth, dtype=np.float64).copy()
        raw[~np.isfinite(raw)] = 0.0
        index = np.full(raw.shape, -1, dtype=np.int64)
    else:
        official = cfg.cloud_projection == "official"
        raw, index = projection.project_to_depth(
            pair.points, pair.K_depth, cameras.invert(pair.T_pc_sensor), pair.depth_size,
            cfg.depth_min, cfg.depth_max, pixel="official" if official else "round", snap=cfg.cloud_snap_m)
    if not np.any((raw > cfg.depth_min) & (raw < cfg.depth_max)):
        where = ("its sensor_depth has no pixel in that range" if pair.sensor_depth is not None
                 else _where_points_went(pair, cfg))
        raise ValueError(f"pair {pair.name}: no point of the cloud projects into the depth view; {where}")
    full = densify.densify(raw, cfg.densify, hole_value=cfg.multiscale_hole_m)
    if cfg.densify != "none" and cfg.dense_png:  # the official *.dense.depth.png, read back
        full = densify.png_round_trip(full, cfg.depth_png_scale)
    dense = projection.clip_to_range(full, cfg.depth_min, cfg.depth_max)
    ids = None
    if pair.point_ids is not None and np.any(index >= 0):
        ids = _nearest_fill(np.where(index >= 0, pair.point_ids[np.maximum(index, 0)], 0), index >= 0)
        ids[dense == 0] = 0
    return DepthView(raw, dense, index, ids, full)


def _where_points_went(pair: Pair, cfg: FreeRegConfig) -> str:
    """How many points are in front of the depth camera, in the depth range, in its view."""
    uv, z = cameras.project(cameras.transform(cameras.invert(pair.T_pc_sensor), pair.points), pair.K_depth)
    H, W = pair.depth_size
    front = z > 0
    in_range = front & (z > cfg.depth_min) & (z < cfg.depth_max)
    with np.errstate(invalid="ignore"):
        inside = in_range & (np.rint(uv[:, 0]) >= 0) & (np.rint(uv[:, 0]) < W) & (np.rint(uv[:, 1]) >= 0) & (np.rint(uv[:, 1]) < H)
    return (
        f"of its {len(z)} points {int(front.sum())} lie in front of the depth camera, {int(in_range.sum())} within "
        f"depth_min..depth_max = {cfg.depth_min:g}..{cfg.depth_max:g} m and {int(inside.sum())} inside its {W} x {H} view "
        "; check T_pc_sensor (the depth camera in the cloud's frame), "
        "K_depth and depth_size"
    )


def _nearest_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Each pixel takes the value of its nearest ``known`` pixel."""

    if not known.any():
        return np.zeros_like(values)
    _, (iy, ix) = ndimage.distance_transform_edt(~known, return_indices=True)
    return values[iy, ix]


def scene_hints(pair: Pair, view: DepthView) -> tuple[dict, dict]:
    """What a synthetic scene knows about each pixel, for the stub backend.

    Image side: class ids and the true scene point of every pixel (from the true depth and
    pose, which only a synthetic scene hands out). Depth side: the class ids and the scene
    points of the densified depth map (no ground truth needed). Empty dicts for a pair that
    is not synthetic.
    """
    if pair.image_ids is None or pair.depth_gt is None:
        return {}, {}
    pts_img, uv_img = cameras.backproject(pair.depth_gt, pair.K_image)
    xyz_img = np.full(pair.depth_gt.shape + (3,), np.nan)
    xyz_img[uv_img[:, 1].astype(int), uv_img[:, 0].astype(int)] = cameras.transform(cameras.invert(pair.T_cam_pc), pts_img)
    pts_dep, uv_dep = cameras.backproject(view.dense, pair.K_depth)
    xyz_dep = np.full(view.dense.shape + (3,), np.nan)
    xyz_dep[uv_dep[:, 1].astype(int), uv_dep[:, 0].astype(int)] = cameras.transform(pair.T_pc_sensor, pts_dep)
    return {"ids": pair.image_ids, "xyz": xyz_img}, {"ids": view.ids, "xyz": xyz_dep}


def diffusion_maps(pair: Pair, view: DepthView, backend) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The nine decoder layers of the image and of the densified depth map.

    Backends that ask for scene hints (the stub) get :func:`scene_hints`; real ones see
    only the image and the depth map.
    """
    hint_img, hint_dep = scene_hints(pair, view) if getattr(backend, "uses_scene_hints", False) else ({}, {})
    return backend.diffusion_rgb(pair.image, **hint_img), backend.diffusion_depth(view.hint_depth, **hint_dep)


def diffusion_maps_batch(pairs: list[Pair], views: list[DepthView], backend,
                         layers=None) -> list[tuple[dict, dict]]:
    """The decoder ``layers`` (all nine when None) of several pairs, ``({layer: map} of the
    image, {layer: map} of the depth map)`` per pair; each side is one backend batch
    (one model call per step for all the pairs with the torch backends), and the models stop
    after the last chosen layer."""
    use_hints = getattr(backend, "uses_scene_hints", False)
    hints = [scene_hints(p, v) if use_hints else ({}, {}) for p, v in zip(pairs, views)]
    rgb = backend.diffusion_rgb_batch([p.image for p in pairs], [h[0] for h in hints], layers)
    dep = backend.diffusion_depth_batch([v.hint_depth for v in views], [h[1] for h in hints], layers)
    return list(zip(rgb, dep))


def diffusion_maps_over_t_hats(pairs: list[Pair], views: list[DepthView], backend, t_hats,
                               layers=None) -> dict[int, list[tuple[dict, dict]]]:
    """:func:`diffusion_maps_batch` at each of ``t_hats`` (Table 3), ``{t_hat: maps}``: each
    t_hat's maps are those of the backend built with ``cfg.t_hat`` = t_hat, the torch backends'
    depth sides read from one DDIM trajectory. The stub has no diffusion time: the same maps."""
    diffusion = getattr(backend, "diffusion", None)
    if diffusion is None:
        maps = diffusion_maps_batch(pairs, views, backend, layers)
        return {int(t): maps for t in t_hats}
    dep = diffusion.depth_batch_over_t_hats([v.hint_depth for v in views], t_hats, layers)
    return {t: list(zip(diffusion.rgb_batch([p.image for p in pairs], layers, t_hat=t), dep[t])) for t in dep}


@dataclass
class PairFeatures:
    """Keypoints and their features on both sides of a pair.

    Image side: ``uv_image (N, 2)``, monocular-depth points ``pts_image (N, 3)`` in the
    camera frame (NaN where the depth is missing), ``diff_image (N, Cd)``,
    ``geo_image (N, Cg)``. Depth side: ``uv_depth (M, 2)`` on the depth map, their cloud
    points ``pts_depth (M, 3)`` in the ``pc`` frame, ``diff_depth``, ``geo_depth``.
    Feature arrays are None when that kind was not computed.
    """

    uv_image: np.ndarray
    pts_image: np.ndarray
    uv_depth: np.ndarray
    pts_depth: np.ndarray
    diff_image: np.ndarray | None
    diff_depth: np.ndarray | None
    geo_image: np.ndarray | None
    geo_depth: np.ndarray | None
    mono_depth: np.ndarray
    view: DepthView


def compute_features(
    pair: Pair, backend, cfg: FreeRegConfig, diffusion: bool = True, geometric: bool = True,
    view: DepthView | None = None, maps: tuple[dict, dict] | None = None, mono: np.ndarray | None = None,
) -> PairFeatures:
    """Everything the matcher needs for ``pair`` (see :class:`PairFeatures`).

    The pair is validated first (by :func:`depth_view`), so bad input fails before any model
    runs. ``view``, ``maps`` (the pair's entry of :func:`diffusion_maps_batch` for
    ``cfg.layers``) and ``mono`` (its monocular depth) skip those steps when already done.
    """

    if view is None:
        view = depth_view(pair, cfg)
    uv_img = keypoints.grid_keypoints(pair.image_size, cfg.keypoint_grid)
    uv_dep = keypoints.grid_keypoints(pair.depth_size, cfg.keypoint_grid)
    z_dep = cameras.nearest_sample(view.dense, uv_dep)
    keep = z_dep > 0
    uv_dep, z_dep = uv_dep[keep], z_dep[keep]
    if len(uv_dep) == 0:
        raise ValueError(
            f"pair {pair.name}: no depth keypoint has a valid depth: none of the {len(keep)} keypoints of the "
            f"{cfg.keypoint_grid[0]} x {cfg.keypoint_grid[1]} grid (cfg.keypoint_grid) falls on one of the "
            f"{int(np.count_nonzero(view.dense))} pixels of the densified depth view that have depth; the cloud "
            "covers too little of the depth camera's view"
        )
    pts_dep_cam = cameras.lift(uv_dep, z_dep, pair.K_depth)
    pts_dep = cameras.transform(pair.T_pc_sensor, pts_dep_cam)

    if mono is None:
        mono = backend.mono_depth(pair.image, depth_gt=pair.depth_gt)
    mono = np.asarray(mono, dtype=np.float64)
    z_img = cameras.nearest_sample(mono, uv_img)
    # The official code lifts every image keypoint with the monocular map as it is (no range
    # mask); only a map with holes (a sensor depth standing in for it) leaves keypoints unlifted.
    z_img = np.where(np.isfinite(z_img) & (z_img > 0), z_img, np.nan)
    pts_img = cameras.lift(uv_img, z_img, pair.K_image)

    diff_img = diff_dep = geo_img = geo_dep = None
    if diffusion:
        maps_img, maps_dep = maps or diffusion_maps_batch([pair], [view], backend, cfg.layers)[0]
        f_img, f_dep = features.pca_reduce(maps_img, maps_dep, cfg.layers, cfg.pca_dim, device=cfg.pca_device)
        diff_img = features.sample_features(f_img, uv_img, pair.image_size)
        diff_dep = features.sample_features(f_dep, uv_dep, pair.depth_size)
    if geometric:
        # As the official code (``projection.feature_cloud``): the monocular map loses its edge
        # pixels (``cfg.edge_filter_m``, on the map as it is), then both maps are cut to the
        # back-projection's range (``cfg.cloud_near_m``..``cfg.cloud_far_m``) and the depth range;
        # the depth side's cloud is the back-projection of the depth map the pipeline uses (its
        # densified PNG), not a stored or wider cloud.
        # Both clouds stay in their own camera's frame (the official ``extrinsic=np.eye(4)``):
        # FCGF is not rotation invariant, and a depth side turned into the cloud's frame (z up
        # where the image side has z forward) would hand it the two halves of a pair in frames
        # it never saw together. Normals face each camera's origin, so FPFH signs agree.
        cloud_img, _ = projection.feature_cloud(mono, pair.K_image, cfg, monocular=True)
        cloud_dep, _ = projection.feature_cloud(view.hint_depth, pair.K_depth, cfg, monocular=False)
        good = np.isfinite(pts_img).all(1)
        # ``at``: only the features the keypoints will read are computed.
        down_img, feats_img = geo.geometric_features(cloud_img, cfg, at=pts_img[good], backend=backend)
        down_dep, feats_dep = geo.geometric_features(cloud_dep, cfg, at=pts_dep_cam, backend=backend)
        geo_img = np.zeros((len(uv_img), feats_img.shape[1]))
        geo_img[good] = geo.pixel_features(pts_img[good], down_img, feats_img, cfg.tau_g)
        geo_dep = geo.pixel_features(pts_dep_cam, down_dep, feats_dep, cfg.tau_g)
    return PairFeatures(uv_img, pts_img, uv_dep, pts_dep, diff_img, diff_dep, geo_img, geo_dep, mono, view)


def compute_features_batch(
    pairs: list[Pair], backend, cfg: FreeRegConfig, diffusion: bool = True, geometric: bool = True
) -> list[PairFeatures | Exception]:
    """:func:`compute_features` for several pairs, the diffusion models and the monocular
    depth model batched over them.

    A pair that fails gets its exception in its place and the others go on. When the batched
    model call itself fails (out of GPU memory, say), each pair is run alone.
    """
    out: list = [None] * len(pairs)
    views: dict[int, DepthView] = {}
    for i, pair in enumerate(pairs):
        try:
            views[i] = depth_view(pair, cfg)
        except Exception as exc:
            out[i] = exc
    idx = list(views)
    maps = _batched(lambda: diffusion_maps_batch([pairs[i] for i in idx], [views[i] for i in idx], backend,
                                                  cfg.layers), idx, diffusion)
    monos = _batched(lambda: backend.mono_depth_batch([pairs[i].image for i in idx],
                                                      [pairs[i].depth_gt for i in idx]), idx, True)
    for i, view in views.items():
        try:
            out[i] = compute_features(pairs[i], backend, cfg, diffusion, geometric, view=view, maps=maps.get(i),
                                      mono=monos.get(i))
        except Exception as exc:
            out[i] = exc
    return out


def _batched(compute, idx: list[int], wanted: bool) -> dict:
    """``{pair index: result}`` of one batched call over ``idx``; empty when not wanted, for a
    single pair, or when the call fails (each pair then runs alone, so the failure lands on
    the pair that causes it)."""
    if not wanted or len(idx) < 2:
        return {}
    try:
        return dict(zip(idx, compute()))
    except Exception:
        return {}


def descriptors(feats: PairFeatures, w: float) -> tuple[np.ndarray, np.ndarray]:
    """Image-side and depth-side descriptors for fusion weight ``w`` (1: diffusion only, 0: geometric only)."""

    if w >= 1.0:
        _need(feats.diff_image, "diffusion")
        return features.l2_normalize(feats.diff_image), features.l2_normalize(feats.diff_depth)
    if w <= 0.0:
        _need(feats.geo_image, "geometric")
        return features.l2_normalize(feats.geo_image), features.l2_normalize(feats.geo_depth)
    _need(feats.diff_image, "diffusion")
    _need(feats.geo_image, "geometric")  # a fused weight on one kind alone would be another method
    return (
        features.fuse(feats.diff_image, feats.geo_image, w),
        features.fuse(feats.diff_depth, feats.geo_depth, w),
    )


def _need(arr, kind: str) -> None:
    if arr is None:
        raise ValueError(f"{kind} features were not computed for this pair; pass {kind}=True to compute_features")


def match(feats: PairFeatures, w: float, device: str = "cpu") -> Matches:
    """Mutual nearest neighbours of the fused descriptors, computed on ``device`` (``"cpu"``,
    ``"cuda[:N]"``; ``cfg.match_device`` in :func:`run_pair`)."""
    d_img, d_dep = descriptors(feats, w)
    if str(device) != "cpu":

        device = resolve_device(device)[0]  # a clear error when CUDA is not there
    ia, ib = matching.mutual_nn(d_img, d_dep, device=device)
    return Matches(ia, ib)


def solve(pair: Pair, feats: PairFeatures, m: Matches, cfg: FreeRegConfig, solver: str) -> pose.PoseResult:
    """Estimate ``T_cam_pc`` from matches with ``solver`` = ``"kabsch"`` or ``"pnp"``.

    Kabsch-RANSAC gets every keypoint of both sides and the matches between them, as the
    official code passes them to Open3D (whose score reads the whole keypoint clouds).
    """
    if solver == "kabsch":
        return pose.kabsch_ransac(
            feats.pts_image, feats.pts_depth, cfg.kabsch_inlier_m, cfg.ransac_iters,
            cfg.ransac_n, cfg.kabsch_with_scale, cfg.min_matches_kabsch, cfg.seed,
            max_scale_ratio=cfg.kabsch_max_scale_ratio,
            corres=np.stack([m.idx_image, m.idx_depth], axis=1),
            confidence=cfg.kabsch_confidence, scoring=cfg.kabsch_scoring,
        )
    if solver == "pnp":
        return pose.pnp_ransac(
            feats.uv_image[m.idx_image], feats.pts_depth[m.idx_depth], pair.K_image, cfg.pnp_reproj_px,
            cfg.ransac_iters, cfg.min_matches_pnp, method=cfg.pnp_method, workers=cfg.pnp_workers,
        )
    raise ValueError(f"unknown solver {solver!r}; expected 'kabsch' or 'pnp'")


def correct_matches(pair: Pair, feats: PairFeatures, m: Matches, cfg: FreeRegConfig,
                    tau_c: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(correct, evaluable)`` per match at ``tau_c`` metres (default ``cfg.tau_c``), each side
    lifted with its own frame's true depth as :func:`evaluate` describes."""
    if pair.depth_gt is None:
        raise ValueError(f"pair {pair.name} has no ground-truth image depth; matches cannot be scored")
    uv_dep = feats.uv_depth[m.idx_depth]
    truth, _ = evaluation_truth(pair, feats.view, cfg)
    pts_true = metrics.lift_truth(uv_dep, truth, pair.K_depth, (cfg.depth_min, cfg.depth_max))
    ok = np.isfinite(pts_true).all(axis=1)
    if ok.any():
        pts_true[ok] = cameras.transform(pair.T_pc_sensor, pts_true[ok])
    return metrics.correct_matches(
        feats.uv_image[m.idx_image], pts_true, pair.depth_gt, pair.K_image,
        pair.T_cam_pc, cfg.tau_c if tau_c is None else tau_c, (cfg.depth_min, cfg.depth_max),
    )


def evaluation_truth(pair: Pair, view: DepthView, cfg: FreeRegConfig) -> tuple[np.ndarray, str]:
    """The depth side's ground truth and where it comes from, as the official evaluation
    (``dpt_gtd``): the depth frame's truth file when the pair has one
    (``pair.depth_frame_gt``: the demo's ``just_for_eval/target_dpt.gtd.png``, a frame's
    ``.depth.gtd.png``, a synthetic room's full depth), else the densified map on a dataset
    that densifies (ScanNet, KITTI: ``view.full``), else the raw map (3DMatch: the sensor
    depth as read). Never the sparse projection of a cloud when a truth file exists."""
    if pair.depth_frame_gt is not None:
        return np.asarray(pair.depth_frame_gt, dtype=np.float64), "truth file"
    if cfg.densify != "none":
        return (view.dense if view.full is None else view.full), "densified map"
    return view.raw, "raw map"


def evaluate(pair: Pair, feats: PairFeatures, m: Matches, result: pose.PoseResult, cfg: FreeRegConfig) -> dict:
    """Per-pair metrics: ``IR`` (fraction), ``IN``, ``RE``, ``TE``, ``registered``, ``n_evaluable``.

    As in the official evaluation both sides of a match are lifted with the ground-truth
    depth of their own frame: the image side with ``pair.depth_gt``, the depth side with
    :func:`evaluation_truth` (a truth file, else the densified map on ScanNet / KITTI, else
    the raw map), not with the map the features were computed on. A match whose true depth
    on either side is outside ``(cfg.depth_min, cfg.depth_max)`` is not evaluable;
    ``n_evaluable`` counts those that are, and a pair with fewer than 3 scores IR 1, IN 1
    as the official code (``cfg.eval_few_matches = "official"``; ``"zero"``: IR 0), which
    :func:`summarize` counts in ``n_few_evaluable``.
    """
    correct, evaluable = correct_matches(pair, feats, m, cfg)
    ir, inn = metrics.inlier_stats(correct, evaluable, cfg.eval_few_matches)
    re, te = metrics.pose_errors(result.T_cam_pc, pair.T_cam_pc) if result.success else (math.nan, math.nan)
    return {
        "IR": ir, "IN": inn, "RE": re, "TE": te,
        "registered": metrics.registered(re, te, cfg.rr_rot_deg, cfg.rr_trans_m),
        "n_evaluable": int(np.count_nonzero(evaluable)),
    }


def _weight(method: str, cfg: FreeRegConfig) -> float:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")
    w = METHODS[method]
    return cfg.fusion_w if w is None else w


def run_pair(
    pair: Pair, backend, cfg: FreeRegConfig, variants: Iterable[tuple[str, str]] = DEFAULT_VARIANTS
) -> list[dict]:
    """One row per (method, solver) variant; features are extracted once.

    Any exception becomes a row with ``error`` set and zero IR / IN, no pose, not registered,
    the way the paper's RR counts a failure.
    """
    variants = list(variants)
    return variant_rows(pair, _features_or_error(pair, backend, cfg, *_kinds_needed(variants, cfg)), cfg, variants)


def _features_or_error(pair: Pair, backend, cfg: FreeRegConfig, diffusion: bool, geometric: bool):
    try:
        return compute_features(pair, backend, cfg, diffusion, geometric)
    except Exception as exc:  # recorded per pair so a batch goes on
        return exc


def _kinds_needed(variants: list[tuple[str, str]], cfg: FreeRegConfig) -> tuple[bool, bool]:
    """Whether the variants need diffusion features, and geometric ones."""
    ws = [_weight(mth, cfg) for mth, _ in variants]
    return any(w > 0 for w in ws), any(w < 1 for w in ws)


def variant_rows(pair: Pair, feats: PairFeatures | Exception, cfg: FreeRegConfig,
                 variants: Iterable[tuple[str, str]] = DEFAULT_VARIANTS) -> list[dict]:
    """The rows of :func:`run_pair` from a pair's features, or from the exception that
    stopped their extraction (then every variant is a failed row)."""
    variants = list(variants)
    ws = [_weight(mth, cfg) for mth, _ in variants]
    if isinstance(feats, Exception):
        reason = _describe(feats)
        return [_row(pair, mth, sol, w, 0, None, reason) for (mth, sol), w in zip(variants, ws)]
    rows = []
    matches_by_w: dict[float, Matches] = {}
    for (mth, sol), w in zip(variants, ws):
        try:
            key = mth if mth == baseline.METHOD else w
            if key not in matches_by_w:
                matches_by_w[key] = (baseline.position_matches(feats, pair.image_size, pair.depth_size)
                                     if mth == baseline.METHOD else match(feats, w, cfg.match_device))
            m = matches_by_w[key]
            res = solve(pair, feats, m, cfg, sol)
            scores = evaluate(pair, feats, m, res, cfg)
            rows.append(_row(pair, mth, sol, w, len(m), res, "" if res.success else res.reason, scores))
        except Exception as exc:
            rows.append(_row(pair, mth, sol, w, 0, None, _describe(exc)))
    return rows


def _describe(exc: Exception) -> str:
    frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    where = f" ({frame.filename.rsplit('/', 1)[-1]}:{frame.lineno})" if frame else ""
    return f"{type(exc).__name__}: {exc}{where}"


ROW_COLUMNS = ("pair", "method", "solver", "w", "n_matches", "IR", "IN", "RE", "TE", "registered",
               "n_evaluable", "n_inliers", "scale", "error")


def rows_frame(rows: list[dict]):
    """Per-pair rows as a DataFrame with the row columns even when there are none (an empty shard)."""

    return pd.DataFrame(rows, columns=list(ROW_COLUMNS))


def _row(pair, method, solver, w, n_matches, res, error, scores=None) -> dict:
    # n_evaluable -1: not scored (the pair failed before matching).
    scores = scores or {"IR": 0.0, "IN": 0, "RE": math.nan, "TE": math.nan, "registered": False, "n_evaluable": -1}
    return {
        "pair": pair.name, "method": method, "solver": solver, "w": w, "n_matches": n_matches,
        **scores,
        "n_inliers": res.n_inliers if res is not None else 0,
        "scale": res.scale if res is not None else math.nan,
        "error": error,
    }


def run_pairs(pairs: Iterable[Pair], backend, cfg: FreeRegConfig, variants=DEFAULT_VARIANTS,
              progress: bool = True,
              on_pair: Callable[[Pair, PairFeatures | Exception, list[dict]], None] | None = None) -> list[dict]:
    """``run_pair`` over ``pairs`` with a progress bar; returns all rows.

    With ``cfg.pair_batch = B > 1`` the diffusion models run on ``B`` pairs at a time
    (:func:`compute_features_batch`): the same rows up to float rounding, fewer and larger
    model calls (a GPU speed-up; on a CPU it gains little and costs memory).
    ``on_pair(pair, features, rows)`` is called after each pair (``features`` the exception
    that stopped their extraction, if one did), e.g. to keep a failed pair's features for a
    picture instead of computing them again.
    """
    variants = list(variants)
    batch = int(cfg.pair_batch)
    if batch < 1:
        raise ValueError(f"cfg.pair_batch must be >= 1, got {cfg.pair_batch}")
    diffusion, geometric = _kinds_needed(variants, cfg)
    rows: list[dict] = []
    it = iter(pairs)
    with tqdm(total=len(pairs) if hasattr(pairs, "__len__") else None, desc="pairs", disable=not progress) as bar:
        while chunk := list(islice(it, batch)):
            feats_of_chunk = ([_features_or_error(chunk[0], backend, cfg, diffusion, geometric)] if len(chunk) == 1
                              else compute_features_batch(chunk, backend, cfg, diffusion, geometric))
            for pair, feats in zip(chunk, feats_of_chunk):
                pair_rows = variant_rows(pair, feats, cfg, variants)
                rows.extend(pair_rows)
                if on_pair is not None:
                    on_pair(pair, feats, pair_rows)
            bar.update(len(chunk))
    return rows


def summarize(rows: list[dict], cfg: FreeRegConfig):
    """A table (pandas DataFrame) with one row per (method, solver): FMR, IR, IN, RR, RE, TE, ladder."""

    out = []
    keys = list(dict.fromkeys((r["method"], r["solver"]) for r in rows))
    for mth, sol in keys:
        sub = [r for r in rows if r["method"] == mth and r["solver"] == sol]
        agg = metrics.aggregate(sub, cfg.rr_rot_deg, cfg.rr_trans_m, cfg.fmr_ratio, cfg.rr_ladder)
        out.append({"method": mth, "solver": sol, **agg})
    if not out:  # an empty shard still has the table's columns
        columns = ["method", "solver", *metrics.aggregate([], ladder=cfg.rr_ladder)]
        return pd.DataFrame(columns=columns)
    return pd.DataFrame(out)
