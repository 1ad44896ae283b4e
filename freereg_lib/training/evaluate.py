"""Held-out quality of the micro diffusion models: trained weights against random ones.

    python -m freereg_lib.training.evaluate [--pairs 30] [--seed 2026] [--weights DIR]
        [--guidance-w 4.0] [--t-hat 150] [--controlnet-scale 1.0] [--trained-only]
        [--random-from eval.json] [--out eval.json]

Runs FreeReg-D (decoder layers 0, 4, 6; PnP-RANSAC) through :func:`freereg_lib.pipeline.run_pairs`
on synthetic indoor pairs made from integer seeds, kept off the training rooms' two-word seed
sequence (:mod:`.views`) by :func:`freereg_lib.data.synthetic.check_eval_seed`, once with the ``micro`` backend's trained weights and
once with the same architecture's random weights. Prints IR, FMR and RR with 95 % bootstrap
intervals over pairs, the ratio of the mean IRs and a paired sign-flip permutation test.
``--random-from`` takes the random-weight run from an earlier result of the same pairs, noise
seed and config (the random weights do not change when the trained ones do).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from freereg_lib.training.splits import guard_eval_seed
from freereg_lib.training.provenance import machine_record

VARIANT = ("FreeReg-D", "pnp")
PERMUTATIONS = 20000  # sign flips of the paired test; its smallest p is 1 / (PERMUTATIONS + 1)


def bootstrap_ci(values, stat=np.mean, n: int = 2000, seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap interval of ``stat`` over ``values`` (pairs resampled)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    stats = [stat(v[rng.integers(0, len(v), len(v))]) for _ in range(n)]
    return float(np.percentile(stats, 2.5)), float(np.percentile(stats, 97.5))


def paired_permutation_p(a, b, n: int = PERMUTATIONS, seed: int = 0) -> float:
    """Two-sided p-value of mean(a - b) = 0 under random sign flips of the paired differences."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    if not np.any(d):
        return 1.0
    rng = np.random.default_rng(seed)
    signs = rng.choice([-1.0, 1.0], size=(n, len(d)))
    null = np.abs((signs * d).mean(axis=1))
    return float((np.sum(null >= abs(d.mean()) - 1e-15) + 1) / (n + 1))


def summarize(rows: list[dict], cfg) -> dict:
    """IR / FMR / RR (%) with bootstrap intervals, from per-pair rows."""
    ir = np.array([r["IR"] for r in rows])
    fm = (ir > cfg.fmr_ratio).astype(float)
    rr = np.array([bool(r["registered"]) for r in rows], dtype=float)
    out = {"n_pairs": len(rows), "IR_per_pair": ir.tolist()}
    for key, v in (("IR", ir), ("FMR", fm), ("RR", rr)):
        lo, hi = bootstrap_ci(v)
        out[key] = 100 * float(v.mean())
        out[key + "_ci"] = [100 * lo, 100 * hi]
    return out


class IncomparableRun(ValueError):
    """An earlier result that is not of this run's pairs, pair seed and config."""


def reuse_random(earlier: dict, n_pairs: int, seed: int, changes: dict) -> dict:
    """The ``random`` entry of an earlier :func:`evaluate` result, checked to be of the same
    pairs, pair seed and config changes (noise seed included)."""
    if "random" not in earlier:
        raise IncomparableRun("the earlier result holds no random-weight run")
    got = (earlier["random"]["n_pairs"], earlier["seed"], earlier["config_changes"])
    want = (n_pairs, seed, json.loads(json.dumps(changes)))
    if got != want:
        raise IncomparableRun(f"the earlier result is of (pairs, seed, config changes) = {got}, this run of {want}")
    return earlier["random"]


