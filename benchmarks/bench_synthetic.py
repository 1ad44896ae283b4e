"""``python benchmarks/bench_synthetic.py``: milliseconds per synthetic pair, overlaps and cloud sizes."""
from __future__ import annotations

import time

from freereg_lib.data.synthetic.pairs import KINDS, make_pair

for kind in KINDS:
    make_pair(kind, seed=0)  # warm-up: imports, cached meshes
    t0 = time.perf_counter()
    pairs = [make_pair(kind, seed=s) for s in range(5)]
    dt = (time.perf_counter() - t0) / len(pairs)
    ov = ", ".join(f"{p.meta['overlap']:.2f}" for p in pairs)
    npts = ", ".join(str(len(p.points)) for p in pairs)
    print(f"{kind}: {dt * 1000:.0f} ms/pair; overlaps {ov}; points {npts}")
