"""Parity with the official FreeReg code, measured: ``python tools/parity.py [DIR]``.

``DIR`` holds golden fixtures made by calling the official functions themselves
(WHU-USI3DV/FreeReg at d13a45f): ``<function>/<case>.npz`` with ``in_<arg>`` (the inputs as
passed) and ``out_<name>`` (the official results; ``out_<k>_is_none`` marks a ``None``), and a
``manifest.json`` describing them. The default ``DIR`` is the set bundled with the tests
(``tests/fixtures/parity``). For every function folder the project's own counterpart (the
adapter named in :data:`ADAPTERS`, a few lines that call library functions) runs on each case's
inputs, whatever the cases, sizes or settings; its outputs are compared with the official
ones and one line is printed per function::

    name: max error X (tolerance T) ok | FAIL
    name: skipped (reason)

then a line with the counts. The exit status is 0 only when nothing fails. ``X`` is the
largest error over the function's cases and outputs, reported against the tolerance of the
output where it is worst relative to its tolerance (:data:`TOLERANCES`). Errors are absolute
differences in the output's unit (metres, degrees, uint8 levels, counts); index sets and
integer outputs must match exactly (a different length is an infinite error); PCA outputs are
compared after aligning each channel's sign (an eigenvector's sign is arbitrary). A dataset
setting named by a case (``in_config``: ``3dmatch``, ``scannet``, ``kitti``, ``demo``) is the
project's :func:`~freereg_lib.config.config_for` of that name with the official cameras and
depth scales (:func:`dataset_setting`).

Tolerances (per function; a dict gives one per output):

* exact (0): integer, boolean and index outputs, ``capture_timestep``, ``return_uv``,
  ``find_corr``, ``feature_match``, ``feature_transfer_xyz``, ``trans_gt_for_kitti``;
* uint8 images (``depth_normalize``, ``load_dpt``, ``resize_image``): 1 level (the manifest:
  exact with the same OpenCV, +-1 with another);
* densification: 1e-4 m (exact with the same OpenCV), ``gen_meta_run``'s uint16 PNGs 1 unit;
* geometry in float64: 1e-9 m (``proj_depth``, ``spconv_feature_extract``, ``kpts_sampling``,
  ``eval_pair``, ``pipeline_eval_run``, ``ransacor_run_after_ransac``, ``Refine_trans``),
  ``proj_pc2dpt`` 1e-12 m, ``compute_T_err`` RE 1e-4 deg, TE 1e-12 m, quaternions 1e-9;
* float32 features: ``feature_merge_on_kpts`` 1e-6, ``network_inputs`` 1e-7, PCA
  (``pca_feat``, ``merge_feat``; the official code runs float32 ``torch.linalg.eig``) 1e-3;
* ``pnpor_run``: pose 1e-5 (outlier-free fixtures; OpenCV's sampling otherwise differs).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
from parity_fixtures import BadFixture, _fmt, format_line, load_case, read_manifest

DEFAULT_DIR = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "parity"  # a repository tool: it knows the tree


class Skip(Exception):
    """Raised by an adapter whose counterpart cannot run here; the message is the reason."""


# --------------------------------------------------------------------------------------
# Dataset settings named by fixtures.

def dataset_setting(name: str) -> dict:
    """The official setting of dataset ``name`` in the project's terms: ``cfg`` (its
    :func:`~freereg_lib.config.config_for`), ``K_rgb``, ``K_dpt`` (the official configs'
    cameras) and ``dpt_scale`` (PNG units per metre)."""
    from freereg_lib.config import config_for
    from freereg_lib.data.datasets.kitti import K_OFFICIAL as K_KITTI
    from freereg_lib.data.datasets.scannet import K_COLOR_OFFICIAL, K_DEPTH_OFFICIAL
    from freereg_lib.data.datasets.threedmatch import K_3DMATCH

    name = str(name).lower()
    cfg = config_for(name)
    if name in ("kitti", "kitti_dc"):
        return {"cfg": cfg, "K_rgb": K_KITTI, "K_dpt": K_KITTI, "dpt_scale": 256.0}
    if name in ("scannet", "demo"):
        return {"cfg": cfg, "K_rgb": K_COLOR_OFFICIAL, "K_dpt": K_DEPTH_OFFICIAL, "dpt_scale": 1000.0}
    return {"cfg": cfg, "K_rgb": K_3DMATCH, "K_dpt": K_3DMATCH, "dpt_scale": 1000.0}


def _icl_K() -> np.ndarray:
    from freereg_lib.data.datasets.icl import ICL_ROOT
    from freereg_lib.geometry import cameras

    intr = json.loads((Path(ICL_ROOT) / "intrinsics.json").read_text())
    return cameras.intrinsics(intr["fx"], intr["fy"], intr["cx"], intr["cy"])


def _scalar(x):
    a = np.asarray(x)
    return a.item() if a.ndim == 0 else a


# --------------------------------------------------------------------------------------
# Adapters: fixture inputs -> the project's outputs, named as the fixture's out_* arrays.

def _fill_in_fast(i):
    from freereg_lib.geometry import densify

    return {"depth": densify.fill_in_fast(i["depth_map"])}


def _fill_in_multiscale(i):
    from freereg_lib.config import config_for
    from freereg_lib.geometry import densify

    return {"depth": densify.fill_in_multiscale(i["depth_map"], hole_value=config_for("kitti").multiscale_hole_m)}


def _depth_normalize(i):
    from freereg_lib.models.base import depth_to_uint8

    return {"image": depth_to_uint8(i["depth"])}


def _load_dpt(i):
    from freereg_lib.models.base import hint_image, official_resize_hw

    png = i["depth_png_u16"]
    hw = official_resize_hw(*png.shape[:2])
    hint = hint_image(png, hw)
    return {"hint_c0": hint[:, :, 0], "backup_first_channel": png.astype(np.float32), "HW": np.array(hw)}


def _resize_image(i):
    from freereg_lib.models.base import official_resize_hw, resize_to

    img = i["image"]
    return {"resized": resize_to(img, official_resize_hw(*img.shape[:2]))}


def _network_inputs(i):
    from freereg_lib.models.base import hint_to_unit, rgb_to_unit

    img = i["img"]
    return {"rgb_in": rgb_to_unit(img, img.shape[:2])[None], "hint_in": hint_to_unit(i["hint"])[None]}


def _capture_timestep(i):
    from freereg_lib.models.base import feature_timestep, n_guided_steps

    t, steps = int(i["t"]), int(_scalar(i.get("steps", 20)))
    t_used = feature_timestep(t, steps, clip=False)
    return {"t_used": t_used, "steps": steps, "index": n_guided_steps(t, steps), "tlist": np.array([t_used])}


def _proj_depth(i):
    from freereg_lib.geometry import projection

    unit = float(i["depth_unit"])
    uv, d, pc = projection.lift_depth_map(
        i["depth"], i["intrinsic"], i["extrinsic"], unit,
        float(i["max_range"]) if bool(i["filter_edge"]) else 0.0, int(i["window_s"]),
        float(i["far_thres"]) if bool(i["filter_far"]) else None,
        float(i["near_thres"]) if bool(i["filter_near"]) else None)
    return {"uv": uv, "d": d, "pc": pc}


def _spconv_feature_extract(i):
    from freereg_lib.geometry import projection

    cfg = dataset_setting(_scalar(i["config"]))["cfg"]
    pts, _ = projection.feature_cloud(i["dpt"], i["intrinsic"], cfg, monocular=bool(i["zoe"]))
    return {"pc": pts}


def _proj_pc2dpt(i):
    from freereg_lib.geometry import projection

    T_sensor_pc = np.linalg.inv(np.asarray(i["extrinsic"], dtype=np.float64))
    depth, _ = projection.project_to_depth(i["ply"], i["intrinsic"], T_sensor_pc,
                                           (int(i["h"]), int(i["w"])), pixel="official")
    return {"depth": depth}


def _return_uv(i):
    from freereg_lib.geometry import keypoints

    uv = keypoints.grid_keypoints((int(i["target_h"]), int(i["target_w"])), (int(i["hf"]), int(i["wf"])))
    return {"uv": uv.astype(np.int64)}


def _kpts_sampling(i):
    from freereg_lib.geometry import cameras

    s = dataset_setting(_scalar(i["config"]))
    uv = np.asarray(i["uv"])
    side = str(_scalar(i["type"]))
    z = cameras.nearest_sample(np.asarray(i["depth"]), uv).astype(np.float64)
    K = s["K_rgb"] if side == "rgb" else s["K_dpt"]
    if side != "rgb":
        z = z / s["dpt_scale"]
    return {"uv": uv, "xyz": cameras.lift(uv, z, K)}


def _pca_feat(i):
    from freereg_lib import features

    X = np.asarray(i["X"])
    k = int(i["n_components"])
    red, _ = features.pca_layers({0: X}, {0: X[:, :0, :]}, (0,), k)
    return {"Y": red[0].astype(np.float32)}


def _merge_feat(i):
    from freereg_lib import features

    layers = [int(k) for k in np.atleast_1d(i["checklayers"])]
    S = {k: i[f"s_layer{k}"] for k in layers}
    T = {k: i[f"t_layer{k}"] for k in layers}
    dim = int(i["pca_dim"])
    fs, ft = features.pca_reduce(S, T, layers, dim)
    out = {"fs": fs, "ft": ft}
    red_s, red_t = features.pca_layers(S, T, layers, dim)
    for k, a, b in zip(layers, red_s, red_t):
        out[f"fs_layer{k}_pca"], out[f"ft_layer{k}_pca"] = a.astype(np.float32), b.astype(np.float32)
    return out


def _feature_merge_on_kpts(i):
    from freereg_lib import features

    W, H = (int(x) for x in np.asarray(i["size_wh"]))
    weight = np.atleast_1d(np.asarray(i["weight"], dtype=np.float64))
    f_d = features.sample_features(np.asarray(i["df"]), i["kpts_uv"], (H, W)) if "df" in i else None
    if f_d is not None and "gf" in i:
        if not math.isclose(weight.sum(), 1.0):
            raise ValueError(f"weights {weight} do not sum to 1; fuse takes w and 1 - w")
        return {"f": features.fuse(f_d, np.asarray(i["gf"]), float(weight[0]))}
    part = f_d if f_d is not None else np.asarray(i["gf"])
    return {"f": (features.l2_normalize(part) * np.asarray(weight[0], part.dtype)).astype(part.dtype)}


def _find_corr(i):
    from freereg_lib.features import matching

    a, b = matching.mutual_nn(i["F0"], i["F1"])
    return {"inds0": a, "inds1": b}


def _feature_match(i):
    from freereg_lib.features import matching
    from freereg_lib.geometry import cameras, projection

    s = dataset_setting(_scalar(i["config"]))
    cfg = s["cfg"]
    depth = projection.clip_to_range(np.asarray(i["dpt_png_u16"]) / s["dpt_scale"], cfg.depth_min, cfg.depth_max)
    keep = np.flatnonzero(cameras.nearest_sample(depth, np.asarray(i["dpt_kpts_uv"])) > 0)
    a, b = matching.mutual_nn(i["sf"], np.asarray(i["tf"])[keep])
    return {"pps": np.stack([a, keep[b]], axis=1).astype(np.int64)}


def _feature_transfer_xyz(i):
    from freereg_lib.features import geometric

    cfg = dataset_setting(_scalar(i["config"]))["cfg"]
    return {"qf": geometric.pixel_features(i["query"], i["source"], np.asarray(i["source_f"]), cfg.tau_g)}


def _score_pair(rgb_uv, rgb_gtd, dpt_uv, dpt_gtd, pps, gt, K_rgb, K_dpt, rng, tau, few):
    """The project's per-pair scoring of matches ``pps`` in the official terms (gt maps the
    source camera into the target camera, the frame of the target's points)."""
    from freereg_lib.geometry import cameras, metrics

    pps = np.asarray(pps, dtype=np.int64).reshape(-1, 2)
    pts_t = metrics.lift_truth(np.asarray(dpt_uv)[pps[:, 1]], dpt_gtd, K_dpt, rng)
    uv_s = np.asarray(rgb_uv)[pps[:, 0]]
    T_cam_pc = np.linalg.inv(np.asarray(gt, dtype=np.float64))
    dist, ev, _ = metrics.match_distances(uv_s, pts_t, rgb_gtd, K_rgb, T_cam_pc, rng)
    correct = ev & (dist < tau)
    ir, inn = metrics.inlier_stats(correct, ev, few)
    ird = dist[ev]
    if ev.sum() < metrics.FEW_EVALUABLE and few == "official":
        ird = np.zeros(1)
    return {"gt_xyz_s": metrics.lift_truth(uv_s, rgb_gtd, K_rgb, rng)[ev], "gt_xyz_t": pts_t[ev],
            "ird": ird, "IN": inn, "IR": ir}


