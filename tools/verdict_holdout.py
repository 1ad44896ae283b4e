"""The rows the verdict rule is fitted on and reported on (docs/your_data.md, "Registered or failed").

The shipped ICL living-room sample has 22 frames (0, 10, ..., 210). The rule is fitted on the pairs
within the first half of the trajectory and reported on the pairs within the second half
(:data:`freereg_lib.commands.verdict_measure.SPLIT`): no frame of one half is in a pair of the
other. Each pair is run as ``freereg register IMAGE CLOUD --depth-pose identity --image-depth DEPTH
--backend stub`` runs it: the cloud file in its sensor's frame, the setting the command chooses for
it (``3dmatch``), FreeReg-G with FPFH, the stub's monocular depth and the true depth, Kabsch and
PnP, 50,000 iterations. A row per (pair, depth, solver), appended to ``--out`` pair by pair (a
rerun skips the pairs already there)::

    python tools/verdict_holdout.py fit --out tests/fixtures/verdict_icl_fit_rows.csv
    python tools/verdict_holdout.py report --out tests/fixtures/verdict_icl_report_rows.csv
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

from freereg_lib.commands.real_frames import run
from freereg_lib.commands.verdict_measure import SPLIT, pairs_within
from freereg_lib.config import config_for
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.sources import spread

KEEP = ("depth", "solver", "success", "n_matches", "n_inliers", "scale", "RE", "TE", "seconds")


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
        rows = [{"pair": r["pair"], "gap": j - i, **{k: r[k] for k in KEEP}}
                for r in run(depths=("stub", "true"), solvers=("kabsch", "pnp"), cfg=cfg, progress=False, pairs=[pair])]
        pd.DataFrame(rows).to_csv(out, mode="a", header=not (os.path.exists(out) and os.path.getsize(out)), index=False)
        print(f"{half} {n}/{len(chosen)} {pair.name}: {time.perf_counter() - t0:.1f} s "
              f"({time.perf_counter() - t_start:.0f} s so far)", flush=True)
    return pd.read_csv(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("half", choices=sorted(SPLIT))
    p.add_argument("--pairs", type=int, help="pairs spread over the half's list (default: all)")
    p.add_argument("--iters", type=int, default=50_000)
    p.add_argument("--out", required=True, help="the rows as CSV (appended to)")
    a = p.parse_args(argv)
    if (a.pairs is not None and a.pairs < 1) or a.iters < 1:
        p.error("--pairs and --iters must be >= 1")
    half_rows(a.half, a.out, a.pairs, a.iters)
    return 0


if __name__ == "__main__":
    sys.exit(main())
