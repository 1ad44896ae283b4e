"""The verdict rule on pairs it was not fitted on (docs/your_data.md, "Registered or failed").

The rule's thresholds (:data:`freereg_lib.pipeline.register.MIN_INLIERS`, ``MIN_INLIER_RATIO``,
``MAX_SCALE``) were set on ICL pairs with frame gaps of 10-80 (``tests/fixtures/verdict_icl_rows.csv``).
This runs the pairs with gaps of 90-150, which no threshold was chosen on, as ``freereg register
IMAGE CLOUD --depth-pose identity --image-depth DEPTH --backend stub`` now runs them: the cloud
file in its sensor's frame, the setting the command chooses for it (``3dmatch``), FreeReg-G with
FPFH, the stub's monocular depth and the true depth, Kabsch and PnP, 50,000 iterations. Its rows
have the columns of ``python -m freereg_lib.commands.verdict_measure``, which counts them::

    python tools/verdict_holdout.py --pairs 30 --out tests/fixtures/verdict_icl_holdout_rows.csv
    python -m freereg_lib.commands.verdict_measure --rows tests/fixtures/verdict_icl_holdout_rows.csv
"""
from __future__ import annotations

import argparse
import dataclasses

import pandas as pd

from freereg_lib.commands.real_frames import run
from freereg_lib.config import config_for
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.sources import spread

MIN_GAP, MAX_GAP = 90, 150  # the fitted rows had gaps of 10-80 frames
KEEP = ("depth", "solver", "success", "n_matches", "n_inliers", "scale", "RE", "TE", "seconds")


def holdout_rows(n_pairs: int = 30, iters: int = 50_000, progress: bool = True) -> list[dict]:
    """One row per (pair, depth, solver) of ``n_pairs`` pairs spread over the gaps 90-150."""
    sample = ICLSample()
    listed = sample.pair_list(max_gap=MAX_GAP, min_gap=MIN_GAP)
    # As the command reads a cloud file: no sensor depth map, the cloud projected on its sensor.
    pairs = [dataclasses.replace(sample.pair(*listed[k]), sensor_depth=None) for k in spread(len(listed), n_pairs)]
    gaps = {p.name: p.meta["frame_cloud"] - p.meta["frame_image"] for p in pairs}
    cfg = config_for("3dmatch", ransac_iters=iters)  # what cli.choose_setting picks for these clouds
    return [{"pair": r["pair"], "gap": gaps[r["pair"]], **{k: r[k] for k in KEEP}}
            for r in run(depths=("stub", "true"), solvers=("kabsch", "pnp"), cfg=cfg, progress=progress, pairs=pairs)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=30)
    p.add_argument("--iters", type=int, default=50_000)
    p.add_argument("--out", required=True, help="the rows as CSV")
    a = p.parse_args(argv)
    if a.pairs < 1 or a.iters < 1:
        p.error("--pairs and --iters must be >= 1")
    pd.DataFrame(holdout_rows(a.pairs, a.iters)).to_csv(a.out, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