def _eval_pair(i):
    from freereg_lib.config import FreeRegConfig

    rng = (float(i["mask_min"]), float(i["mask_max"]))
    return _score_pair(i["rgb_kpts_uv"], i["rgb_gtd"], i["dpt_kpts_uv"], i["dpt_gtd"], i["pps"], i["gt"],
                       i["rgb_intrinsic"], i["dpt_intrinsic"], rng, float(i["ir_thres"]),
                       FreeRegConfig().eval_few_matches)


def _compute_T_err(i):
    from freereg_lib.geometry import cameras, metrics

    re, te = metrics.transform_errors(i["T"], i["T_gt"])
    return {"re": re, "te": te, "q_gt": cameras.quaternion_from_matrix(i["T_gt"][:3, :3]),
            "q": cameras.quaternion_from_matrix(i["T"][:3, :3])}


def _pipeline_eval_run(i):
    from freereg_lib.config import config_for
    from freereg_lib.geometry import metrics

    cfg = config_for(str(_scalar(i.get("config", "3dmatch"))))  # the manifest's setting: 3DMatch's thresholds
    named = {"mask_min": "depth_min", "mask_max": "depth_max", "ir_thres": "tau_c", "r_thres": "rr_rot_deg",
             "t_thres": "rr_trans_m"}
    cfg = cfg.override(**{f: float(i[k]) for k, f in named.items() if k in i})  # a case may name its own
    K = np.asarray(i["rgb_intrinsic"]) if "rgb_intrinsic" in i else _icl_K()
    K_d = np.asarray(i["dpt_intrinsic"]) if "dpt_intrinsic" in i else K
    uv_s = i.get("rgb_kpts_uv", i.get("kpts_uv"))
    uv_t = i.get("dpt_kpts_uv", i.get("kpts_uv"))
    n = len({k.split("_")[0] for k in i if k.startswith("pair")})
    rows = []
    for k in range(n):
        p = {key[len(f"pair{k}_"):]: v for key, v in i.items() if key.startswith(f"pair{k}_")}
        sc = _score_pair(uv_s, i["rgb_gtd"], uv_t, i["dpt_gtd"], p["pps"], p["gt"], K, K_d,
                         (cfg.depth_min, cfg.depth_max), cfg.tau_c, cfg.eval_few_matches)
        re, te = metrics.transform_errors(p["Tpre"], p["gt"])
        rows.append({"IR": sc["IR"], "IN": sc["IN"], "RE": re, "TE": te, "pair": k})
    agg = metrics.aggregate(rows, cfg.rr_rot_deg, cfg.rr_trans_m, cfg.fmr_ratio)
    col = {c: np.array([r[c] for r in rows]) for c in ("IR", "IN", "RE", "TE")}
    return {"FMR": agg["FMR"] / 100, "IR": agg["IR"] / 100, "IN": agg["IN"], "RE": agg["RE"], "TE": agg["TE"],
            "RR": agg["RR"] / 100, "RE_succ": agg["RE_reg"], "TE_succ": agg["TE_reg"],
            "irs": col["IR"], "ins": col["IN"].astype(np.int64), "res": col["RE"], "tes": col["TE"]}


