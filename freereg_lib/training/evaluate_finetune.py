"""The paper's fine-tuning table (Table 11, fine-tuning: FreeReg vs FreeReg-Ft) on the micro models.

    python -m freereg_lib.training.evaluate_finetune --model committed --pairs 100 \
        --rows runs/micro/finetune/rows_committed.jsonl
    python -m freereg_lib.training.evaluate_finetune --model finetuned --weights runs/micro/finetune/weights \
        --pairs 100 --shard 0/2 --rows runs/micro/finetune/rows_finetuned_0.jsonl   (and 1/2, side by side)
    python -m freereg_lib.training.evaluate_finetune --summarize --weights runs/micro/finetune/weights \
        --rows runs/micro/finetune/rows_committed.jsonl runs/micro/finetune/rows_finetuned_[01].jsonl \
        --out freereg_lib/models/micro/weights/finetune_test.json

Fused FreeReg (Kabsch- and PnP-RANSAC) on the test split with the committed micro weights and with
the ControlNet fine-tuned on sensor-like hints (:mod:`.finetune_controlnet`); every other part is
the committed one (:func:`differing_parts` checks the weight files, and the micro depth model is
the committed ``depth/`` folder, which the exported folder lacks). Each model runs in its own
process (one rows file each, resumable, so both can run side by side); the summary pairs the two
on the pairs ``k = 0 .. n-1`` that both have. Nothing is chosen on these numbers: the step budget
was fixed before either was run.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib.config import FreeRegConfig
from freereg_lib.training.evaluate_split import (
    RowsError, _plain, _stat, difference_line, paired_difference, parse_shard, publish, stamped,
)
from freereg_lib.training.splits import SPLITS

MODELS = ("committed", "finetuned")
VARIANTS = (("FreeReg", "kabsch"), ("FreeReg", "pnp"))
ROW_KEYS = ("solver", "n_matches", "IR", "IN", "RE", "TE", "registered", "error")
SOLVERS = ("kabsch", "pnp")


def differing_parts(folder: str | Path, reference: str | Path | None = None) -> list[str]:
    """The micro parts whose weight files in ``folder`` differ from ``reference``'s (default: the
    committed weights): ``["controlnet"]`` for a fine-tuned ControlNet alone."""
    from freereg_lib.models.micro import diffusion as M

    reference = Path(reference) if reference else M.WEIGHTS_DIR

    def digest(root: Path, part: str) -> str:
        h = hashlib.sha256()
        for f in sorted((root / part).glob("*.safetensors")):
            h.update(f.read_bytes())
        return h.hexdigest()

    return [p for p in M.PARTS if p != "tokenizer" and digest(Path(folder), p) != digest(reference, p)]


def pair_record(pair, backend, cfg: FreeRegConfig) -> dict:
    """One pair's fused-FreeReg rows (Kabsch, PnP) with ``backend``, timing each half."""
    from freereg_lib import pipeline

    t0 = time.perf_counter()
    base = pipeline.compute_features(pair, backend, cfg, diffusion=False, geometric=True)
    t1 = time.perf_counter()
    try:
        d = pipeline.compute_features(pair, backend, cfg, diffusion=True, geometric=False, view=base.view,
                                      mono=base.mono_depth)
        feats = dataclasses.replace(base, diff_image=d.diff_image, diff_depth=d.diff_depth)
    except Exception as exc:  # scored as run_pair scores a failed pair
        feats = exc
    t2 = time.perf_counter()
    rows = pipeline.variant_rows(pair, feats, cfg, VARIANTS)
    return {"seconds_geometric": round(t1 - t0, 3), "seconds_diffusion": round(t2 - t1, 3),
            "rows": [{k: _plain(r.get(k)) for k in ROW_KEYS} for r in rows]}


