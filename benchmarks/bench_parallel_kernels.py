"""Threads of parallel kernels: K torch processes at once, with and without a share of the cores each.

    python benchmarks/bench_parallel_kernels.py [--copies 2] [--pairs 2]

Runs ``python -m freereg_lib.training.evaluate --pairs P --trained-only`` (the micro FreeReg-D
chain: torch diffusion features, PnP) once alone, then K copies at the same time with the
environment's thread settings minus ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` (torch then
uses every core in each copy), then K copies with the share the batch runner's local Dask
workers give their kernels (:func:`freereg_lib.commands.cluster.worker_thread_env`), and prints the
wall times. This is what ``batch run --executor dask`` on a CPU machine and ``pytest -n 2``
do: several notebook kernels at once on the same cores.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from freereg_lib.commands.cluster import THREAD_VARIABLES, available_cores, worker_thread_env  # noqa: E402


def run_copies(copies: int, pairs: int, env: dict) -> float:
    cmd = [sys.executable, "-m", "freereg_lib.training.evaluate", "--pairs", str(pairs), "--trained-only"]
    t0 = time.perf_counter()
    procs = [subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for _ in range(copies)]
    codes = [p.wait() for p in procs]
    if any(codes):
        raise SystemExit(f"a copy of {' '.join(cmd)} exited with {codes}")
    return time.perf_counter() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--copies", type=int, default=2)
    p.add_argument("--pairs", type=int, default=2)
    args = p.parse_args(argv)
    cores = available_cores()
    free = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    shared = {**free, **worker_thread_env(args.copies, cores, environ={})}
    print(f"{cores} cores; each copy: micro FreeReg-D on {args.pairs} synthetic pair(s), models loaded included")
    alone = run_copies(1, args.pairs, free)
    print(f"  one copy alone, torch on all cores:               {alone:7.1f} s")
    together = run_copies(args.copies, args.pairs, free)
    print(f"  {args.copies} copies at once, torch on all cores each:     {together:7.1f} s "
          f"({together / (args.copies * alone):.1f}x one after the other)")
    capped = run_copies(args.copies, args.pairs, shared)
    share = ", ".join(f"{k}={shared[k]}" for k in THREAD_VARIABLES)
    print(f"  {args.copies} copies at once, {share}: {capped:7.1f} s "
          f"({capped / (args.copies * alone):.1f}x one after the other)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