def _gen_meta_run(i):
    from freereg_lib.data.datasets import kitti
    from freereg_lib.geometry import cameras, densify

    name = str(_scalar(i["config"]))
    s = dataset_setting(name)
    frames = sorted(int(k[len("depth"):]) for k in i if k.startswith("depth"))
    out = {f"dense{f}": densify.dense_png(i[f"depth{f}"], s["dpt_scale"], s["cfg"].densify) for f in frames}
    if "overlap" in i:
        from freereg_lib.data.datasets.scannet import scannet_official

        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "scene" / "query").mkdir(parents=True)
            np.savetxt(Path(tmp) / "scene" / "query" / "overlap.txt", np.asarray(i["overlap"]).reshape(-1, 3))
            entries = scannet_official(tmp)._build()
        pairs = [(int(e.image_frame), int(e.cloud_frame)) for e in entries]
    else:
        pairs = kitti.official_seq_pairs(len(frames))
    gts = []
    for q, d in pairs:
        T_cam_pc = cameras.invert(np.asarray(i[f"pose{q}"])) @ np.asarray(i[f"pose{d}"])  # as the loaders
        gt = np.linalg.inv(T_cam_pc)
        gts.append(kitti.trans_gt_for_kitti(gt) if name == "kitti" else gt)
    out["pairs"] = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    out["gts"] = np.array(gts).reshape(-1, 4, 4)
    return out