def run(split_name: str, n_pairs: int, rows_path: Path, model: str, weights: str | None = None,
        shard: tuple[int, int] = (0, 1), progress: bool = True) -> None:
    """Append ``model``'s rows of the split's pairs ``k < n_pairs`` (those with ``k % n == i`` for
    ``shard = (i, n)``) not yet in ``rows_path``."""
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    backend = get_backend("micro", cfg, device="cpu", weights_dir=weights if model == "finetuned" else None)
    done = {r["k"] for r in _read(rows_path) if r.get("model") == model} if rows_path.exists() else set()
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    todo = [k for k in range(n_pairs) if k not in done and k % shard[1] == shard[0]]
    for k in tqdm(todo, desc=f"{model}, {split.name} split",
                  disable=not progress):
        seed = split.pair_seeds(k + 1)[k]
        pair = synthetic.make_pair("indoor", seed=seed, world=split.world)
        rec = {"k": k, "model": model, "pair_seed": seed, "pair": pair.name, "label": backend.label,
               "weights": str(backend.weights_dir), "depth_weights": str(backend.depth_weights_dir),
               "load_average": round(os.getloadavg()[0], 2), **pair_record(pair, backend, cfg)}
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def _read(path: Path) -> list[dict]:
    """The records of one rows file; :class:`RowsError` (one line) when it cannot be read."""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise RowsError(f"--rows {path}: cannot read it ({type(exc).__name__}: {exc.strerror or exc})") from None
    out = []
    for no, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
            if not isinstance(r.get("k"), int) or r.get("model") not in MODELS:
                raise TypeError("no integer 'k' or no 'model' of " + ", ".join(MODELS))
        except (ValueError, TypeError, AttributeError) as exc:
            raise RowsError(f"--rows {path}, line {no}: not a row of evaluate_finetune: {exc}") from None
        out.append(r)
    return out


def paired_records(rows_paths) -> list[dict[str, dict]]:
    """``[{model: record}]`` for pairs ``k = 0 .. n-1``, the longest prefix that every model has."""
    by = {m: {} for m in MODELS}
    for path in rows_paths:
        for r in _read(Path(path)):
            by[r["model"]].setdefault(r["k"], r)
    n = 0
    while all(n in by[m] for m in MODELS):
        n += 1
    return [{m: by[m][k] for m in MODELS} for k in range(n)]


def _row(rec: dict, solver: str) -> dict:
    return next(r for r in rec["rows"] if r["solver"] == solver)


def summarize(pairs: list[dict[str, dict]], split_name: str) -> dict:
    """Per model and solver FMR, IR, IN, RR with 95 % bootstrap intervals; fine-tuned minus committed
    per pair (bootstrap interval, paired sign-flip permutation p)."""
    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    per, tests = {}, {}
    for m in MODELS:
        for solver in SOLVERS:
            rows = [_row(p[m], solver) for p in pairs]
            ir = [r["IR"] or 0.0 for r in rows]
            reg = [int(bool(r["registered"])) for r in rows]
            per[f"{m} {solver}"] = {"n": len(rows), "FMR": _stat(np.asarray(ir) > cfg.fmr_ratio), "IR": _stat(ir),
                                    "IN": float(np.mean([r["IN"] or 0 for r in rows])), "RR": _stat(reg),
                                    "IR_per_pair": ir, "registered_per_pair": reg,
                                    "failed": sum(bool(r["error"]) for r in rows)}
        per[f"{m} seconds_diffusion"] = float(np.median([p[m]["seconds_diffusion"] for p in pairs]))
    for solver in SOLVERS:
        a, b = per[f"finetuned {solver}"], per[f"committed {solver}"]
        for metric, key in (("RR", "registered_per_pair"), ("IR", "IR_per_pair"), ("FMR", "IR_per_pair")):
            x, y = np.asarray(a[key], dtype=np.float64), np.asarray(b[key], dtype=np.float64)
            if metric == "FMR":
                x, y = (x > cfg.fmr_ratio).astype(np.float64), (y > cfg.fmr_ratio).astype(np.float64)
            tests[f"{metric} {solver}: finetuned - committed"] = paired_difference(x, y)
    first = pairs[0] if pairs else {}
    return {"split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed,
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(pairs) - 1}", "n_pairs": len(pairs),
            "backend": first.get("committed", {}).get("label"),
            "weights": {m: first.get(m, {}).get("weights") for m in MODELS},
            "depth_weights": {m: first.get(m, {}).get("depth_weights") for m in MODELS},
            "results": per, "tests": tests,
            "load_average": [min(p[m]["load_average"] for p in pairs for m in MODELS),
                             max(p[m]["load_average"] for p in pairs for m in MODELS)] if pairs else None,
            "note": "Fused FreeReg (the config's w), FPFH, Kabsch- and PnP-RANSAC; committed: the committed micro "
                    "weights; finetuned: their ControlNet fine-tuned on sensor-like hints (finetune_controlnet), "
                    "every other part the committed one; p: two-sided paired sign-flip permutation test over "
                    "pairs; intervals: 95 % percentile bootstrap; seconds: median wall-clock of the diffusion "
                    "half per pair on a shared CPU."}