def evaluate(n_pairs: int = 30, seed: int = 2026, weights_dir=None, progress: bool = True,
             which=("trained", "random"), noise_seed: int | None = None, random_from: dict | None = None,
             **changes) -> dict:
    """The trained-vs-random comparison on ``n_pairs`` held-out pairs drawn from ``seed``;
    ``changes`` override the config (e.g. ``guidance_w``, ``t_hat``); ``noise_seed`` sets the
    config's seed (the diffusion features' noise draws); ``which=("trained",)`` skips the
    random baseline (a sweep of the trained model); ``random_from`` (an earlier result of the
    same pairs and config, checked by :func:`reuse_random`) gives the random run instead of running it again."""
    from freereg_lib import pipeline
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import sources
    from freereg_lib.models import get_backend

    if noise_seed is not None:
        changes = {**changes, "seed": int(noise_seed)}
    cfg = FreeRegConfig().override(**changes) if changes else FreeRegConfig()
    pairs = list(sources.iter_pairs("synthetic_indoor", n_pairs, seed=seed))
    result = {"seed": seed, "config_changes": changes}
    if random_from is not None:
        result["random"] = reuse_random(random_from, n_pairs, seed, changes)
        which = tuple(w for w in which if w != "random")
    for name, kw in (("trained", {"weights_dir": weights_dir}), ("random", {"random_weights": True})):
        if name not in which:
            continue
        backend = get_backend("micro", cfg, device="cpu", **kw)
        rows = pipeline.run_pairs(pairs, backend, cfg, [VARIANT], progress=progress)
        result[name] = summarize(rows, cfg)
    if "trained" not in result or "random" not in result:
        return result
    a, b = result["trained"]["IR_per_pair"], result["random"]["IR_per_pair"]
    result["IR_ratio"] = result["trained"]["IR"] / max(result["random"]["IR"], 1e-9)
    result["p_value"] = paired_permutation_p(a, b)
    return result


def report(result: dict) -> str:
    lines = [f"FreeReg-D (layers 0, 4, 6; PnP) on {result['trained']['n_pairs']} synthetic indoor "
             f"pairs (seed {result['seed']}; {result['config_changes'] or 'default config'}):"]
    for name in ("trained", "random"):
        if name not in result:
            continue
        r = result[name]
        lines.append(f"  {name:8s} IR {r['IR']:5.1f} % [{r['IR_ci'][0]:.1f}, {r['IR_ci'][1]:.1f}]   "
                     f"FMR {r['FMR']:5.1f} % [{r['FMR_ci'][0]:.1f}, {r['FMR_ci'][1]:.1f}]   "
                     f"RR {r['RR']:5.1f} % [{r['RR_ci'][0]:.1f}, {r['RR_ci'][1]:.1f}]")
    if "IR_ratio" not in result:
        return "\n".join(lines)
    lines.append(f"  trained / random IR = {result['IR_ratio']:.2f}x (paired permutation p = {result['p_value']:.4f}); "
                 "the paper's FreeReg-D on 3DMatch: IR 39.6 %, FMR 91.9 %")
    return "\n".join(lines)


SWEPT_FIELDS = ("guidance_w", "t_hat", "ddim_steps", "ddim_eta", "controlnet_scale")


def config_changes(args: argparse.Namespace) -> dict:
    """The config fields the command line set (only those given, so a default run records ``{}``)."""
    return {k: getattr(args, k) for k in SWEPT_FIELDS if getattr(args, k) is not None}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pairs", type=int, default=30)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--weights", default=None, help="micro weights folder (default: the committed ones)")
    p.add_argument("--guidance-w", type=float, default=None)
    p.add_argument("--t-hat", type=int, default=None)
    p.add_argument("--ddim-steps", type=int, default=None)
    p.add_argument("--ddim-eta", type=float, default=None)
    p.add_argument("--controlnet-scale", type=float, default=None,
                   help="the ControlNet residuals' weight (diffusers' conditioning_scale; the official 1)")
    p.add_argument("--noise-seed", type=int, default=None,
                   help="the config's seed (the diffusion features' noise draws); default the config's")
    p.add_argument("--trained-only", action="store_true", help="skip the random-weight baseline (sweeps)")
    p.add_argument("--random-from", default=None,
                   help="an earlier result (JSON) of the same pairs, noise seed and config whose random-weight "
                        "run is reused instead of run again")
    p.add_argument("--out", default=None, help="write the result as JSON here")
    args = p.parse_args(argv)
    guard_eval_seed(args.seed, args.pairs)  # no pair may draw a training room
    from freereg_lib.training.command_inputs import weights_fault

    if args.weights and (fault := weights_fault(args.weights)):  # SHA256SUMS, whole files: before any pair
        p.error(f"--weights {args.weights}: {fault}")
    changes = config_changes(args)
    which = ("trained",) if args.trained_only else ("trained", "random")
    random_from = json.loads(Path(args.random_from).read_text()) if args.random_from else None
    try:
        result = evaluate(args.pairs, args.seed, args.weights, which=which, noise_seed=args.noise_seed,
                          random_from=random_from, **changes)
    except IncomparableRun as exc:
        raise SystemExit(f"--random-from {args.random_from}: {exc}") from None
    print(report(result))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({**result, "provenance": machine_record()}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
