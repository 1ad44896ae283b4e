"""Registration on the shipped real RGB-D sample (ICL-NUIM living room), the floors CI holds.

FreeReg-G (FPFH) with the library's default ICL config on an evenly spread subset of the
sample's pair list; the image side's depth is either the RGB frame's own sensor depth
(``"true"``: what the solvers can do with perfect monocular depth) or the stub's monocular
depth (``"stub"``: the true depth with a global scale error and a smooth distortion of
ZoeDepth's size). Each pair is solved by Kabsch- and PnP-RANSAC; a row per (pair, depth,
solver). Real frames, no synthetic scene: a change to the solver, the depth handling or the
evaluation that costs registration on real data shows here.

    python -m freereg_lib.commands.real_frames [--pairs 12] [--iters 50000]
    python -m freereg_lib.commands.real_frames --demo path/to/FreeReg/data/demo

``--demo`` runs the same on the official demo pair instead (``config_for("demo")``, its
``source_rgb.gtd.png`` as the true depth, matches scored with ``target_dpt.gtd.png``).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from freereg_lib import pipeline
from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.sources import spread
from freereg_lib.pipeline import verdict

DEPTHS = ("true", "stub")
SOLVERS = ("kabsch", "pnp")


def icl_pairs(n_pairs: int | None = 12):
    """The ICL pairs of an evenly spread subset of the sample's pair list."""
    sample = ICLSample()
    pair_list = sample.pair_list()
    for k in spread(len(pair_list), n_pairs):
        yield sample.pair(*pair_list[k])


def run(n_pairs: int | None = 12, depths=DEPTHS, solvers=SOLVERS, cfg: FreeRegConfig | None = None,
        progress: bool = True, pairs=None) -> list[dict]:
    """Rows ``pair, depth, solver, success, n_matches, n_inliers, scale, IR, IN, n_evaluable, RE, TE,
    registered, seconds, error`` over ``pairs`` (default: :func:`icl_pairs` of ``n_pairs``)."""
    from tqdm.auto import tqdm

    from freereg_lib.models import get_backend

    cfg = cfg or config_for("icl")
    pairs = list(icl_pairs(n_pairs)) if pairs is None else list(pairs)
    backend = get_backend("stub", cfg)
    return [row for pair in tqdm(pairs, desc="pairs", disable=not progress)
            for row in pair_rows(pair, backend, cfg, depths, solvers)]


def pair_rows(pair, backend, cfg: FreeRegConfig, depths=DEPTHS, solvers=SOLVERS, null: bool = False) -> list[dict]:
    """The rows of :func:`run` for one pair: FreeReg-G on its depth (``"stub"``: the backend's monocular
    depth; ``"true"``: ``depth_gt``) with each solver. ``null``: also each pose's per-run null
    (``null_inliers``, :func:`freereg_lib.pipeline.verdict.null_inliers`, ";"-joined), timed with the solve."""
    rows = []
    for depth in depths:
        mono = pair.depth_gt if depth == "true" else backend.mono_depth(pair.image, depth_gt=pair.depth_gt)
        feats = pipeline.compute_features(pair, backend, cfg, diffusion=False, geometric=True, mono=mono)
        m = pipeline.match(feats, 0.0)
        for solver in solvers:
            t0 = time.perf_counter()
            res = pipeline.solve(pair, feats, m, cfg, solver)
            extra = {"null_inliers": ";".join(map(str, verdict.null_inliers(pair, feats, m, cfg, solver)))} if null else {}
            seconds = time.perf_counter() - t0
            scores = pipeline.evaluate(pair, feats, m, res, cfg)
            rows.append({"pair": pair.name, "depth": depth, "solver": solver, "success": bool(res.success),
                         "n_matches": len(m), "n_inliers": res.n_inliers, "scale": res.scale, **scores, **extra,
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
    p.add_argument("--demo", metavar="DIR", help="the official demo folder (data/demo of the official code) "
                                                 "instead of the ICL sample")
    a = p.parse_args(argv)
    changes = {"ransac_iters": a.iters, "kabsch_scoring": a.kabsch_scoring}
    if a.edge_filter is not None:
        changes["edge_filter_m"] = a.edge_filter
    if a.demo:
        from freereg_lib.data.datasets.demo import load_demo_pair

        cfg = config_for("demo", **changes)
        rows, title = run(cfg=cfg, pairs=[load_demo_pair(a.demo)]), f"the official demo ({a.demo})"
    else:
        cfg = config_for("icl", **changes)
        rows, title = run(a.pairs or None, cfg=cfg), "ICL living room"
    print(f"\n{title}, FreeReg-G (FPFH), densify {cfg.densify!r}, edge filter {cfg.edge_filter_m:g} m, "
          f"{cfg.ransac_iters} iterations, Kabsch scoring {cfg.kabsch_scoring!r}")
    print("| depth | solver | pairs | RR % | IR % | IN | evaluable | median RE (deg) | median TE (m) | solver s / pair |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (depth, solver), rr in recall(rows).items():
        sel = [r for r in rows if r["depth"] == depth and r["solver"] == solver]
        col = lambda k: [r[k] for r in sel]  # noqa: E731
        print(f"| {depth} | {solver} | {len(sel)} | {100 * rr:.1f} | {100 * np.mean(col('IR')):.1f} | "
              f"{np.mean(col('IN')):.1f} | {np.mean(col('n_evaluable')):.0f} / {np.mean(col('n_matches')):.0f} | "
              f"{np.nanmedian(col('RE')):.2f} | {np.nanmedian(col('TE')):.3f} | {np.mean(col('seconds')):.2f} |")


if __name__ == "__main__":
    main()
