"""The fusion weight w for the micro models, chosen on the development set, reported on the test split once.

    python -m freereg_lib.training.fusion_sweep --split dev --cache runs/micro/split43/feat_dev
        --w 0.3 0.4 0.5 0.6 0.7 0.8 0.9 --solvers kabsch --out runs/micro/split43/sweep_dev.json
    python -m freereg_lib.training.fusion_sweep --split test --cache runs/micro/split43/feat_test
        --w <the chosen w> --solvers kabsch pnp --out freereg_lib/models/micro/weights/test_split_w.json

Reads the features :mod:`.evaluate_split` cached per pair (``--cache``; the same pairs, noise seed and
features as its rows), re-matches them at each w and solves (Kabsch-RANSAC and / or PnP-RANSAC), scored
as :func:`freereg_lib.pipeline.evaluate`. The rule, fixed before the development run: the w with the
highest mean IR on the development set (the fusion claim's measure; Kabsch RR breaks a tie). Each w is
compared with w = 1 (FreeReg-D) and w = 0 (FreeReg-G) on the same pairs (paired permutation tests).

``--fpfh VOXEL:FACTOR ...`` first recomputes the geometric half with each FPFH setting (``cfg.fpfh_voxel``,
``cfg.fpfh_radius_factor``; the micro depth as before) and keeps the one with the highest FreeReg-G IR
(w = 0) on the split, then sweeps w with it: on the development set that is the choice, on the test
split pass the chosen setting alone.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib.training.evaluate import paired_permutation_p
from freereg_lib.training.evaluate_split import _git_head, _stat, load_features, publish
from freereg_lib.training.splits import SPLITS


def _ir(pair, feats, w, cfg) -> float:
    from freereg_lib import pipeline
    from freereg_lib.geometry import metrics

    m = pipeline.match(feats, w)
    return metrics.inlier_stats(*pipeline.correct_matches(pair, feats, m, cfg), cfg.eval_few_matches)[0]


def choose_fpfh(split, pairs_feats, settings: list[tuple[float, float]], cfg, weights_dir=None) -> tuple[dict, list]:
    """Per setting, FreeReg-G's IR; the geometric features of the best setting replace the cached ones.
    ``weights_dir``: the micro weights whose depth model lifted the cached features (None: the committed)."""
    from dataclasses import replace

    from freereg_lib import pipeline
    from freereg_lib.models import get_backend

    backend = get_backend("micro", cfg, device="cpu", weights_dir=weights_dir)
    geo = {st: [] for st in settings}
    irs = {st: [] for st in settings}
    for pair, feats in tqdm(pairs_feats, desc=f"FPFH settings, {split.name}"):
        mono = backend.mono_depth(pair.image, depth_gt=pair.depth_gt)
        for st in settings:
            c = cfg.override(fpfh_voxel=st[0], fpfh_radius_factor=st[1])
            g = pipeline.compute_features(pair, backend, c, diffusion=False, geometric=True, mono=mono)
            f = replace(feats, geo_image=g.geo_image, geo_depth=g.geo_depth)
            geo[st].append(f)
            irs[st].append(_ir(pair, f, 0.0, cfg))
    best = max(settings, key=lambda st: np.mean(irs[st]))
    table = {f"{v:g}:{k:g}": {"FreeReg-G IR": _stat(irs[(v, k)]), "IR_per_pair": irs[(v, k)]} for v, k in settings}
    return {"settings": table, "best": f"{best[0]:g}:{best[1]:g}",
            "rule": "the FPFH setting with the highest FreeReg-G IR (w = 0)"}, [
        (p, f) for (p, _), f in zip(pairs_feats, geo[best])]


def sweep(split_name: str, cache: Path, ws: list[float], solvers: list[str], n_pairs: int | None = None,
          fpfh: list[tuple[float, float]] | None = None, weights_dir=None) -> dict:
    from freereg_lib import pipeline
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    n = n_pairs or split.n_pairs
    missing = [k for k in range(n) if not (Path(cache) / f"{k}.npz").exists()]
    if missing:
        raise SystemExit(f"{cache}: no cached features for pairs {missing[:10]}{' ...' if len(missing) > 10 else ''}"
                         " (evaluate_split --cache)")
    ws = sorted(set(ws) | {0.0, 1.0}, reverse=True)
    per = {(w, s): {"IR": [], "reg": []} for w in ws for s in solvers}
    pairs_feats = [(synthetic.make_pair("indoor", seed=split.pair_seeds(k + 1)[k], world=split.world),
                    load_features(Path(cache) / f"{k}.npz")) for k in range(n)]
    fpfh_choice = None
    if fpfh:
        fpfh_choice, pairs_feats = choose_fpfh(split, pairs_feats, fpfh, cfg, weights_dir)
    for pair, feats in tqdm(pairs_feats, desc=f"w sweep, {split.name}"):
        for w in ws:
            m = pipeline.match(feats, w)
            for s in solvers:
                res = pipeline.solve(pair, feats, m, cfg, s)
                sc = pipeline.evaluate(pair, feats, m, res, cfg)
                per[(w, s)]["IR"].append(sc["IR"])
                per[(w, s)]["reg"].append(float(sc["registered"]))
    out = {}
    for (w, s), v in per.items():
        d, g = per[(1.0, s)], per[(0.0, s)]
        out[f"w={w:g} {s}"] = {
            "w": w, "solver": s, "IR": _stat(v["IR"]), "RR": _stat(v["reg"]),
            "IR_minus_D": 100 * float(np.mean(v["IR"]) - np.mean(d["IR"])), "p_IR_vs_D": paired_permutation_p(v["IR"], d["IR"]),
            "IR_minus_G": 100 * float(np.mean(v["IR"]) - np.mean(g["IR"])), "p_IR_vs_G": paired_permutation_p(v["IR"], g["IR"]),
            "RR_minus_D": 100 * float(np.mean(v["reg"]) - np.mean(d["reg"])), "p_RR_vs_D": paired_permutation_p(v["reg"], d["reg"]),
            "IR_per_pair": v["IR"], "registered_per_pair": v["reg"]}
    inner = [w for w in ws if 0.0 < w < 1.0]
    s0 = solvers[0]
    best = max(inner, key=lambda w: (out[f"w={w:g} {s0}"]["IR"]["mean"], out[f"w={w:g} {s0}"]["RR"]["mean"])) if inner else None
    return {"split": split.name, "n_pairs": n, "noise_seed": split.noise_seed,
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{n - 1}", "weights": ws, "solvers": solvers,
            "rule": "the inner w with the highest mean IR (Kabsch RR breaks a tie), on the development set only",
            "best_w": best, "fpfh": fpfh_choice, "results": out}


def report(res: dict) -> str:
    lines = [f"fusion weight on the {res['split']} split, {res['n_pairs']} pairs ({res['pair_seeds']}):"]
    for key, r in res["results"].items():
        lines.append(f"  {key:14s} IR {r['IR']['mean']:5.1f} [{r['IR']['ci'][0]:.1f}, {r['IR']['ci'][1]:.1f}]  "
                     f"RR {r['RR']['mean']:5.1f}  vs D {r['IR_minus_D']:+.1f} (p {r['p_IR_vs_D']:.4f})  "
                     f"vs G {r['IR_minus_G']:+.1f} (p {r['p_IR_vs_G']:.4f})  RR vs D {r['RR_minus_D']:+.1f}")
    if res.get("fpfh"):
        for st, v in res["fpfh"]["settings"].items():
            lines.append(f"  FPFH {st}: FreeReg-G IR {v['FreeReg-G IR']['mean']:.1f} [{v['FreeReg-G IR']['ci'][0]:.1f}, "
                         f"{v['FreeReg-G IR']['ci'][1]:.1f}]")
        lines.append(f"  FPFH setting by the rule: {res['fpfh']['best']}")
    lines.append(f"  by the rule ({res['rule']}): w = {res['best_w']}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="dev", choices=sorted(SPLITS))
    p.add_argument("--cache", required=True)
    p.add_argument("--pairs", type=int, default=None)
    p.add_argument("--w", type=float, nargs="+", default=[0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    p.add_argument("--solvers", nargs="+", default=["kabsch"], choices=["kabsch", "pnp"])
    p.add_argument("--fpfh", nargs="+", default=None, help="VOXEL:FACTOR FPFH settings (the best by FreeReg-G IR is used)")
    p.add_argument("--weights", default=None,
                   help="with --fpfh: the micro weights folder the features were cached with (default: the committed)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    fpfh = [tuple(float(x) for x in st.split(":")) for st in args.fpfh] if args.fpfh else None
    res = sweep(args.split, Path(args.cache), args.w, args.solvers, args.pairs, fpfh, args.weights)
    res["commands"] = ["python -m freereg_lib.training.fusion_sweep " + " ".join(sys.argv[1:] if argv is None else argv)]
    res["git_head"] = _git_head()
    publish(res, report(res), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
