"""How much of the geometric half's inlier ratio a monocular depth keeps.

FreeReg-G (FPFH) on a split's pairs with the config of the split evaluation
(:mod:`freereg_lib.training.evaluate_split`: the paper's defaults, the split's noise seed), its image
side lifted with each depth source in turn, its depth side the sensor's cloud as always:

* ``true``: the image's true depth, the ceiling no depth model can pass;
* ``true at 96 x 128``: the true depth brought to the micro ZoeDepth's output size and back
  (area, then bicubic), the ceiling at that model's resolution;
* each micro ZoeDepth weights folder given (the full inference path,
  :func:`freereg_lib.models.micro.depth.load`);
* for the first folder, its error split in two bands (:func:`error_bands`): the true depth times
  the model's log error coarser than ``--band-px`` pixels, and times the finer rest; which band
  costs the inliers says whether a model needs a better overall layout or better local shape.

Per source: IR (the official per-pair measure, :func:`freereg_lib.geometry.metrics.inlier_stats` of
:func:`freereg_lib.pipeline.steps.correct_matches`) with a 95 % bootstrap interval over pairs, the
depth's mean absolute error over valid pixels, and each model's IR against the first model's with a
paired permutation test. IR does not depend on the solver, so none runs.

    python -m freereg_lib.training.depth_ceiling --split rooms-dev \\
        --weights freereg_lib/models/micro/weights/depth runs/micro/rooms/depth_weights \\
        --out freereg_lib/models/micro/weights/rooms/depth_ceiling_dev.json
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

MODEL_HW = (96, 128)  # the micro ZoeDepth's output size (its processor's input)
BAND_PX = 40.0  # the Gaussian sigma (image pixels) between the coarse and the fine error band


def at_resolution(depth: np.ndarray, hw: tuple[int, int] = MODEL_HW) -> np.ndarray:
    """``(H, W) float64`` depth brought to ``hw`` (area average) and back (bicubic); holes (0) stay holes."""
    import cv2

    small = cv2.resize(depth.astype(np.float32), (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
    back = cv2.resize(small, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_CUBIC)
    return np.where(depth > 0, back, 0.0).astype(np.float64)


def error_bands(depth: np.ndarray, truth: np.ndarray, sigma_px: float = BAND_PX) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W) float64`` depths ``truth * exp(coarse)`` and ``truth * exp(fine)``, where the log error
    ``log(depth) - log(truth)`` on pixels with a true depth is ``coarse + fine``: ``coarse`` is its
    Gaussian average of ``sigma_px`` over those pixels only (a normalised convolution, so holes do not
    pull it to 0), ``fine`` the rest. Holes (truth 0) stay holes in both."""
    import cv2

    valid = (truth > 0) & (depth > 0)
    err = np.zeros(truth.shape, np.float64)
    err[valid] = np.log(depth[valid]) - np.log(truth[valid])

    def blur(x):
        return cv2.GaussianBlur(x, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)

    weight = blur(valid.astype(np.float64))
    coarse = np.where(valid, blur(err) / np.maximum(weight, 1e-12), 0.0)
    return np.where(valid, truth * np.exp(coarse), 0.0), np.where(valid, truth * np.exp(err - coarse), 0.0)


def band_names(folder: str, sigma_px: float = BAND_PX) -> tuple[str, str]:
    return (f"true x the coarse error (> {sigma_px:g} px) of {folder}",
            f"true x the fine error (< {sigma_px:g} px) of {folder}")


def geometric_ir(pair, depth: np.ndarray, backend, cfg) -> tuple[float, int]:
    """FreeReg-G's IR (fraction) on ``pair`` with ``depth`` as the image side's depth, and the number
    of evaluable matches (below 3 the official IR is 1, ``cfg.eval_few_matches``)."""
    from freereg_lib.geometry import metrics
    from freereg_lib.pipeline import steps

    feats = steps.compute_features(pair, backend, cfg, diffusion=False, geometric=True, mono=depth)
    m = steps.match(feats, 0.0)
    correct, evaluable = steps.correct_matches(pair, feats, m, cfg)
    return float(metrics.inlier_stats(correct, evaluable, cfg.eval_few_matches)[0]), int(np.count_nonzero(evaluable))


def mean_abs_error(depth: np.ndarray, truth: np.ndarray) -> float:
    """Mean |depth - truth| (m) over pixels with a true depth."""
    valid = truth > 0
    return float(np.abs(depth[valid] - truth[valid]).mean())


