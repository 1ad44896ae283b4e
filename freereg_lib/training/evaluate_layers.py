"""Table 2 (layer selection) with the committed micro models on a split (:mod:`.splits`).

    python -m freereg_lib.training.evaluate_layers --split test [--pairs 100] [--shard 0/1]
        --rows runs/micro/test_layers.jsonl
    python -m freereg_lib.training.evaluate_layers --split test --summarize
        --rows runs/micro/test_layers.jsonl --out freereg_lib/models/micro/weights/test_split_layers.json

Per pair the nine decoder maps of both sides are computed once (:func:`freereg_lib.pipeline.diffusion_maps`,
noise seed = the split's), then each of Table 2's rows (single layers a-i, combinations j-m) is reduced
(joint PCA), sampled at the pipeline's keypoints and matched (mutual nearest neighbours, w = 1), as
notebook 01 does; IR and IN are scored as :func:`freereg_lib.pipeline.evaluate` scores them. No pose is
solved (Table 2's RR is left out: 13 PnP runs a pair). ``--summarize`` writes IR, IN and FMR with 95 %
bootstrap intervals per row over the longest complete prefix of pairs, the layer groups' order and
whether row m (0, 4, 6) is the best combination, beside the paper's 3DMatch columns.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from freereg_lib.training.evaluate import paired_permutation_p
from freereg_lib.training.evaluate_split import _done, _git_head, _stat, publish, rows_to_summarize
from freereg_lib.training.splits import SPLITS

LAYER_SETS = {"a": [0], "b": [1], "c": [2], "d": [3], "e": [4], "f": [5], "g": [6], "h": [7], "i": [8],
              "j": [0, 4], "k": [0, 6], "l": [4, 6], "m": [0, 4, 6]}
GROUPS = {"coarse 0-2": "abc", "medium 3-5": "def", "fine 6-8": "ghi"}


def pair_rows(pair, backend, cfg, layer_sets: dict[str, list[int]] = LAYER_SETS) -> dict:
    """IR, IN, n_matches per row of ``layer_sets`` (default: Table 2's) for one pair."""
    from dataclasses import replace

    from freereg_lib import features, pipeline
    from freereg_lib.geometry import metrics

    base = pipeline.compute_features(pair, backend, cfg, diffusion=False, geometric=False)
    maps_img, maps_dep = pipeline.diffusion_maps(pair, base.view, backend)
    out = {}
    for row, layers in layer_sets.items():
        f_img, f_dep = features.pca_reduce(maps_img, maps_dep, layers, cfg.pca_dim)
        feats = replace(base, diff_image=features.sample_features(f_img, base.uv_image, pair.image_size),
                        diff_depth=features.sample_features(f_dep, base.uv_depth, pair.depth_size))
        m = pipeline.match(feats, 1.0)
        ir, inn = metrics.inlier_stats(*pipeline.correct_matches(pair, feats, m, cfg), cfg.eval_few_matches)
        out[row] = {"IR": float(ir), "IN": int(inn), "n_matches": len(m)}
    return out


def run(split_name: str, n_pairs: int, rows_path: Path, shard: str = "0/1") -> None:
    from tqdm import tqdm

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    split = SPLITS[split_name]
    i, n = (int(x) for x in shard.split("/"))
    cfg = FreeRegConfig(seed=split.noise_seed)
    backend = get_backend("micro", cfg, device="cpu")
    done = _done(rows_path)
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    for k in tqdm([k for k in range(n_pairs) if k % n == i and k not in done], desc=f"Table 2, {split.name}"):
        seed = split.pair_seeds(k + 1)[k]
        t0 = time.time()
        pair = synthetic.make_pair("indoor", seed=seed, world=split.world)
        rec = {"k": k, "pair_seed": seed, "pair": pair.name, "label": backend.label,
               "rows": pair_rows(pair, backend, cfg), "seconds": 0.0}
        rec["seconds"] = round(time.time() - t0, 1)
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def summarize(recs: list[dict], split_name: str) -> dict:
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import paper

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    p2 = paper.table("table2_layer_selection").set_index("id")
    per = {}
    for row, layers in LAYER_SETS.items():
        ir = [r["rows"][row]["IR"] for r in recs]
        inn = [r["rows"][row]["IN"] for r in recs]
        s_in = _stat(inn)
        per[row] = {"layers": layers, "IR": _stat(ir), "FMR": _stat(np.asarray(ir) > cfg.fmr_ratio),
                    "IN": {"mean": s_in["mean"] / 100, "ci": [c / 100 for c in s_in["ci"]]},
                    "paper_3DMatch": {k: float(p2.loc[row, f"3DMatch_{k}"]) for k in ("IR", "IN", "FMR")},
                    "IR_per_pair": ir, "IN_per_pair": inn}
    verdict = {}
    for metric in ("IR", "IN"):
        ours = {g: float(np.mean([per[r][metric]["mean"] for r in rows])) for g, rows in GROUPS.items()}
        theirs = {g: float(np.mean([per[r]["paper_3DMatch"][metric] for r in rows])) for g, rows in GROUPS.items()}
        verdict[f"{metric} group order"] = {"micro": sorted(ours, key=ours.get, reverse=True),
                                            "paper": sorted(theirs, key=theirs.get, reverse=True),
                                            "micro_means": ours, "paper_means": theirs}
    combos = "jklm"
    for metric in ("IR", "IN"):
        best = max(combos, key=lambda r: per[r][metric]["mean"])
        key = f"{metric}_per_pair"
        verdict[f"best combination by {metric}"] = {
            "micro": best, "micro_layers": LAYER_SETS[best],
            "paper": max(combos, key=lambda r: per[r]["paper_3DMatch"][metric]),
            "p_best_vs_m": paired_permutation_p(per[best][key], per["m"][key]) if best != "m" else None}
    return {"split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed, "n_pairs": len(recs),
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(recs) - 1}",
            "backend": recs[0]["label"] if recs else None, "rows": per, "verdict": verdict,
            "note": "FreeReg-D (w = 1) matches per Table 2 row, no pose solved (no RR); IR %, FMR %, IN (count) "
                    "with 95 % bootstrap intervals over pairs; p: paired permutation test over pairs."}