def report(res: dict) -> str:
    lines = [f"{res['split']} split: {res['n_pairs']} synthetic indoor pairs (both models), {res['backend']}",
             "  model     solver  FMR    IR     IN     RR"]
    for m in MODELS:
        for solver in SOLVERS:
            r = res["results"][f"{m} {solver}"]
            lines.append(f"  {m:9s} {solver:6s} {r['FMR']['mean']:5.1f}  {r['IR']['mean']:5.1f}  {r['IN']:5.1f}  "
                         f"{r['RR']['mean']:5.1f}")
    for key, t in res["tests"].items():
        lines.append(difference_line(key, t))
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="test", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--model", default="committed", choices=MODELS, help="which weights this process runs")
    p.add_argument("--weights", default=None, help="the fine-tuned weights folder (finetune_controlnet --export)")
    p.add_argument("--rows", nargs="+", required=True, help="per-pair rows (JSON lines), appended to or summarized")
    p.add_argument("--shard", default="0/1", help="i/n: this process runs pairs k with k %% n == i")
    p.add_argument("--summarize", action="store_true")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.pairs < 1:
        p.error(f"--pairs {args.pairs}: expected >= 1")
    try:
        shard = parse_shard(args.shard)
    except ValueError as exc:
        p.error(str(exc))
    if (args.model == "finetuned" or args.summarize) and not args.weights:
        p.error("--weights is needed for the fine-tuned model and for --summarize")
    if args.weights and not Path(args.weights, "controlnet").is_dir():
        p.error(f"--weights {args.weights}: no controlnet/ folder there (finetune_controlnet --export)")
    from freereg_lib.training.command_inputs import rows_fault, weights_fault

    if args.weights and (fault := weights_fault(args.weights)):  # as finetune_controlnet checks it: SHA256SUMS
        p.error(f"--weights {args.weights}: {fault}")
    if not args.summarize and (fault := rows_fault(args.rows[0], "evaluate_finetune", "solver", writing=True)):
        p.error(fault)
    if not args.summarize:
        if len(args.rows) != 1:
            p.error("--rows: one file when running a model (several only with --summarize)")
        run(args.split, args.pairs, Path(args.rows[0]), args.model, args.weights, shard)
        return 0
    try:
        pairs = paired_records(args.rows)
    except RowsError as exc:
        p.error(str(exc))
    if not pairs:
        p.error(f"--rows {' '.join(args.rows)}: no pair k = 0 that both models ran")
    res = summarize(pairs, args.split)
    res["differing_parts"] = differing_parts(args.weights)
    res["finetune"] = json.loads(Path(args.weights, "training.json").read_text()).get("finetune")
    res["commands"] = [
        f"python -m freereg_lib.training.evaluate_finetune --split {args.split} --model committed --pairs "
        f"{len(pairs)} --rows {args.rows[0]}",
        f"python -m freereg_lib.training.evaluate_finetune --split {args.split} --model finetuned --weights "
        f"{args.weights} --pairs {len(pairs)} [--shard i/n] --rows {' '.join(args.rows[1:]) or args.rows[0]}",
        f"python -m freereg_lib.training.evaluate_finetune --split {args.split} --summarize --weights {args.weights} "
        f"--rows {' '.join(args.rows)}" + (f" --out {args.out}" if args.out else "")]
    publish(stamped(res), report(res), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