def _trans_gt_for_kitti(i):
    from freereg_lib.data.datasets import kitti

    return {"gt": kitti.trans_gt_for_kitti(i["gt"])}


def _pnpor_run(i):
    from freereg_lib.geometry import pose

    m = np.asarray(i["matches"], dtype=np.int64)
    res = pose.pnp_ransac(np.asarray(i["kpts_q"])[m[:, 0]], np.asarray(i["kpts_d"])[m[:, 1]], i["intrinsic"],
                          10.0, 50_000)
    if not res.success:
        raise ValueError(f"pnp_ransac failed: {res.reason}")
    return {"T": np.linalg.inv(res.T_cam_pc), "inlier": np.sort(res.inliers)}


def _pose_fn(name: str) -> Callable:
    from freereg_lib.geometry import pose

    fn = getattr(pose, name, None)
    if fn is None:
        raise Skip(f"pose.{name} not available yet")
    return fn


def _ransacor_run_after_ransac(i):
    refine = _pose_fn("official_refinement")
    m = np.asarray(i["match"], dtype=np.int64)
    trans, inl = refine(np.asarray(i["keys0"])[m[:, 0]], np.asarray(i["keys1"])[m[:, 1]], np.asarray(i["T0"]),
                        float(i["inlierd"]), bool(i["scaling"]))
    return {"trans": trans, "inlier": inl}