def report(res: dict) -> str:
    lines = [f"Table 2 on the {res['split']} split, {res['n_pairs']} pairs ({res['pair_seeds']}), {res['backend']}"]
    for row, r in res["rows"].items():
        lines.append(f"  {row} {str(r['layers']):10s} IR {r['IR']['mean']:5.1f} [{r['IR']['ci'][0]:.1f}, {r['IR']['ci'][1]:.1f}]"
                     f"  IN {r['IN']['mean']:5.1f}  FMR {r['FMR']['mean']:5.1f}   paper IR {r['paper_3DMatch']['IR']:.1f}"
                     f" IN {r['paper_3DMatch']['IN']:.1f}")
    for k, v in res["verdict"].items():
        lines.append(f"  {k}: {json.dumps({a: b for a, b in v.items() if not a.endswith('means')})}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="test", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=None)
    p.add_argument("--shard", default="0/1")
    p.add_argument("--rows", nargs="+", required=True)
    p.add_argument("--summarize", action="store_true")
    p.add_argument("--out", default=None)
    p.add_argument("--run-command", action="append", default=[])
    args = p.parse_args(argv)
    if not args.summarize:
        run(args.split, args.pairs or SPLITS[args.split].n_pairs, Path(args.rows[0]), args.shard)
        return 0
    res = summarize(rows_to_summarize(p, args.rows), args.split)
    res["commands"] = args.run_command + [
        f"python -m freereg_lib.training.evaluate_layers --split {args.split} --summarize --rows {' '.join(args.rows)}"
        + (f" --out {args.out}" if args.out else "")]
    res["git_head"] = _git_head()
    publish(res, report(res), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
