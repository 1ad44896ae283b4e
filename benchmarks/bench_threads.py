"""One pair's micro diffusion maps at ``cpu_threads`` 1 and 0 (torch's own count), quiet and beside
one busy process, with a hash of the maps: the figures of docs/performance.md, "Threads on a CPU".

    python benchmarks/bench_threads.py [--repeats 3] [--seed 3]

The busy process is a Python loop on one core (as ``yes > /dev/null`` is); it is stopped before
the command ends. Seconds are the best of ``--repeats`` after one warm-up call.
"""
from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import time

import numpy as np

from freereg_lib import pipeline
from freereg_lib.config import config_for
from freereg_lib.data import synthetic
from freereg_lib.models import get_backend


def maps_hash(maps: tuple[dict, dict]) -> str:
    """A short hash of a pair's image-side and depth-side maps, layer by layer."""
    h = hashlib.sha1()
    for side in maps:
        for layer in sorted(side):
            h.update(np.ascontiguousarray(side[layer]).tobytes())
    return h.hexdigest()[:12]


def time_maps(threads: int, pair, repeats: int) -> tuple[float, str]:
    cfg = config_for("3dmatch", cpu_threads=threads)
    backend = get_backend("micro", cfg)
    view = pipeline.depth_view(pair, cfg)
    pipeline.diffusion_maps_batch([pair], [view], backend, cfg.layers)  # loads the models
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = pipeline.diffusion_maps_batch([pair], [view], backend, cfg.layers)[0]
        best = min(best, time.perf_counter() - t)
    return best, maps_hash(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {args.repeats}")
    pair = synthetic.make_pair(seed=args.seed)
    rows = []
    for load in ("quiet", "busy"):
        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if load == "busy" else None
        try:
            for threads in (1, 0):
                seconds, digest = time_maps(threads, pair, args.repeats)
                rows.append((load, threads, seconds, digest))
                print(f"{load:5s} cpu_threads={threads}: {seconds:6.2f} s  maps {digest}", flush=True)
        finally:
            if busy is not None:
                busy.kill()
                busy.wait()
    same = {t: len({d for _, tt, _, d in rows if tt == t}) == 1 for t in (1, 0)}
    print(f"maps identical quiet and busy: cpu_threads=1 {same[1]}, cpu_threads=0 {same[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