def _refine_trans(i):
    stage = _pose_fn("official_refine_stage")
    s, T, overlap = stage(np.asarray(i["key_m0"]), np.asarray(i["key_m1"]), np.asarray(i["T"]),
                          np.asarray(i["scores"]), float(i["inlinerdist"]), bool(i["scaling"]))
    return {"s": s, "Tnew": T, "overlap": overlap}


ADAPTERS: dict[str, Callable[[dict], dict]] = {
    "fill_in_fast": _fill_in_fast, "fill_in_multiscale": _fill_in_multiscale,
    "depth_normalize": _depth_normalize, "load_dpt": _load_dpt, "resize_image": _resize_image,
    "network_inputs": _network_inputs, "capture_timestep": _capture_timestep,
    "proj_depth": _proj_depth, "spconv_feature_extract": _spconv_feature_extract, "proj_pc2dpt": _proj_pc2dpt,
    "return_uv": _return_uv, "kpts_sampling": _kpts_sampling, "pca_feat": _pca_feat, "merge_feat": _merge_feat,
    "feature_merge_on_kpts": _feature_merge_on_kpts, "find_corr": _find_corr, "feature_match": _feature_match,
    "feature_transfer_xyz": _feature_transfer_xyz, "eval_pair": _eval_pair, "compute_T_err": _compute_T_err,
    "pipeline_eval_run": _pipeline_eval_run, "gen_meta_run": _gen_meta_run,
    "trans_gt_for_kitti": _trans_gt_for_kitti, "pnpor_run": _pnpor_run,
    "ransacor_run_after_ransac": _ransacor_run_after_ransac, "Refine_trans": _refine_trans,
}