def measure(pairs, weights: list[str], cfg, progress: bool = True, band_px: float = BAND_PX) -> dict[str, list[dict]]:
    """Per source name, one ``{"pair", "IR", "n_evaluable", "MAE"}`` row per pair, with ``cfg``; the
    first folder's error bands (:func:`error_bands`) as two more sources."""
    from tqdm.auto import tqdm

    from freereg_lib.models import get_backend
    from freereg_lib.models.micro import depth as micro_depth

    backend = get_backend("stub", cfg)  # no monocular depth is asked of it: every source is given
    models = {w: micro_depth.load(w) for w in weights}
    bands = band_names(weights[0], band_px) if weights else ()
    rows: dict[str, list[dict]] = {"true": [], "true at 96 x 128": [], **{w: [] for w in weights},
                                   **{b: [] for b in bands}}
    for pair in tqdm(pairs, desc="pairs", disable=not progress):
        sources = {"true": pair.depth_gt, "true at 96 x 128": at_resolution(pair.depth_gt)}
        sources.update({w: np.asarray(est(pair.image), dtype=np.float64) for w, est in models.items()})
        if bands:
            sources.update(zip(bands, error_bands(sources[weights[0]], pair.depth_gt, band_px)))
        for name, depth in sources.items():
            ir, n_evaluable = geometric_ir(pair, depth, backend, cfg)
            rows[name].append({"pair": pair.name, "IR": ir, "n_evaluable": n_evaluable,
                               "MAE": mean_abs_error(depth, pair.depth_gt)})
    return rows


def summarize(rows: dict[str, list[dict]], weights: list[str]) -> dict:
    """IR (%) and MAE (m) per source, mean with a bootstrap interval; models against the first model."""
    from freereg_lib.training.evaluate import bootstrap_ci, paired_permutation_p

    out = {}
    for name, rs in rows.items():
        ir = 100 * np.asarray([r["IR"] for r in rs])
        mae = np.asarray([r["MAE"] for r in rs])
        out[name] = {"IR": {"mean": float(ir.mean()), "ci95": [float(v) for v in bootstrap_ci(ir)]},
                     "MAE_m": {"mean": float(mae.mean()), "ci95": [float(v) for v in bootstrap_ci(mae)]},
                     "n_few_evaluable": sum(r["n_evaluable"] < 3 for r in rs)}
    first = 100 * np.asarray([r["IR"] for r in rows[weights[0]]]) if weights else None
    for w in weights[1:]:
        other = 100 * np.asarray([r["IR"] for r in rows[w]])
        out[w]["against_first_model"] = {"diff": float((other - first).mean()),
                                         "p": float(paired_permutation_p(other, first))}
    return out


def table(summary: dict) -> str:
    lines = ["| image-side depth | FreeReg-G IR % [95 %] | depth MAE, m | pairs with < 3 evaluable matches |",
             "|---|---|---|---|"]
    for name, s in summary.items():
        vs = s.get("against_first_model")
        extra = f" ({vs['diff']:+.1f} against the first model, p = {vs['p']:.3f})" if vs else ""
        lines.append(f"| {name} | {s['IR']['mean']:.1f} [{s['IR']['ci95'][0]:.1f}, {s['IR']['ci95'][1]:.1f}]{extra} "
                     f"| {s['MAE_m']['mean']:.3f} | {s['n_few_evaluable']} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.training.evaluate_split import publish, stamped
    from freereg_lib.training.splits import SPLITS, guard_eval_seed

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="rooms-dev", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=None, help="the first N pairs of the split (default: all)")
    p.add_argument("--weights", nargs="*", default=[], help="micro ZoeDepth folders")
    p.add_argument("--band-px", type=float, default=BAND_PX,
                   help="Gaussian sigma (pixels) between the first model's coarse and fine error bands")
    p.add_argument("--out", default=None, help="write the rows and the summary here (JSON)")
    a = p.parse_args(argv)
    if a.band_px <= 0:
        p.error(f"--band-px must be > 0, got {a.band_px}")
    split = SPLITS[a.split]
    n = split.n_pairs if a.pairs is None else a.pairs
    guard_eval_seed(split.seed, n)
    cfg = FreeRegConfig(seed=split.noise_seed)
    pairs = [synthetic.make_pair("indoor", seed=s, world=split.world) for s in split.pair_seeds(n)]  # as evaluate_split
    rows = measure(pairs, list(a.weights), cfg, band_px=a.band_px)
    summary = summarize(rows, list(a.weights))
    res = stamped({"split": split.name, "dataset_seed": split.seed, "n_pairs": n,
                   "config": {"geometric": cfg.geometric, "densify": cfg.densify, "seed": cfg.seed},
                   "band_px": a.band_px,
                   "summary": summary, "rows": rows,
                   "command": "python -m freereg_lib.training.depth_ceiling " + " ".join(sys.argv[1:] if argv is None else argv)})
    publish(res, table(summary), a.out)


if __name__ == "__main__":
    main()
