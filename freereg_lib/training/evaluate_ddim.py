"""The paper's acceleration table (Table 13, DDIM iterations) on the micro models.

    python -m freereg_lib.training.evaluate_ddim --split test --pairs 30 --steps 5 20 --rows runs/micro/ddim/rows.jsonl
    python -m freereg_lib.training.evaluate_ddim --split test --summarize --rows runs/micro/ddim/rows.jsonl
        --out freereg_lib/models/micro/weights/ddim_iterations_test.json

The depth side's DDIM sampling runs ``cfg.ddim_steps`` iterations and stops at ``t_hat``
(:func:`~freereg_lib.models.base.n_guided_steps`: 4 guided steps of 5, 17 of 20); the paper
times it at 9.3 s a pair with 20 and 4.7 s with 5, for 1.4 points of registration recall.
Here each pair's geometric half (the micro depth and FPFH) is computed once and the diffusion
half once per iteration count, with a micro backend built for that count; fused FreeReg is then
matched and solved with Kabsch- and PnP-RANSAC. Nothing is chosen on these numbers, so the test
split is used directly. The seconds are wall-clock seconds of the diffusion half on this
machine (its load average is recorded beside them), and of the geometric half once.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib import pipeline
from freereg_lib.config import FreeRegConfig
from freereg_lib.data import synthetic
from freereg_lib.models import get_backend
from freereg_lib.training.evaluate import paired_permutation_p
from freereg_lib.training.evaluate_split import (
    _done, _plain, _stat, load_average_range, paired_difference, publish, rows_to_summarize, stamped,
)
from freereg_lib.training.splits import SPLITS

STEPS = (5, 10, 15, 20)
VARIANTS = (("FreeReg", "kabsch"), ("FreeReg", "pnp"))
ROW_KEYS = ("solver", "n_matches", "IR", "IN", "RE", "TE", "registered", "error")


def pair_record(pair, backends: dict, cfg: FreeRegConfig, variants=VARIANTS) -> dict:
    """One pair's rows, one per (method, solver) of ``variants``, for every iteration count of
    ``backends`` (``{steps: backend}``)."""
    t0 = time.perf_counter()
    base = pipeline.compute_features(pair, backends[max(backends)], cfg, diffusion=False, geometric=True)
    rec = {"seconds_geometric": round(time.perf_counter() - t0, 3), "by_steps": {}}
    for steps, backend in sorted(backends.items()):
        c = cfg.override(ddim_steps=steps)
        t1 = time.perf_counter()
        try:
            d = pipeline.compute_features(pair, backend, c, diffusion=True, geometric=False, view=base.view,
                                          mono=base.mono_depth)
            feats = dataclasses.replace(base, diff_image=d.diff_image, diff_depth=d.diff_depth)
        except Exception as exc:  # scored as run_pair scores a failed pair
            feats = exc
        seconds = round(time.perf_counter() - t1, 3)
        rows = pipeline.variant_rows(pair, feats, c, variants)
        rec["by_steps"][str(steps)] = {"seconds_diffusion": seconds,
                                       "rows": [{k: _plain(r.get(k)) for k in ROW_KEYS} for r in rows]}
    return rec


def run(split_name: str, n_pairs: int, rows_path: Path, steps=STEPS, progress: bool = True) -> None:
    """Append the rows of the split's pairs ``k < n_pairs`` not yet in ``rows_path``."""
    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    backends = {s: get_backend("micro", cfg.override(ddim_steps=s), device="cpu") for s in steps}
    done = _done(rows_path)
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    for k in tqdm([k for k in range(n_pairs) if k not in done], desc=f"{split.name} split", disable=not progress):
        seed = split.pair_seeds(k + 1)[k]
        pair = synthetic.make_pair("indoor", seed=seed, world=split.world)
        rec = {"k": k, "pair_seed": seed, "pair": pair.name, "label": backends[max(backends)].label,
               "load_average": round(os.getloadavg()[0], 2), **pair_record(pair, backends, cfg)}
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def summarize(recs: list[dict], split_name: str) -> dict:
    """Per iteration count and solver: FMR, IR, IN, RR with intervals, the seconds of the diffusion
    half (median over pairs), and RR / IR against 20 iterations (paired permutation tests)."""
    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    steps = sorted({int(s) for r in recs for s in r["by_steps"]})
    per, tests = {}, {}
    for s in steps:
        for solver in ("kabsch", "pnp"):
            rows = [next(r for r in rec["by_steps"][str(s)]["rows"] if r["solver"] == solver) for rec in recs]
            ir = [r["IR"] or 0.0 for r in rows]
            per[f"{s} {solver}"] = {
                "FMR": _stat(np.asarray(ir) > cfg.fmr_ratio), "IR": _stat(ir), "RR": _stat([bool(r["registered"])
                                                                                          for r in rows]),
                "IN": float(np.mean([r["IN"] or 0 for r in rows])),
                "IR_per_pair": ir, "registered_per_pair": [int(bool(r["registered"])) for r in rows]}
        per[f"{s} seconds"] = float(np.median([rec["by_steps"][str(s)]["seconds_diffusion"] for rec in recs]))
    top = max(steps)
    for s in steps[:-1]:
        for solver in ("kabsch", "pnp"):
            a, b = per[f"{s} {solver}"]["registered_per_pair"], per[f"{top} {solver}"]["registered_per_pair"]
            tests[f"RR {solver}: {s} - {top} iterations"] = paired_difference(a, b)
        a, b = per[f"{s} kabsch"], per[f"{top} kabsch"]
        tests[f"IR: {s} - {top} iterations"] = {"diff": 100 * float(np.mean(a["IR_per_pair"]) - np.mean(b["IR_per_pair"])),
                                                "p": paired_permutation_p(a["IR_per_pair"], b["IR_per_pair"])}
    return {"split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed,
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(recs) - 1}", "n_pairs": len(recs),
            "backend": recs[0]["label"] if recs else None, "steps": steps, "results": per, "tests": tests,
            "seconds_geometric": float(np.median([r["seconds_geometric"] for r in recs])) if recs else None,
            "load_average": load_average_range(recs),
            "note": "Fused FreeReg (w = 0.5), layers (0, 4, 6), FPFH; seconds: median wall-clock of the diffusion "
                    "half per pair on the CPU, with the machine's 1-minute load average range beside them; "
                    "p: two-sided paired sign-flip permutation test over pairs; intervals: 95 % percentile bootstrap."}


