#!/usr/bin/env python
"""Time per 480 x 640 image of the micro monocular depth.

    python benchmarks/bench_micro_depth.py [--images 4] [--reps 3] [--threads 1]

``get_backend("micro").mono_depth(image)`` (the micro ZoeDepth through ``ZoeDepthEstimator``:
processor, image + flip in one call, bicubic resize back) on held-out synthetic indoor images,
one warm-up call, then the median / min / max seconds per image over images x repetitions; and
``mono_depth_batch`` of all images at once (per image). Prints the machine's load average,
since the CPU may be shared.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--images", type=int, default=4)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=2026)
    a = p.parse_args(argv)

    import torch

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data.synthetic import make_pairs
    from freereg_lib.models import get_backend

    torch.set_num_threads(a.threads)
    images = [pr.image for pr in make_pairs(a.images, "indoor", seed=a.seed)]
    backend = get_backend("micro", FreeRegConfig(), device="cpu")
    backend.mono_depth(images[0])  # warm-up (loads the weights)
    times = []
    for _ in range(a.reps):
        for im in images:
            t = time.perf_counter()
            backend.mono_depth(im)
            times.append(time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(a.reps):
        backend.mono_depth_batch(images)
    batched = (time.perf_counter() - t) / (a.reps * len(images))
    print(f"micro ZoeDepth, {images[0].shape[0]} x {images[0].shape[1]} image, torch threads {a.threads}, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"  mono_depth: median {np.median(times):.3f} s per image (min {min(times):.3f}, max {max(times):.3f}; "
          f"{len(times)} calls)")
    print(f"  mono_depth_batch of {len(images)}: {batched:.3f} s per image")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
