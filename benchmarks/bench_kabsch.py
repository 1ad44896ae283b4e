"""Kabsch-RANSAC scoring: the official Open3D call against the correspondence-scored RANSAC.

Runs the FreeReg chain (stub backend) on synthetic indoor pairs (FreeReg fused + Kabsch)
and on the embedded ICL pairs (FreeReg-G + Kabsch: the stub's diffusion features need a
synthetic scene), extracts the features once per pair, and solves the same matches with
each ``cfg.kabsch_scoring``. Prints registration recall, mean / median RE and TE over the
registered pairs, and the mean solver time per pair.

    python benchmarks/bench_kabsch.py --synthetic 20 --icl 10 [--iters 50000]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from freereg_lib import config_for, metrics, pipeline, sources
from freereg_lib.backends import get_backend


def solve_all(dataset: str, n: int, method: str, iters: int, scorings) -> dict:
    cfg = config_for(dataset, ransac_iters=iters)
    backend = get_backend("stub", cfg)
    w = pipeline._weight(method, cfg)
    out = {s: {"re": [], "te": [], "reg": [], "time": []} for s in scorings}
    for pair in sources.iter_pairs(dataset, n, seed=100):
        feats = pipeline.compute_features(pair, backend, cfg, diffusion=w > 0, geometric=w < 1)
        m = pipeline.match(feats, w)
        for s in scorings:
            t = time.perf_counter()
            res = pipeline.solve(pair, feats, m, cfg.override(kabsch_scoring=s), "kabsch")
            out[s]["time"].append(time.perf_counter() - t)
            re, te = metrics.pose_errors(res.T_cam_pc, pair.T_cam_pc) if res.success else (math.nan, math.nan)
            out[s]["re"].append(re)
            out[s]["te"].append(te)
            out[s]["reg"].append(metrics.registered(re, te, cfg.rr_rot_deg, cfg.rr_trans_m))
    return out


def report(title: str, out: dict) -> None:
    print(f"\n{title}")
    print(f"| scoring | pairs | RR % | RE mean / median (deg, registered) | TE mean / median (m, registered) | solver s / pair |")
    print("|---|---|---|---|---|---|")
    for s, r in out.items():
        reg = np.array(r["reg"], bool)
        re, te = np.array(r["re"])[reg], np.array(r["te"])[reg]
        f = lambda a, fn: f"{fn(a):.2f}" if len(a) else "-"
        print(f"| {s} | {len(reg)} | {100 * reg.mean():.1f} | {f(re, np.mean)} / {f(re, np.median)} | "
              f"{f(te, np.mean)} / {f(te, np.median)} | {np.mean(r['time']):.2f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--synthetic", type=int, default=20, help="synthetic indoor pairs (seed 100)")
    p.add_argument("--icl", type=int, default=10, help="embedded ICL pairs")
    p.add_argument("--iters", type=int, default=50_000, help="RANSAC iterations (the paper's 50k)")
    a = p.parse_args()
    scorings = ("official", "matches")
    if a.synthetic:
        report(f"synthetic indoor, FreeReg (fused) + Kabsch, stub backend, {a.iters} iterations",
               solve_all("synthetic_indoor", a.synthetic, "FreeReg", a.iters, scorings))
    if a.icl:
        report(f"ICL living room, FreeReg-G + Kabsch, stub backend, {a.iters} iterations",
               solve_all("icl", a.icl, "FreeReg-G", a.iters, scorings))


if __name__ == "__main__":
    main()