TOLERANCES: dict[str, float | dict] = {
    "fill_in_fast": 1e-4, "fill_in_multiscale": 1e-4, "depth_normalize": 1, "load_dpt": 1, "resize_image": 1,
    "network_inputs": 1e-7, "capture_timestep": 0, "proj_depth": 1e-9, "spconv_feature_extract": 1e-9,
    "proj_pc2dpt": 1e-12, "return_uv": 0, "kpts_sampling": 1e-9, "pca_feat": 1e-3, "merge_feat": 1e-3,
    "feature_merge_on_kpts": 1e-6, "find_corr": 0, "feature_match": 0, "feature_transfer_xyz": 0,
    "eval_pair": 1e-9, "compute_T_err": {"re": 1e-4, "te": 1e-12, "q": 1e-9, "q_gt": 1e-9},
    "pipeline_eval_run": 1e-9, "gen_meta_run": {"dense": 1, "gts": 1e-12, "pairs": 0},
    "trans_gt_for_kitti": 0, "pnpor_run": {"T": 1e-5, "inlier": 0},
    "ransacor_run_after_ransac": {"trans": 1e-9, "inlier": 0}, "Refine_trans": 1e-9,
}
# Official outputs that are not the function's results (or not the project's business).
IGNORED = {"pnpor_run": {"T_true"}, "pipeline_eval_run": {"message"}}
# Outputs compared up to a sign per channel (PCA); pairs share one sign (one basis for both sides).
SIGNED = {"pca_feat": [("Y",)], "merge_feat": "fs/ft"}


# --------------------------------------------------------------------------------------
# Comparison.

def _tol(name: str, key: str) -> float:
    t = TOLERANCES.get(name, 0.0)
    if isinstance(t, dict):
        for k in sorted(t, key=len, reverse=True):
            if key == k or key.startswith(k):
                return float(t[k])
        return 0.0
    return float(t)


def _err(got, exp) -> float:
    """Max absolute difference; inf on a shape mismatch; exact match for integers."""
    g, e = np.asarray(got), np.asarray(exp)
    if g.shape != e.shape:
        if g.size == e.size == 0:
            return 0.0
        return math.inf
    if g.size == 0:
        return 0.0
    if e.dtype.kind in "US":
        return 0.0 if np.array_equal(g, e) else math.inf
    g64, e64 = np.atleast_1d(g.astype(np.float64)), np.atleast_1d(e.astype(np.float64))
    both_nan = np.isnan(g64) & np.isnan(e64)
    d = np.abs(g64 - e64)
    d[both_nan] = 0.0
    d[np.isnan(d)] = math.inf
    return float(d.max())


def _sign_groups(name: str, keys) -> list[tuple[str, ...]]:
    spec = SIGNED.get(name)
    if spec is None:
        return []
    if spec == "fs/ft":
        return [(k, "ft" + k[2:]) for k in keys if k.startswith("fs") and "ft" + k[2:] in keys]
    return list(spec)


def _align_signs(got: dict, exp: dict, group: tuple[str, ...]) -> None:
    """Flip each channel (axis 0) of the ``group``'s outputs in ``got`` by one common sign,
    the sign of the dot product with the official channels over the whole group."""
    if not all(k in got and k in exp and np.shape(got[k]) == np.shape(exp[k]) for k in group):
        return
    C = np.shape(exp[group[0]])[0]
    dots = np.zeros(C)
    for k in group:
        g = np.asarray(got[k], np.float64).reshape(C, -1)
        e = np.asarray(exp[k], np.float64).reshape(C, -1)
        dots += (g * e).sum(axis=1)
    sign = np.where(dots < 0, -1.0, 1.0)
    for k in group:
        got[k] = np.asarray(got[k], np.float64) * sign.reshape((C,) + (1,) * (np.ndim(got[k]) - 1))


def compare(name: str, got: dict, exp: dict) -> list[tuple[str, float, float]]:
    """``[(output, error, tolerance)]`` for every official output of one case."""
    got = dict(got)
    for k in list(got):
        if got[k] is None:
            got[k + "_is_none"] = True
            got[k] = np.zeros((0,) + np.shape(exp.get(k, np.zeros(0)))[1:])
        elif f"{k}_is_none" in exp and f"{k}_is_none" not in got:
            got[f"{k}_is_none"] = False
    for group in _sign_groups(name, list(exp)):
        _align_signs(got, exp, group)
    out = []
    for k, e in exp.items():
        if k in IGNORED.get(name, ()):
            continue
        if k not in got:
            out.append((k, math.inf, _tol(name, k)))
            continue
        out.append((k, _err(got[k], e), _tol(name, k)))
    return out


