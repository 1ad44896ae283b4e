"""Kabsch-RANSAC: the official algorithm (open3d 0.12's, in NumPy) against the installed Open3D's call.

Two measurements:

1. The solver alone, the official setting: 50,000 iterations, ransac_n 4, a similarity, on
   1,400 matches (a 32 x 44 keypoint grid) of which 80 % are outliers. Prints the seconds of
   each ``cfg.kabsch_scoring`` (best of ``--repeat``) and what each recovered.
2. The chain on the embedded ICL pairs (FreeReg-G, FPFH, the true depth on the image side,
   the default ICL config), the same matches solved with each scoring: registration recall,
   median RE / TE and the solver's seconds per pair.

    python benchmarks/bench_kabsch.py [--icl 8] [--iters 50000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import time

import numpy as np

from freereg_lib import config_for, pipeline
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.sources import spread
from freereg_lib.geometry import cameras, metrics, pose
from freereg_lib.models import get_backend

SCORINGS = ("official", "open3d")


def solver_alone(iters: int, repeat: int, n: int = 1408, outliers: float = 0.8) -> None:
    rng = np.random.default_rng(0)
    T = cameras.make_pose(cameras.rotation_about([0.2, 1, 0.1], 0.5), [0.4, -0.1, 0.8])
    pts_pc = rng.uniform([-2, -1.5, 1], [2, 1.5, 6], size=(n, 3))
    pts_cam = cameras.transform(T, pts_pc) / 1.25  # a monocular depth 20 % short
    bad = rng.random(n) < outliers
    pts_pc[bad] = rng.uniform([-2, -1.5, 1], [2, 1.5, 6], size=(int(bad.sum()), 3))
    print(f"\n1. Solver alone: {n} matches, {100 * outliers:.0f} % outliers, {iters} iterations, similarity "
          f"({platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')})")
    print("| scoring | seconds (best of %d) | RE (deg) | TE (m) | scale | inliers |" % repeat)
    print("|---|---|---|---|---|---|")
    for s in SCORINGS:
        times = []
        for _ in range(repeat if s == "official" else 1):
            t0 = time.perf_counter()
            res = pose.kabsch_ransac(pts_cam, pts_pc, 0.2, iters, scoring=s)
            times.append(time.perf_counter() - t0)
        re, te = metrics.pose_errors(res.T_cam_pc, T) if res.success else (math.nan, math.nan)
        print(f"| {s} | {min(times):.2f} | {re:.2f} | {te:.3f} | {res.scale:.3f} | {res.n_inliers} |")


def chain(n_pairs: int, iters: int) -> None:
    cfg = config_for("icl", ransac_iters=iters)
    backend = get_backend("stub", cfg)
    sample = ICLSample()
    pair_list = sample.pair_list()
    out = {s: {"re": [], "te": [], "reg": [], "time": []} for s in SCORINGS}
    for k in spread(len(pair_list), n_pairs):
        pair = sample.pair(*pair_list[k])
        feats = pipeline.compute_features(pair, backend, cfg, diffusion=False, mono=pair.depth_gt)
        m = pipeline.match(feats, 0.0)
        for s in SCORINGS:
            t0 = time.perf_counter()
            res = pipeline.solve(pair, feats, m, cfg.override(kabsch_scoring=s), "kabsch")
            out[s]["time"].append(time.perf_counter() - t0)
            re, te = metrics.pose_errors(res.T_cam_pc, pair.T_cam_pc) if res.success else (math.nan, math.nan)
            out[s]["re"].append(re)
            out[s]["te"].append(te)
            out[s]["reg"].append(metrics.registered(re, te, cfg.rr_rot_deg, cfg.rr_trans_m))
    print(f"\n2. ICL living room, {n_pairs} spread pairs, FreeReg-G (FPFH) with the true depth + Kabsch, "
          f"{iters} iterations")
    print("| scoring | pairs | RR % | median RE (deg) | median TE (m) | solver s / pair |")
    print("|---|---|---|---|---|---|")
    for s, r in out.items():
        print(f"| {s} | {len(r['reg'])} | {100 * np.mean(r['reg']):.1f} | {np.nanmedian(r['re']):.2f} | "
              f"{np.nanmedian(r['te']):.3f} | {np.mean(r['time']):.2f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--icl", type=int, default=8, help="spread ICL pairs for the chain (0: skip)")
    p.add_argument("--iters", type=int, default=50_000, help="RANSAC iterations (the paper's 50k)")
    p.add_argument("--repeat", type=int, default=3, help="timed runs of the official solver")
    a = p.parse_args()
    solver_alone(a.iters, a.repeat)
    if a.icl:
        chain(a.icl, a.iters)


if __name__ == "__main__":
    main()
