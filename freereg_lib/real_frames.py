"""Registration on the shipped real RGB-D sample (ICL-NUIM living room), the floors CI holds.

FreeReg-G (FPFH) with the library's default ICL config on an evenly spread subset of the
sample's pair list; the image side's depth is either the RGB frame's own sensor depth
(``"true"``: what the solvers can do with perfect monocular depth) or the stub's monocular
depth (``"stub"``: the true depth with a global scale error and a smooth distortion of
ZoeDepth's size). Each pair is solved by Kabsch- and PnP-RANSAC; a row per (pair, depth,
solver). Real frames, no synthetic scene: a change to the solver, the depth handling or the
evaluation that costs registration on real data shows here.

    python -m freereg_lib.real_frames [--pairs 12] [--iters 50000]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from . import metrics, pipeline
from .config import FreeRegConfig, config_for
from .datasets.icl import ICLSample
from .sources import spread

DEPTHS = ("true", "stub")
SOLVERS = ("kabsch", "pnp")


def run(n_pairs: int | None = 12, depths=DEPTHS, solvers=SOLVERS, cfg: FreeRegConfig | None = None,
        progress: bool = True) -> list[dict]:
    """Rows ``pair, depth, solver, n_matches, n_inliers, scale, RE, TE, registered, seconds, error``."""
    from tqdm.auto import tqdm

    from .backends import get_backend

    cfg = cfg or config_for("icl")
    sample = ICLSample()
    pair_list = sample.pair_list()
    chosen = [pair_list[k] for k in spread(len(pair_list), n_pairs)]
    backend = get_backend("stub", cfg)
    rows = []
    for i, j in tqdm(chosen, desc="ICL pairs", disable=not progress):
        pair = sample.pair(i, j)
        for depth in depths:
            mono = pair.depth_gt if depth == "true" else backend.mono_depth(pair.image, depth_gt=pair.depth_gt)
            feats = pipeline.compute_features(pair, backend, cfg, diffusion=False, geometric=True, mono=mono)
            m = pipeline.match(feats, 0.0)
            for solver in solvers:
                t0 = time.perf_counter()
                res = pipeline.solve(pair, feats, m, cfg, solver)
                seconds = time.perf_counter() - t0
                re, te = metrics.pose_errors(res.T_cam_pc, pair.T_cam_pc) if res.success else (math.nan, math.nan)
                rows.append({"pair": pair.name, "depth": depth, "solver": solver, "n_matches": len(m),
                             "n_inliers": res.n_inliers, "scale": res.scale, "RE": re, "TE": te,
                             "registered": metrics.registered(re, te, cfg.rr_rot_deg, cfg.rr_trans_m),
                             "seconds": seconds, "error": res.reason})
    return rows


def recall(rows: list[dict]) -> dict[tuple[str, str], float]:
    """RR (fraction) per ``(depth, solver)``."""
    out: dict[tuple[str, str], list[bool]] = {}
    for r in rows:
        out.setdefault((r["depth"], r["solver"]), []).append(bool(r["registered"]))
    return {k: float(np.mean(v)) for k, v in out.items()}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=12, help="spread pairs of the ICL pair list (0: all)")
    p.add_argument("--iters", type=int, default=50_000, help="RANSAC iterations (the paper's 50000)")
    p.add_argument("--kabsch-scoring", default="official", choices=("official", "open3d"))
    p.add_argument("--edge-filter", type=float, default=None, help="cfg.edge_filter_m (default: the config's)")
    a = p.parse_args(argv)
    changes = {"ransac_iters": a.iters, "kabsch_scoring": a.kabsch_scoring}
    if a.edge_filter is not None:
        changes["edge_filter_m"] = a.edge_filter
    cfg = config_for("icl", **changes)
    rows = run(a.pairs or None, cfg=cfg)
    print(f"\nICL living room, FreeReg-G (FPFH), config_for('icl'): densify {cfg.densify!r}, edge filter "
          f"{cfg.edge_filter_m:g} m, {cfg.ransac_iters} iterations, Kabsch scoring {cfg.kabsch_scoring!r}")
    print("| depth | solver | pairs | RR % | median RE (deg) | median TE (m) | solver s / pair |")
    print("|---|---|---|---|---|---|---|")
    for (depth, solver), rr in recall(rows).items():
        sel = [r for r in rows if r["depth"] == depth and r["solver"] == solver]
        print(f"| {depth} | {solver} | {len(sel)} | {100 * rr:.1f} | {np.nanmedian([r['RE'] for r in sel]):.2f} | "
              f"{np.nanmedian([r['TE'] for r in sel]):.3f} | {np.mean([r['seconds'] for r in sel]):.2f} |")


if __name__ == "__main__":
    main()
