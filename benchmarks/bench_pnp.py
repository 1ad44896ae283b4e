#!/usr/bin/env python
"""PnP-RANSAC variants on FreeReg's own matches: time per call and registration quality.

    python benchmarks/bench_pnp.py [--pairs N] [--methods iterative iterative:2 usac ...] [--iters I]
                                   [--json PATH]

What it measures: for N synthetic indoor pairs (seeds 0..N-1, the paper's indoor
configuration, ``stub`` backend), the features and the FreeReg matches (fusion weight
``cfg.fusion_w``) are computed once per pair; then every PnP method of ``pose.PNP_METHODS``
asked for solves the same matches through ``pipeline.solve(..., "pnp")`` with
``cfg.pnp_method`` set to it (``name:W`` also sets ``cfg.pnp_workers = W``; threshold ``cfg.pnp_reproj_px``, iteration cap ``--iters``,
default ``cfg.ransac_iters`` = 50k). Each solve is timed with ``time.perf_counter`` (one
call per pair and method, no warm-up: the calls are independent) and scored by
``pipeline.evaluate``. The table gives per method the median / min / max seconds per call,
the registration recall RR (``evaluate(...)["registered"]``: RE < 20 deg and TE < 0.5 m),
and the median rotation / translation errors over the registered pairs; the device line
names the CPU, its cores, the OpenCV version and the date.

Run it from the repository root with the project's virtualenv::

    export OPENBLAS_NUM_THREADS=1
    .venv/bin/python benchmarks/bench_pnp.py --pairs 20 [--json pnp.json]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: see Makefile

import argparse
import datetime
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_METHODS = ("iterative", "usac", "usac_accurate", "ap3p")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_meter import cpu_model  # noqa: E402  (this folder is on sys.path when run as a script)


def device_line() -> str:
    """CPU model, usable cores, load average, OpenCV version and threads, date."""
    import cv2

    from freereg_lib.commands.cluster import available_cores

    cores = available_cores()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f"device: CPU {cpu_model()}, {cores} cores (load average {load}); "
            f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads); {date}")


def within_px(uv: np.ndarray, pts_pc: np.ndarray, K: np.ndarray, T_cam_pc: np.ndarray, px: float) -> float:
    """Fraction of matches whose cloud point projects (true pose) within ``px`` of its pixel."""
    cam = pts_pc @ T_cam_pc[:3, :3].T + T_cam_pc[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = (cam @ K.T)[:, :2] / z[:, None]
    ok = (z > 0) & (np.linalg.norm(proj - uv, axis=1) < px)
    return float(ok.mean()) if len(uv) else math.nan


def _median(xs: list[float]) -> float:
    return statistics.median(xs) if xs else math.nan


def summarize(rows: list[dict], methods: list[str]) -> list[dict]:
    """Per method: seconds per call (median, min, max), RR and median RE / TE of registered pairs."""
    out = []
    for meth in methods:
        mine = [r for r in rows if r["method"] == meth]
        secs = [r["seconds"] for r in mine]
        reg = [r for r in mine if r["registered"]]
        out.append({
            "method": meth,
            "calls": len(mine),
            "median_s": _median(secs),
            "min_s": min(secs) if secs else math.nan,
            "max_s": max(secs) if secs else math.nan,
            "registered": len(reg),
            "RR_percent": 100.0 * len(reg) / len(mine) if mine else math.nan,
            "median_RE_deg": _median([r["RE"] for r in reg]),
            "median_TE_m": _median([r["TE"] for r in reg]),
            "failed_solves": sum(not r["success"] for r in mine),
        })
    return out


def format_table(summary: list[dict]) -> str:
    def num(x: float, fmt: str) -> str:
        return "-" if math.isnan(x) else format(x, fmt)

    lines = [
        "| PnP method | calls | median [s] | min [s] | max [s] | RR [%] | median RE [deg] | median TE [m] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary:
        lines.append(
            f"| {s['method']} | {s['calls']} | {num(s['median_s'], '.3f')} | {num(s['min_s'], '.3f')} "
            f"| {num(s['max_s'], '.3f')} | {num(s['RR_percent'], '.0f')} ({s['registered']}/{s['calls']}) "
            f"| {num(s['median_RE_deg'], '.2f')} | {num(s['median_TE_m'], '.3f')} |"
        )
    return "\n".join(lines)


def _spec(method: str) -> tuple[str, int]:
    """``"iterative:2"`` -> ``("iterative", 2)`` (``cfg.pnp_workers``); no suffix: one worker;
    a suffix that is not a positive count: 0 (refused)."""
    name, sep, workers = method.partition(":")
    if not sep:
        return name, 1
    return name, int(workers) if workers.isdigit() else 0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pairs", type=int, default=20, help="synthetic indoor pairs (seeds 0..N-1)")
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                   help=f"PnP methods of pose.PNP_METHODS, each optionally with a worker count, "
                        f"e.g. iterative:2 (default: {' '.join(DEFAULT_METHODS)})")
    p.add_argument("--iters", type=int, default=None,
                   help="RANSAC iteration cap (default: cfg.ransac_iters, the paper's 50k)")
    p.add_argument("--json", default=None, help="also write the per-call rows and the summary here")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from tqdm import tqdm

    from freereg_lib import config_for, pipeline
    from freereg_lib.data import synthetic
    from freereg_lib.geometry import pose
    from freereg_lib.models import get_backend

    unknown = [m for m in args.methods if _spec(m)[0] not in pose.PNP_METHODS or _spec(m)[1] < 1]
    if unknown:
        print(f"unknown PnP method(s) {unknown}; expected some of {sorted(pose.PNP_METHODS)}", file=sys.stderr)
        return 2
    cfg = config_for("synthetic_indoor")
    iters = args.iters if args.iters is not None else cfg.ransac_iters
    be = get_backend("stub", cfg)

    print(device_line(), flush=True)
    print(f"pairs: {args.pairs} synthetic indoor (seeds 0-{args.pairs - 1}), stub backend, FreeReg matches "
          f"(w = {cfg.fusion_w}); PnP-RANSAC cap {iters} iterations, {cfg.pnp_reproj_px:g} px, "
          f"methods {', '.join(args.methods)}", flush=True)

    rows: list[dict] = []
    n_matches: list[int] = []
    inlier_ratio: list[float] = []
    px_ratio: list[float] = []
    for seed in tqdm(range(args.pairs), desc="pairs", unit="pair"):
        pair = synthetic.make_pair("indoor", seed=seed)
        feats = pipeline.compute_features(pair, be, cfg)
        m = pipeline.match(feats, cfg.fusion_w)
        n_matches.append(len(m.idx_image))
        px_ratio.append(within_px(feats.uv_image[m.idx_image], feats.pts_depth[m.idx_depth], pair.K_image,
                                  pair.T_cam_pc, cfg.pnp_reproj_px))
        for meth in args.methods:
            name, workers = _spec(meth)
            c = cfg.override(pnp_method=name, pnp_workers=workers, ransac_iters=iters)
            t0 = time.perf_counter()
            res = pipeline.solve(pair, feats, m, c, "pnp")
            seconds = time.perf_counter() - t0
            ev = pipeline.evaluate(pair, feats, m, res, c)
            rows.append({
                "seed": seed, "method": meth, "seconds": seconds, "success": res.success,
                "reason": res.reason, "n_inliers": res.n_inliers, "n_matches": len(m.idx_image),
                "IR": float(ev["IR"]), "RE": float(ev["RE"]), "TE": float(ev["TE"]),
                "registered": bool(ev["registered"]),
            })
        inlier_ratio.append(rows[-1]["IR"])

    summary = summarize(rows, args.methods)
    print()
    print(f"matches per pair: median {_median(n_matches):.0f} ({min(n_matches)} - {max(n_matches)}); "
          f"inlier ratio IR (tau_c {cfg.tau_c} m) median {100 * _median(inlier_ratio):.0f} %; "
          f"within {cfg.pnp_reproj_px:g} px of the true projection: median {100 * _median(px_ratio):.0f} % "
          f"({100 * min(px_ratio):.0f} - {100 * max(px_ratio):.0f} %)")
    print(format_table(summary))
    failed = {s["method"]: s["failed_solves"] for s in summary if s["failed_solves"]}
    if failed:
        print(f"solves that returned no pose: {failed}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"device": device_line(), "iters": iters, "rows": rows, "summary": summary}, fh, indent=1)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