# --------------------------------------------------------------------------------------
# The runner.

def check_function(folder: Path, verbose: bool = False) -> dict:
    """Run one function folder: ``{"name", "status": ok | FAIL | skipped, "error", "tol",
    "reason", "cases": [(case, output, error, tol)]}``."""
    name = folder.name
    res = {"name": name, "status": "ok", "error": 0.0, "tol": _tol(name, ""), "reason": "", "cases": []}
    adapter = ADAPTERS.get(name)
    if adapter is None:
        return {**res, "status": "skipped", "reason": "no counterpart of this function in the project"}
    cases = sorted(folder.glob("*.npz"))
    if not cases:  # a function with no case is not checked: not a pass
        return {**res, "status": "FAIL", "reason": f"no <case>.npz in {folder}", "error": math.inf}
    worst = -1.0
    for case in cases:
        try:
            ins, outs = load_case(case)
        except BadFixture as exc:
            res.update(status="FAIL", reason=str(exc), error=math.inf, bad_input=True)
            continue
        try:
            got = adapter(ins)
        except Skip as exc:
            return {**res, "status": "skipped", "reason": str(exc)}
        except Exception as exc:  # a crash is a failure, with its reason
            res.update(status="FAIL", reason=f"{case.stem}: {type(exc).__name__}: {exc}", error=math.inf)
            res["cases"].append((case.stem, "*", math.inf, res["tol"]))
            continue
        for key, err, tol in compare(name, got, outs):
            res["cases"].append((case.stem, key, err, tol))
            rel = err / tol if tol > 0 else (0.0 if err == 0 else math.inf)
            if rel > worst or worst < 0:
                worst = rel
                res["error"], res["tol"] = err, tol
            if not err <= tol:
                res["status"] = "FAIL"
    return res


def run(directory: str | Path = DEFAULT_DIR, verbose: bool = False, out=None) -> int:
    """Check every function folder of ``directory``; print the lines; return the exit status."""
    out = out or sys.stdout
    directory = Path(directory)
    if not directory.is_dir():
        print(f"no fixture folder {directory}", file=out)
        return 2
    try:
        manifest = read_manifest(directory / "manifest.json")
    except BadFixture as exc:
        print(exc, file=out)
        return 2
    folders = sorted((p for p in directory.iterdir() if p.is_dir()), key=lambda p: p.name.lower())
    if not folders:
        print(f"no function folder (<function>/<case>.npz) in {directory}: nothing checked", file=out)
        return 2
    bad_input = False
    counts = {"ok": 0, "FAIL": 0, "skipped": 0}
    for folder in folders:
        r = check_function(folder, verbose)
        bad_input |= bool(r.get("bad_input"))
        counts[r["status"]] += 1
        print(format_line(r), file=out)
        if verbose:
            if folder.name in manifest:
                print(f"    official: {manifest[folder.name].get('official', '?')}", file=out)
            for case, key, err, tol in r["cases"]:
                flag = "" if err <= tol else "  <-- over"
                print(f"    {case}/{key}: {_fmt(err)} (tolerance {_fmt(tol)}){flag}", file=out)
    missing = sorted(set(manifest) - {p.name for p in folders})
    for name in missing:  # the manifest promises its cases: a set missing some is not a pass
        print(f"{name}: FAIL [the manifest lists it, and {directory / name} does not exist: the fixture set is "
              "incomplete; copy that folder again]", file=out)
        counts["FAIL"] += 1
    print(f"{len(folders) + len(missing)} functions: {counts['ok']} ok, {counts['FAIL']} FAIL, "
          f"{counts['skipped']} skipped", file=out)
    return 2 if bad_input else (1 if counts["FAIL"] else 0)  # 2: a fixture file that cannot be read


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python tools/parity.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("directory", nargs="?", default=str(DEFAULT_DIR),
                    help=f"fixture folder (<function>/<case>.npz + manifest.json); default {DEFAULT_DIR}")
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per case and output")
    args = ap.parse_args(argv)
    return run(args.directory, args.verbose)


if __name__ == "__main__":
    sys.exit(main())
