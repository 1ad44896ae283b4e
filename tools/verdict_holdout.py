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
matches shuffled, a ``;``-separated count per shuffle). ``sample`` reports it on another folder in
the ICL layout (``--root``, default the shipped TUM fr1_rpy Kinect v1 frames): every ordered pair
``i != j`` of its frames whose overlap (:func:`freereg_lib.data.synthetic.overlap_ratio`) is above
``--min-overlap`` (0.3), those with ``i < j`` first. A row per (pair, depth, solver), appended to
``--out`` pair by pair (a rerun skips the pairs already there); an ``--out`` ending in ``.json``
holds the rows with the machine that measured them (:func:`freereg_lib.training.provenance.machine_record`)::

    python tools/verdict_holdout.py fit --out tests/fixtures/verdict_icl_fit_rows.csv
    python tools/verdict_holdout.py report --out tests/fixtures/verdict_icl_report_rows.csv
    python tools/verdict_holdout.py demo --demo path/to/FreeReg/data/demo --out demo_rows.csv
    python tools/verdict_holdout.py synthetic --pairs 20 --out tests/fixtures/verdict_synthetic_rows.csv
    python tools/verdict_holdout.py sample --out tests/fixtures/verdict_tum_rows.json
    python -m freereg_lib.commands.verdict_measure --fit tests/fixtures/verdict_icl_fit_rows.csv \\
        --rows tests/fixtures/verdict_icl_report_rows.csv
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import pandas as pd

from freereg_lib.commands import real_frames
from freereg_lib.commands.verdict_measure import SPLIT, pairs_within
from freereg_lib.config import config_for
from freereg_lib.data.datasets.icl import TUM_ROOT, ICLSample
from freereg_lib.data.sources import spread
from freereg_lib.models import get_backend

KEEP = ("depth", "solver", "success", "n_matches", "n_inliers", "scale", "null_inliers", "RE", "TE", "seconds")


def pair_rows(pair, cfg, depths=("stub", "true"), solvers=("kabsch", "pnp")) -> list[dict]:
    """A row per (depth, solver) of ``pair``: the command's chain, its pose and its per-run null."""
    return real_frames.pair_rows(pair, get_backend("stub", cfg), cfg, depths, solvers, null=True)


def _read(out: str) -> pd.DataFrame:
    """The rows of ``out`` (a CSV, or a ``.json`` of :func:`_append`); none when it is absent or empty."""
    if not (os.path.exists(out) and os.path.getsize(out)):
        return pd.DataFrame(columns=["pair"])
    return pd.DataFrame(json.loads(open(out).read())["rows"]) if out.endswith(".json") else pd.read_csv(out)


def _append(rows: list[dict], out: str, about: dict | None = None) -> None:
    """Append ``rows`` to the CSV ``out``; to a ``.json`` ``{**about, "provenance", "rows"}`` (rewritten)."""
    if out.endswith(".json"):
        from freereg_lib.training.provenance import machine_record

        old = json.loads(open(out).read()) if os.path.exists(out) and os.path.getsize(out) else {}
        head = {**(about or {}), "provenance": old.get("provenance") or machine_record()}
        rows = old.get("rows", []) + [{k: (None if v != v else round(v, 2 if k == "seconds" else 6))
                                       if isinstance(v, float) else v for k, v in r.items()} for r in rows]
        with open(out, "w") as f:  # a row a line
            f.write(json.dumps(head, indent=1)[:-2] + ',\n "rows": [\n' + ",\n".join(map(json.dumps, rows)) + "\n]}\n")
        return
    fresh = not (os.path.exists(out) and os.path.getsize(out))
    pd.DataFrame(rows).to_csv(out, mode="a", header=fresh, index=False)


def overlapping_pairs(sample: ICLSample, min_overlap: float = 0.3) -> list[tuple[int, int]]:
    """The ordered pairs ``(i, j)``, ``i != j``, of ``sample.frames`` whose overlap is above
    ``min_overlap``; those with ``i < j`` first (each list by ``i``, then ``j``)."""
    from freereg_lib.data.synthetic import overlap_ratio

    both = [(i, j) for i in sample.frames for j in sample.frames if i < j] + \
           [(i, j) for i in sample.frames for j in sample.frames if i > j]
    return [(i, j) for i, j in both if overlap_ratio(sample.pair(i, j)) > min_overlap]