def report(res: dict) -> str:
    lines = [f"{res['split']} split: {res['n_pairs']} synthetic indoor pairs, {res['backend']}",
             "  steps solver  FMR    IR     IN     RR     diffusion s"]
    for s in res["steps"]:
        for solver in ("kabsch", "pnp"):
            r = res["results"][f"{s} {solver}"]
            lines.append(f"  {s:5d} {solver:6s} {r['FMR']['mean']:5.1f}  {r['IR']['mean']:5.1f}  {r['IN']:5.1f}  "
                         f"{r['RR']['mean']:5.1f}  {res['results'][f'{s} seconds']:.2f}")
    for key, t in res["tests"].items():
        ci = f" [{t['diff_ci'][0]:+.1f}, {t['diff_ci'][1]:+.1f}]" if "diff_ci" in t else ""
        lines.append(f"  {key}: {t['diff']:+.1f} points{ci}, p = {t['p']:.4f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="test", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--steps", type=int, nargs="+", default=list(STEPS))
    p.add_argument("--rows", required=True, help="per-pair rows (JSON lines), appended to or summarized")
    p.add_argument("--summarize", action="store_true")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.pairs < 1 or any(s < 1 for s in args.steps):
        p.error("--pairs and --steps must be >= 1")
    if not args.summarize:
        run(args.split, args.pairs, Path(args.rows), tuple(args.steps))
        return 0
    recs = rows_to_summarize(p, args.rows)
    res = summarize(recs, args.split)
    res["commands"] = [f"python -m freereg_lib.training.evaluate_ddim --split {args.split} --pairs {len(recs)} "
                       f"--steps {' '.join(str(s) for s in res['steps'])} --rows {args.rows}",
                       f"python -m freereg_lib.training.evaluate_ddim --split {args.split} --summarize --rows "
                       f"{args.rows}" + (f" --out {args.out}" if args.out else "")]
    publish(stamped(res), report(res), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
