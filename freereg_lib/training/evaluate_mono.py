"""The paper's mono-modality table (Table 10, mono-modality registration) on the micro models.

    python -m freereg_lib.training.evaluate_mono --split test --pairs 100 --rows runs/micro/mono/rows.jsonl
    python -m freereg_lib.training.evaluate_mono --split test --summarize --rows runs/micro/mono/rows.jsonl
        --out freereg_lib/models/micro/weights/mono_modality_test.json

A synthetic indoor pair has two cameras: the image camera A (the pair's RGB image, true depth
``pair.depth_gt``) and the depth camera B, whose rendered depth frame (``pair.depth_frame_gt``)
is sampled into the pair's 60,000-point cloud. The renderer can also shade B's colour image
(``make_pair(..., depth_camera_image=True)``; the pair is otherwise bit-identical). Per pair the
same two views are registered three ways, each with fused FreeReg (``cfg.fusion_w`` = 0.5;
decoder layers ``cfg.layers``, joint PCA of the two sides; FPFH, ``cfg.geometric``; mutual
nearest neighbours; the config's 50,000 RANSAC iterations), and scored against the same truth
(:func:`freereg_lib.pipeline.evaluate`: each side's keypoints lifted with its own frame's true
depth, A's ``depth_gt`` and B's ``depth_frame_gt``):

* ``RGB`` (RGB to RGB): the diffusion features of both colour images (the UNet path; B's image
  gets forward noise of its own, ``noise_tag="depth-camera-image"``, as the diagnosis does, so
  the two sides do not share a pixel-aligned draw); the micro monocular depth of both images lifts
  the keypoints (for Kabsch) and gives both FPFH clouds (the monocular edge filter on both).
  Kabsch-RANSAC with scale (both sides are monocular estimates).
* ``DPT`` (depth to depth): "registration on point clouds recovered from depth maps", sensor
  depth on both sides, the depth branch (ControlNet-guided DDIM, features at t_hat) on both. A's
  map is its true depth frame made a depth view (:func:`freereg_lib.pipeline.depth_view` of the
  pair with ``sensor_depth = depth_gt``: densified, range-clipped), its DDIM draws seeded with the
  noise seed + :data:`DEPTH_A_SEED_OFFSET` (their own draws, as B's image in ``RGB``); B's map is
  the cross-modality depth side itself (the cloud projected and densified; its maps shared with
  ``cross``). Each map lifts its keypoints and gives its FPFH cloud (no edge filter). Kabsch-RANSAC.
* ``cross`` (image to cloud, the paper's Table 1 setting): FreeReg as the pipeline runs it, A's
  image against B's cloud (:func:`freereg_lib.pipeline.compute_features` gives the same
  features, which the tests check); Kabsch-RANSAC and PnP-RANSAC (PnP only here: it is the
  image-to-cloud solver).

Every row's features are built by :func:`mono_features` from two :class:`Side` records, so the
three rows differ only in what each side is given. Nothing is chosen on these numbers, so the test
split is used directly. ``--summarize`` writes FMR, IR, IN, RR (with 95 % bootstrap intervals over
pairs), median RE / TE, and paired permutation tests of each mono-modality row against ``cross``
(and ``DPT`` against ``RGB``).
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freereg_lib.training.evaluate_split import (
    _done, _plain, _stat, load_average_range, paired_difference, result_lines, split_command,
)
from freereg_lib.training.splits import SPLITS

MODALITIES = ("RGB", "DPT", "cross")
SOLVERS = {"RGB": ("kabsch",), "DPT": ("kabsch",), "cross": ("kabsch", "pnp")}
ROW_KEYS = ("modality", "solver", "n_matches", "IR", "IN", "RE", "TE", "registered", "n_evaluable", "error")
DEPTH_A_SEED_OFFSET = 1  # the DDIM draws of A's depth map: noise seed + 1 (B's map keeps the pipeline's)
TESTS = (("RGB", "cross"), ("DPT", "cross"), ("DPT", "RGB"))


@dataclass
class Side:
    """What one view of a pair hands the matcher.

    ``maps``: decoder maps ``{layer: (C, h, w) float32}`` (of an image or a depth map);
    ``lift (H, W)``: the depth in metres that lifts the keypoints (0 / NaN: none); ``cloud (H, W)``:
    the depth map whose back-projection gives the geometric features; ``monocular``: whether that
    map is a monocular estimate (:func:`~freereg_lib.geometry.projection.feature_cloud`'s edge filter).
    """

    maps: dict
    lift: np.ndarray
    cloud: np.ndarray
    monocular: bool


def mono_features(pair, a: Side, b: Side, cfg, backend, geometric: bool = True):
    """:class:`~freereg_lib.pipeline.PairFeatures` of side ``a`` (the image camera: every keypoint
    of the grid kept, NaN points where ``a.lift`` has no depth) against side ``b`` (the depth
    camera: only keypoints where ``b.lift > 0``, their points in the cloud's frame), as
    :func:`~freereg_lib.pipeline.compute_features` builds them from an image and a depth view."""
    from freereg_lib import features, pipeline
    from freereg_lib.features import geometric as geo
    from freereg_lib.geometry import cameras, keypoints, projection

    uv_a = keypoints.grid_keypoints(pair.image_size, cfg.keypoint_grid)
    z_a = cameras.nearest_sample(np.asarray(a.lift, dtype=np.float64), uv_a)
    z_a = np.where(np.isfinite(z_a) & (z_a > 0), z_a, np.nan)  # unlifted keypoints stay, as the image side's
    pts_a = cameras.lift(uv_a, z_a, pair.K_image)
    uv_b = keypoints.grid_keypoints(pair.depth_size, cfg.keypoint_grid)
    z_b = cameras.nearest_sample(np.asarray(b.lift, dtype=np.float64), uv_b)
    keep = np.isfinite(z_b) & (z_b > 0)
    if not keep.any():
        raise ValueError(f"pair {pair.name}: no keypoint of the second view has a depth")
    uv_b, pts_b_cam = uv_b[keep], cameras.lift(uv_b[keep], z_b[keep], pair.K_depth)
    f_a, f_b = features.pca_reduce(a.maps, b.maps, cfg.layers, cfg.pca_dim, device=cfg.pca_device)
    diff_a = features.sample_features(f_a, uv_a, pair.image_size)
    diff_b = features.sample_features(f_b, uv_b, pair.depth_size)
    geo_a = geo_b = None
    if geometric:  # each cloud in its own camera's frame, as compute_features (FCGF is not rotation invariant)
        cloud_a, _ = projection.feature_cloud(a.cloud, pair.K_image, cfg, monocular=a.monocular)
        cloud_b, _ = projection.feature_cloud(b.cloud, pair.K_depth, cfg, monocular=b.monocular)
        good = np.isfinite(pts_a).all(1)
        down_a, feats_a = geo.geometric_features(cloud_a, cfg, at=pts_a[good], backend=backend)
        down_b, feats_b = geo.geometric_features(cloud_b, cfg, at=pts_b_cam, backend=backend)
        geo_a = np.zeros((len(uv_a), feats_a.shape[1]))
        geo_a[good] = geo.pixel_features(pts_a[good], down_a, feats_a, cfg.tau_g)
        geo_b = geo.pixel_features(pts_b_cam, down_b, feats_b, cfg.tau_g)
    return pipeline.PairFeatures(uv_a, pts_a, uv_b, cameras.transform(pair.T_pc_sensor, pts_b_cam), diff_a, diff_b,
                                 geo_a, geo_b, np.asarray(a.lift, dtype=np.float64), None)


def image_camera_view(pair, cfg):
    """A's true depth frame as a depth view (:func:`~freereg_lib.pipeline.depth_view` of the pair
    with A as its depth camera and ``depth_gt`` as its sensor depth: densified and clipped as B's)."""
    import dataclasses

    from freereg_lib import pipeline
    from freereg_lib.geometry import cameras

    swapped = dataclasses.replace(pair, sensor_depth=pair.depth_gt, K_depth=pair.K_image, depth_size=pair.image_size,
                                  T_pc_sensor=cameras.invert(pair.T_cam_pc), meta=dict(pair.meta))
    return pipeline.depth_view(swapped, cfg)


def sides(pair, backend, cfg) -> tuple[dict[str, tuple[Side, Side]], dict[str, float]]:
    """``({modality: (side A, side B)}, {part: seconds})`` of a pair made with
    ``depth_camera_image=True`` (:data:`MODALITIES`, as the module's docstring says)."""
    from freereg_lib import pipeline
    from freereg_lib.geometry import projection

    image_b = pair.meta.get("depth_camera_image")
    if image_b is None or pair.depth_frame_gt is None:
        raise ValueError(f"pair {pair.name} holds no depth-camera image or depth frame; make it with "
                         "synthetic.make_pair(..., depth_camera_image=True)")
    sec = {}
    t0 = time.perf_counter()
    view, view_a = pipeline.depth_view(pair, cfg), image_camera_view(pair, cfg)
    rgb_a, dep_b = pipeline.diffusion_maps_batch([pair], [view], backend, cfg.layers)[0]  # the pipeline's own
    sec["cross diffusion"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mono_a = backend.mono_depth(pair.image, depth_gt=pair.depth_gt)
    mono_b = backend.mono_depth(image_b, depth_gt=pair.depth_frame_gt)
    sec["monocular depth"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hint_a, hint_b = (pipeline.scene_hints(pair, view) if getattr(backend, "uses_scene_hints", False) else ({}, {}))
    if hasattr(backend, "diffusion"):  # the torch backends: draws of their own for the second image and map
        from freereg_lib.models.diffusion import DiffusionFeatures

        D = backend.diffusion
        rgb_b = D.rgb_batch([image_b], cfg.layers, noise_tag="depth-camera-image")[0]
        sec["RGB diffusion"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        D_a = DiffusionFeatures(D.unet, D.controlnet, D.vae, D.text_encoder, D.tokenizer,
                                D.cfg.override(seed=D.cfg.seed + DEPTH_A_SEED_OFFSET), D.device, D.dtype,
                                D.resize_hw, D.a_prompt)  # the same modules, another seed
        dep_a = D_a.depth_batch([view_a.hint_depth], cfg.layers)[0]
    else:  # the stub: its features read the scene's ids (B's image: the depth view's; A's map: the image's)
        rgb_b = backend.diffusion_rgb_batch([image_b], [hint_b], cfg.layers)[0]
        sec["RGB diffusion"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        dep_a = backend.diffusion_depth_batch([view_a.hint_depth], [hint_a], cfg.layers)[0]
    sec["DPT diffusion"] = time.perf_counter() - t0
    lift_b = projection.clip_to_range(mono_b, cfg.depth_min, cfg.depth_max)  # B's keypoints in range, as its view's
    return {"RGB": (Side(rgb_a, mono_a, mono_a, True), Side(rgb_b, lift_b, mono_b, True)),
            "DPT": (Side(dep_a, view_a.dense, view_a.hint_depth, False), Side(dep_b, view.dense, view.hint_depth, False)),
            "cross": (Side(rgb_a, mono_a, mono_a, True), Side(dep_b, view.dense, view.hint_depth, False))}, sec


def pair_rows(pair, backend, cfg) -> tuple[list[dict], dict[str, float]]:
    """The rows of one pair (a row per modality and solver, :data:`SOLVERS`) and the seconds of
    its parts; a failure becomes rows with ``error`` set, as :func:`~freereg_lib.pipeline.run_pair`."""
    from freereg_lib import pipeline

    try:
        by_modality, sec = sides(pair, backend, cfg)
    except Exception as exc:  # scored as run_pair scores a failed pair
        by_modality, sec = {m: exc for m in MODALITIES}, {}
    rows = []
    for m in MODALITIES:
        t0 = time.perf_counter()
        feats = by_modality[m]
        if not isinstance(feats, Exception):
            try:
                feats = mono_features(pair, *feats, cfg, backend)
            except Exception as exc:
                feats = exc
        for r in pipeline.variant_rows(pair, feats, cfg, [("FreeReg", s) for s in SOLVERS[m]]):
            rows.append({"modality": m, **{k: _plain(r.get(k)) for k in ROW_KEYS if k != "modality"}})
        sec[f"{m} geometric, matching, solving"] = time.perf_counter() - t0
    return rows, {k: round(v, 3) for k, v in sec.items()}


def run(split_name: str, n_pairs: int, rows_path: Path, backend_name: str = "micro", progress: bool = True,
        **changes) -> None:
    """Append the rows of the split's pairs ``k < n_pairs`` not yet in ``rows_path``; ``changes``
    override the config (the tests' fewer RANSAC iterations)."""
    from tqdm import tqdm

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed).override(**changes) if changes else FreeRegConfig(seed=split.noise_seed)
    backend = get_backend(backend_name, cfg, device="cpu")
    done = _done(rows_path)
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    for k in tqdm([k for k in range(n_pairs) if k not in done], desc=f"Table 10, {split.name} split",
                  disable=not progress):
        seed = split.pair_seeds(k + 1)[k]
        synthetic.check_eval_seed(seed)
        t0 = time.perf_counter()
        pair = synthetic.make_pair("indoor", seed=seed, depth_camera_image=True, world=split.world)
        rows, sec = pair_rows(pair, backend, cfg)
        rec = {"k": k, "pair_seed": seed, "pair": pair.name, "label": backend.label, "config_changes": changes,
               "load_average": round(os.getloadavg()[0], 2), "seconds": round(time.perf_counter() - t0, 1),
               "seconds_parts": sec, "rows": rows}
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def _median(v) -> float | None:
    v = [x for x in v if x is not None]
    return float(np.median(v)) if v else None


def summarize(recs: list[dict], split_name: str) -> dict:
    """Per modality and solver: FMR, IR, RR (%, 95 % bootstrap intervals), IN (mean count), median
    RE / TE of the solved poses, failures; paired tests of :data:`TESTS` (RR, Kabsch; IR)."""
    from freereg_lib.config import FreeRegConfig

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    per = {}
    for m in MODALITIES:
        for s in SOLVERS[m]:
            rows = [next(r for r in rec["rows"] if r["modality"] == m and r["solver"] == s) for rec in recs]
            ir = [r["IR"] or 0.0 for r in rows]
            reg = [int(bool(r["registered"])) for r in rows]
            per[f"{m} {s}"] = {"FMR": _stat(np.asarray(ir) > cfg.fmr_ratio), "IR": _stat(ir), "RR": _stat(reg),
                               "IN": float(np.mean([r["IN"] or 0 for r in rows])),
                               "RE_median": _median([r["RE"] for r in rows]), "TE_median": _median([r["TE"] for r in rows]),
                               "errors": sum(1 for r in rows if r["error"]), "n_rows": len(rows),
                               "IR_per_pair": ir, "registered_per_pair": reg}
    tests = {}
    for a, b in TESTS:
        x, y = per[f"{a} kabsch"], per[f"{b} kabsch"]
        tests[f"RR kabsch: {a} - {b}"] = paired_difference(x["registered_per_pair"], y["registered_per_pair"])
        tests[f"IR: {a} - {b}"] = paired_difference(x["IR_per_pair"], y["IR_per_pair"])
    parts = sorted({k for r in recs for k in r.get("seconds_parts", {})})
    return {"split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed, "n_pairs": len(recs),
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(recs) - 1}",
            "backend": recs[0]["label"] if recs else None, "config_changes": recs[0].get("config_changes", {}) if recs else {},
            "config": {"fusion_w": cfg.fusion_w, "layers": list(cfg.layers), "geometric": cfg.geometric,
                       "ransac_iters": cfg.ransac_iters, "fmr_ratio": cfg.fmr_ratio, "tau_c": cfg.tau_c,
                       "rr_rot_deg": cfg.rr_rot_deg, "rr_trans_m": cfg.rr_trans_m},
            "results": per, "tests": tests,
            "seconds_per_pair": _median([r["seconds"] for r in recs]),
            "seconds_parts": {p: _median([r["seconds_parts"].get(p) for r in recs]) for p in parts},
            "load_average": load_average_range(recs),
            "note": "Fused FreeReg (w = 0.5) on both views of each pair: RGB = both colour images (UNet features, micro "
                    "monocular depth of both), DPT = both depth maps (ControlNet-guided DDIM features, sensor depth of "
                    "both), cross = the image against the cloud (Table 1's setting); Kabsch with scale, PnP for cross "
                    "only. IR / FMR / RR in %, IN a count, RE degrees / TE metres (medians of solved poses); intervals: "
                    "95 % percentile bootstrap over pairs; p: two-sided paired sign-flip permutation test; errors: rows whose "
                    "features or pose failed (a solver's refusal included), scored not registered; seconds: "
                    "medians of the CPU's wall clock, with its 1-minute load average range."}


def report(res: dict) -> str:
    lines = [f"Table 10 on the {res['split']} split: {res['n_pairs']} synthetic indoor pairs ({res['pair_seeds']}), "
             f"{res['backend']}", "  modality solver   FMR    IR     IN      RR  [95 % interval]"]
    return "\n".join(lines + result_lines(res, 15))


def main(argv=None) -> int:
    from freereg_lib.training.command_inputs import exit_on_bad_rows

    exit_on_bad_rows(argv, "evaluate_mono", "modality")  # one line, exit 2, before any pair runs
    return split_command("freereg_lib.training.evaluate_mono", __doc__, run, summarize, report, argv)


if __name__ == "__main__":
    raise SystemExit(main())
