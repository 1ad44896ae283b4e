"""The paper's layer combinations on the validation scene (Table 8) with the micro models.

    python -m freereg_lib.training.evaluate_combinations --split dev --rows runs/micro/dev_combinations.jsonl
    python -m freereg_lib.training.evaluate_combinations --split dev --summarize
        --rows runs/micro/dev_combinations.jsonl --out freereg_lib/models/micro/weights/dev_layer_combinations.json

Table 8 is where the paper chose its layers: 21 combinations of three or four decoder layers on
its validation scene (BFO). Its counterpart here is the development set, where every choice of
the micro models is made; Table 2's rows on the test split (:mod:`.evaluate_layers`) report the
chosen (0, 4, 6) once. Per pair the nine decoder maps are computed once and each combination is
reduced, sampled and matched as :func:`.evaluate_layers.pair_rows` does (FreeReg-D, w = 1, no
pose solved: the table's RR is left out). ``--summarize`` writes IR, IN and FMR with intervals per
combination, their ranking beside the paper's, and the paired test of the best against (0, 4, 6).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib.config import FreeRegConfig
from freereg_lib.data import paper, synthetic
from freereg_lib.models import get_backend
from freereg_lib.training.evaluate import paired_permutation_p
from freereg_lib.training.evaluate_layers import pair_rows
from freereg_lib.training.evaluate_split import _done, _git_head, _stat, publish, rows_to_summarize
from freereg_lib.training.splits import SPLITS

CHOSEN = [0, 4, 6]


def combinations() -> dict[str, list[int]]:
    """Table 8's rows, ``{id: layers}``, read from the paper's table."""
    t = paper.table("table_supp_layer_combinations")
    return {str(i): [int(v) for v in str(layers).split(";")] for i, layers in zip(t["id"], t["layers"])}


def run(split_name: str, n_pairs: int, rows_path: Path) -> None:
    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    backend = get_backend("micro", cfg, device="cpu")
    sets = combinations()
    done = _done(rows_path)
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    for k in tqdm([k for k in range(n_pairs) if k not in done], desc=f"Table 8, {split.name}"):
        seed = split.pair_seeds(k + 1)[k]
        t0 = time.time()
        pair = synthetic.make_pair("indoor", seed=seed, world=split.world)
        rec = {"k": k, "pair_seed": seed, "pair": pair.name, "label": backend.label,
               "rows": pair_rows(pair, backend, cfg, sets)}
        rec["seconds"] = round(time.time() - t0, 1)
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def summarize(recs: list[dict], split_name: str) -> dict:
    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    sets = combinations()
    ref = paper.table("table_supp_layer_combinations").set_index("id")
    per = {}
    for row, layers in sets.items():
        ir = [r["rows"][row]["IR"] for r in recs]
        inn = [r["rows"][row]["IN"] for r in recs]
        s_in = _stat(inn)
        per[row] = {"layers": layers, "IR": _stat(ir), "FMR": _stat(np.asarray(ir) > cfg.fmr_ratio),
                    "IN": {"mean": s_in["mean"] / 100, "ci": [c / 100 for c in s_in["ci"]]},
                    "paper_BFO": {k: float(ref.loc[row, f"BFO_{k}"]) for k in ("IR", "IN", "FMR", "RR")},
                    "IR_per_pair": ir, "IN_per_pair": inn}
    chosen = next(r for r, layers in sets.items() if layers == CHOSEN)
    verdict = {}
    for metric in ("IR", "IN"):
        ours = sorted(per, key=lambda r: per[r][metric]["mean"], reverse=True)
        theirs = sorted(per, key=lambda r: per[r]["paper_BFO"][metric], reverse=True)
        key = f"{metric}_per_pair"
        verdict[metric] = {"micro_best": ours[0], "micro_best_layers": sets[ours[0]], "paper_best": theirs[0],
                           "paper_best_layers": sets[theirs[0]], "chosen_rank_micro": ours.index(chosen) + 1,
                           "chosen_rank_paper": theirs.index(chosen) + 1, "n_rows": len(per),
                           "p_best_vs_chosen": (paired_permutation_p(per[ours[0]][key], per[chosen][key])
                                                if ours[0] != chosen else None),
                           "rank_correlation": _spearman([per[r][metric]["mean"] for r in per],
                                                         [per[r]["paper_BFO"][metric] for r in per])}
    return {"split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed, "n_pairs": len(recs),
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(recs) - 1}",
            "backend": recs[0]["label"] if recs else None, "chosen": chosen, "rows": per, "verdict": verdict,
            "note": "FreeReg-D (w = 1) matches per Table 8 row, no pose solved (no RR); IR %, FMR %, IN (count) "
                    "with 95 % bootstrap intervals over pairs; p: paired permutation test over pairs; "
                    "rank_correlation: Spearman's, micro against the paper's BFO column, over the rows."}


def _spearman(a, b) -> float:
    ra = np.argsort(np.argsort(a)).astype(float)
    rb = np.argsort(np.argsort(b)).astype(float)
    return float(np.corrcoef(ra, rb)[0, 1])


def report(res: dict) -> str:
    lines = [f"Table 8 on the {res['split']} split, {res['n_pairs']} pairs ({res['pair_seeds']}), {res['backend']}"]
    for row, r in sorted(res["rows"].items(), key=lambda kv: -kv[1]["IR"]["mean"]):
        lines.append(f"  {row} {str(r['layers']):14s} IR {r['IR']['mean']:5.1f} [{r['IR']['ci'][0]:.1f}, "
                     f"{r['IR']['ci'][1]:.1f}]  IN {r['IN']['mean']:5.1f}   paper BFO IR {r['paper_BFO']['IR']:.1f} "
                     f"IN {r['paper_BFO']['IN']:.1f}")
    for k, v in res["verdict"].items():
        lines.append(f"  {k}: {json.dumps(v)}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="dev", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=None, help="default: the split's size")
    p.add_argument("--rows", required=True)
    p.add_argument("--summarize", action="store_true")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.pairs is not None and args.pairs < 1:
        p.error("--pairs must be >= 1")
    if not args.summarize:
        run(args.split, args.pairs or SPLITS[args.split].n_pairs, Path(args.rows))
        return 0
    recs = rows_to_summarize(p, args.rows)
    res = summarize(recs, args.split)
    res["commands"] = [f"python -m freereg_lib.training.evaluate_combinations --split {args.split} --pairs {len(recs)} "
                       f"--rows {args.rows}",
                       f"python -m freereg_lib.training.evaluate_combinations --split {args.split} --summarize "
                       f"--rows {args.rows}" + (f" --out {args.out}" if args.out else "")]
    res["git_head"] = _git_head()
    publish(res, report(res), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
