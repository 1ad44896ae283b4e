"""What ending a notebook's kernel costs: papermill runs of a one-cell notebook that imports what
the project's notebooks import (torch, diffusers, Open3D, matplotlib), with nbclient's graceful
shutdown and with ``shutdown_kernel="immediate"`` (the kernel is killed once the notebook has run,
as ``freereg_lib.commands.batch``, ``reproduce`` and the tests do).

    python benchmarks/bench_kernel_shutdown.py [--runs 6]

Prints, per mode, the wall seconds of each run, their mean and the kernels' CPU seconds a run
(user + system of the reaped kernel processes). The runs alternate between the modes so that a
change in the machine's load falls on both.
"""
from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

CELL = "import torch, diffusers, open3d, matplotlib.pyplot\nx = 1"
MODES = ("graceful", "immediate")


def children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=6, help="runs per mode")
    args = parser.parse_args()

    import nbformat
    import papermill as pm

    tmp = Path(tempfile.mkdtemp())
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(CELL)])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(nb, tmp / "imports.ipynb")

    walls: dict[str, list[float]] = {m: [] for m in MODES}
    cpu: dict[str, float] = {m: 0.0 for m in MODES}
    for _ in range(args.runs):
        for mode in MODES:
            c0, t0 = children_cpu(), time.perf_counter()
            pm.execute_notebook(str(tmp / "imports.ipynb"), str(tmp / "out.ipynb"), kernel_name="python3",
                                progress_bar=False, shutdown_kernel=mode)
            walls[mode].append(time.perf_counter() - t0)
            cpu[mode] += children_cpu() - c0

    print(f"one-cell notebook `{CELL.splitlines()[0]}`, {args.runs} runs per mode")
    print("| shutdown | wall s per run | mean wall s | kernel CPU s per run |")
    print("|---|---|---:|---:|")
    for mode in MODES:
        runs = " ".join(f"{w:.2f}" for w in walls[mode])
        print(f"| {mode} | {runs} | {statistics.mean(walls[mode]):.2f} | {cpu[mode] / args.runs:.2f} |")


if __name__ == "__main__":
    main()
