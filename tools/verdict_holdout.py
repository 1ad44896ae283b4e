"""The rows the verdict rule is fitted on and reported on (docs/your_data.md, "Registered or failed").

The shipped ICL living-room sample has 22 frames (0, 10, ..., 210). The rule is fitted on the pairs
within the first half of the trajectory and reported on the pairs within the second half
(:data:`freereg_lib.commands.verdict_measure.SPLIT`): no frame of one half is in a pair of the
other; ``demo`` reports it on the official demo pair (another sensor, a ScanNet frame; its folder
with ``--demo``), ``synthetic`` on rendered synthetic rooms (another "sensor": exact depth, a
thinned cloud, other rooms). Each pair is run as ``freereg register IMAGE CLOUD --depth-pose identity
--image-depth DEPTH --backend stub`` runs it: the cloud file in its sensor's frame, the setting the
command chooses for it (``3dmatch``; the demo's own ``demo``), FreeReg-G with FPFH, the stub's
monocular depth and the true depth, Kabsch and PnP, 50,000 iterations, and the verdict's per-run
null (:func:`freereg_lib.pipeline.verdict.null_inliers`: the inliers the same solver reaches on the
matches shuffled, a ``;``-separated count per shuffle). A row per (pair, depth, solver), appended
to ``--out`` pair by pair (a rerun skips the pairs already there)::

    python tools/verdict_holdout.py fit --out tests/fixtures/verdict_icl_fit_rows.csv
    python tools/verdict_holdout.py report --out tests/fixtures/verdict_icl_report_rows.csv
    python tools/verdict_holdout.py demo --demo path/to/FreeReg/data/demo --out demo_rows.csv
    python tools/verdict_holdout.py synthetic --pairs 20 --out tests/fixtures/verdict_synthetic_rows.csv
    python -m freereg_lib.commands.verdict_measure --fit tests/fixtures/verdict_icl_fit_rows.csv \\
        --rows tests/fixtures/verdict_icl_report_rows.csv
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import pandas as pd

from freereg_lib.commands import real_frames
from freereg_lib.commands.verdict_measure import SPLIT, pairs_within
from freereg_lib.config import config_for
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.sources import spread
from freereg_lib.models import get_backend

KEEP = ("depth", "solver", "success", "n_matches", "n_inliers", "scale", "null_inliers", "RE", "TE", "seconds")


def pair_rows(pair, cfg, depths=("stub", "true"), solvers=("kabsch", "pnp")) -> list[dict]:
    """A row per (depth, solver) of ``pair``: the command's chain, its pose and its per-run null."""
    return real_frames.pair_rows(pair, get_backend("stub", cfg), cfg, depths, solvers, null=True)


def _append(rows: list[dict], out: str) -> None:
    fresh = not (os.path.exists(out) and os.path.getsize(out))
    pd.DataFrame(rows).to_csv(out, mode="a", header=fresh, index=False)


def half_rows(half: str, out: str, n_pairs: int | None = None, iters: int = 50_000) -> pd.DataFrame:
    """Run the pairs within ``half`` of :data:`SPLIT` (``n_pairs`` of them spread over the list,
    default all), appending each pair's four rows to the CSV ``out``; the rows of ``out``."""
    sample = ICLSample()
    listed = pairs_within(SPLIT[half])
    chosen = [listed[k] for k in spread(len(listed), n_pairs)]
    done = set(pd.read_csv(out)["pair"]) if os.path.exists(out) and os.path.getsize(out) else set()
    cfg = config_for("3dmatch", ransac_iters=iters)  # what cli.choose_setting picks for these clouds
    t_start = time.perf_counter()
    for n, (i, j) in enumerate(chosen, 1):
        # As the command reads a cloud file: no sensor depth map, the cloud projected on its sensor.
        pair = dataclasses.replace(sample.pair(i, j), sensor_depth=None)
        if pair.name in done:
            continue
        t0 = time.perf_counter()
        _append([{"pair": r["pair"], "gap": j - i, **{k: r[k] for k in KEEP}} for r in pair_rows(pair, cfg)], out)
        print(f"{half} {n}/{len(chosen)} {pair.name}: {time.perf_counter() - t0:.1f} s "
              f"({time.perf_counter() - t_start:.0f} s so far)", flush=True)
    return pd.read_csv(out)


def demo_rows(root: str, out: str, iters: int = 50_000) -> pd.DataFrame:
    """The official demo pair (its own ``demo`` setting), appended to ``out`` unless already there."""
    from freereg_lib.data.datasets.demo import load_demo_pair

    pair = load_demo_pair(root)
    done = set(pd.read_csv(out)["pair"]) if os.path.exists(out) and os.path.getsize(out) else set()
    if pair.name not in done:
        _append([{"pair": r["pair"], "gap": 0, **{k: r[k] for k in KEEP}}
                 for r in pair_rows(pair, config_for("demo", ransac_iters=iters))], out)
    return pd.read_csv(out)


def synthetic_rows(out: str, n_pairs: int = 20, iters: int = 50_000) -> pd.DataFrame:
    """Synthetic indoor pairs (seeds ``0 .. n_pairs - 1``; rendered rooms, their cloud a thinned
    sample of the surfaces, so the command's ``demo`` setting), appended to ``out`` pair by pair."""
    from freereg_lib.data import synthetic

    done = set(pd.read_csv(out)["pair"]) if os.path.exists(out) and os.path.getsize(out) else set()
    cfg = config_for("demo", ransac_iters=iters)
    for seed in range(n_pairs):
        pair = synthetic.make_pair("indoor", seed=seed)
        if pair.name in done:
            continue
        _append([{"pair": r["pair"], "gap": 0, **{k: r[k] for k in KEEP}} for r in pair_rows(pair, cfg)], out)
    return pd.read_csv(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("half", choices=sorted(SPLIT) + ["demo", "synthetic"])
    p.add_argument("--pairs", type=int, help="pairs spread over the half's list (default: all)")
    p.add_argument("--iters", type=int, default=50_000)
    p.add_argument("--demo", metavar="DIR", help="the official demo folder (FreeReg/data/demo), for 'demo'")
    p.add_argument("--out", required=True, help="the rows as CSV (appended to)")
    a = p.parse_args(argv)
    if (a.pairs is not None and a.pairs < 1) or a.iters < 1:
        p.error("--pairs and --iters must be >= 1")
    if a.half == "demo":
        if not a.demo:
            p.error("demo needs --demo DIR (the official demo folder)")
        demo_rows(a.demo, a.out, a.iters)
    elif a.half == "synthetic":
        synthetic_rows(a.out, a.pairs or 20, a.iters)
    else:
        half_rows(a.half, a.out, a.pairs, a.iters)
    return 0


if __name__ == "__main__":
    sys.exit(main())