def sample_rows(out: str, root=TUM_ROOT, min_overlap: float = 0.3, n_pairs: int | None = None,
                iters: int = 50_000) -> pd.DataFrame:
    """The :func:`overlapping_pairs` of the folder ``root`` (``n_pairs`` of them spread over the list,
    default all), each in the setting the command chooses for it, appended to ``out`` pair by pair."""
    from freereg_lib.commands.cli import choose_setting

    sample = ICLSample(root)
    listed = overlapping_pairs(sample, min_overlap)
    chosen = [listed[k] for k in spread(len(listed), n_pairs)]
    about = {"root": sample.root.name, "min_overlap": min_overlap, "iters": iters,
             "pairs_listed": len(listed), "pairs_chosen": len(chosen)}
    return _run(sample, chosen, out, iters, about, lambda pair: choose_setting("auto", pair, False, False)[0])


def _run(sample, chosen, out, iters, about=None, setting=lambda pair: "3dmatch") -> pd.DataFrame:
    done = set(_read(out)["pair"])
    t_start = time.perf_counter()
    for n, (i, j) in enumerate(chosen, 1):
        # As the command reads a cloud file: no sensor depth map, the cloud projected on its sensor.
        pair = dataclasses.replace(sample.pair(i, j), sensor_depth=None)
        if pair.name in done:
            continue
        t0 = time.perf_counter()
        name = setting(pair)
        extra = {"setting": name} if about is not None else {}
        rows = pair_rows(pair, config_for(name, ransac_iters=iters))
        _append([{"pair": r["pair"], "gap": j - i, **extra, **{k: r[k] for k in KEEP}} for r in rows], out, about)
        print(f"{n}/{len(chosen)} {pair.name} ({name}): {time.perf_counter() - t0:.1f} s "
              f"({time.perf_counter() - t_start:.0f} s so far)", flush=True)
    return _read(out)


def half_rows(half: str, out: str, n_pairs: int | None = None, iters: int = 50_000) -> pd.DataFrame:
    """Run the pairs within ``half`` of :data:`SPLIT` (``n_pairs`` of them spread over the list,
    default all), appending each pair's four rows to the CSV ``out``; the rows of ``out``."""
    listed = pairs_within(SPLIT[half])
    # 3dmatch: what cli.choose_setting picks for these clouds
    return _run(ICLSample(), [listed[k] for k in spread(len(listed), n_pairs)], out, iters)


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
    p.add_argument("half", choices=sorted(SPLIT) + ["demo", "synthetic", "sample"])
    p.add_argument("--pairs", type=int, help="pairs spread over the half's list (default: all)")
    p.add_argument("--iters", type=int, default=50_000)
    p.add_argument("--demo", metavar="DIR", help="the official demo folder (FreeReg/data/demo), for 'demo'")
    p.add_argument("--root", metavar="DIR", default=str(TUM_ROOT), help="the folder, for 'sample' (default: TUM fr1_rpy)")
    p.add_argument("--min-overlap", type=float, default=0.3, help="the least overlap of a pair, for 'sample'")
    p.add_argument("--out", required=True, help="the rows as CSV (appended to)")
    a = p.parse_args(argv)
    if (a.pairs is not None and a.pairs < 1) or a.iters < 1:
        p.error("--pairs and --iters must be >= 1")
    if a.half == "demo":
        if not a.demo:
            p.error("demo needs --demo DIR (the official demo folder)")
        demo_rows(a.demo, a.out, a.iters)
    elif a.half == "sample":
        sample_rows(a.out, a.root, a.min_overlap, a.pairs, a.iters)
    elif a.half == "synthetic":
        synthetic_rows(a.out, a.pairs or 20, a.iters)
    else:
        half_rows(a.half, a.out, a.pairs, a.iters)
    return 0


if __name__ == "__main__":
    sys.exit(main())
