"""Where a run's last bits go between CPUs: committed test pairs' chain under several kernel settings.

    python benchmarks/bench_cross_cpu.py [--pairs 0 33 66] [--out runs/bench_cross_cpu]

Part 1 runs the micro chain on each pair in a fresh process per kernel setting, as another CPU would
choose its kernels: this CPU's default; torch's AVX2 kernels with oneDNN capped at AVX2 and OpenBLAS
told it is a Haswell (a CPU without AVX-512); torch's scalar kernels; oneDNN off; two torch threads.
Against the default it prints the largest difference of the monocular depth, the diffusion and
the FPFH descriptors, the share of mutual matches that differ (w = 1, 0, 0.5), and how many of the
six (method, solver) outcomes flip.

Part 2 perturbs the default process's monocular depth, then its diffusion maps, by a relative 1e-6
(what another kernel path does) and measures the same: which step turns a last-bit difference into
other matches. The figures are in docs/reproducibility.md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SETTINGS = {
    "default": {},
    "avx2 kernels": {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "OPENBLAS_CORETYPE": "Haswell"},
    "scalar torch kernels": {"ATEN_CPU_CAPABILITY": "default"},
    "oneDNN off": {"FREEREG_BENCH_ONEDNN_OFF": "1"},
    "2 torch threads": {"FREEREG_BENCH_THREADS": "2"},
}
ARRAYS = ("mono_depth", "diff_image", "diff_depth", "geo_image", "geo_depth")
WEIGHTS = (1.0, 0.0, 0.5)


def _pair_and_backend(k: int, threads: int = 1):
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend
    from freereg_lib.training.splits import SPLITS

    split = SPLITS["test"]
    cfg = FreeRegConfig(seed=split.noise_seed, cpu_threads=threads)
    return synthetic.make_pair("indoor", seed=split.pair_seeds(k + 1)[k]), get_backend("micro", cfg, device="cpu"), cfg


def _outcome(pair, feats, cfg) -> dict:
    from freereg_lib import pipeline
    from freereg_lib.training.evaluate_split import VARIANTS

    matches = {w: pipeline.match(feats, w) for w in WEIGHTS}
    rows = pipeline.variant_rows(pair, feats, cfg, VARIANTS)
    return {"matches": {str(w): sorted(zip(m.idx_image.tolist(), m.idx_depth.tolist())) for w, m in matches.items()},
            "registered": [bool(r["registered"]) for r in rows]}


def child(k: int, out: Path) -> None:
    """One pair under the kernel setting of this process's environment: arrays and outcome to ``out``."""
    import torch

    if os.environ.get("FREEREG_BENCH_ONEDNN_OFF"):
        torch.backends.mkldnn.enabled = False
    from freereg_lib import pipeline

    pair, backend, cfg = _pair_and_backend(k, int(os.environ.get("FREEREG_BENCH_THREADS", "1")))
    t0 = time.perf_counter()
    feats = pipeline.compute_features(pair, backend, cfg, True, True)
    seconds = time.perf_counter() - t0
    np.savez(out, **{a: getattr(feats, a) for a in ARRAYS})
    out.with_suffix(".json").write_text(json.dumps({**_outcome(pair, feats, cfg), "seconds": seconds}))


def compare(a: dict, b: dict, oa: dict, ob: dict) -> dict:
    """Largest absolute differences of the arrays, share of matches that differ per weight, flips."""
    diffs = {name: float(np.nanmax(np.abs(a[name] - b[name]))) if a[name].shape == b[name].shape else float("inf")
             for name in ARRAYS}
    moved = {}
    for w in map(str, WEIGHTS):
        x, y = set(map(tuple, oa["matches"][w])), set(map(tuple, ob["matches"][w]))
        moved[w] = len(x ^ y) / max(1, len(x | y))
    flips = sum(p != q for p, q in zip(oa["registered"], ob["registered"]))
    return {"max_diff": diffs, "matches_differ": moved, "outcomes_flipped": flips}


def perturbed(k: int, eps: float = 1e-6, seed: int = 0) -> dict:
    """Part 2: the default chain with its monocular depth, then its diffusion maps, times (1 + eps * noise)."""
    from freereg_lib import pipeline

    pair, backend, cfg = _pair_and_backend(k)
    view = pipeline.depth_view(pair, cfg)
    maps = pipeline.diffusion_maps_batch([pair], [view], backend, cfg.layers)[0]
    mono = np.asarray(backend.mono_depth(pair.image, depth_gt=pair.depth_gt), dtype=np.float64)
    rng = np.random.default_rng(seed)
    base = pipeline.compute_features(pair, backend, cfg, view=view, maps=maps, mono=mono)
    arrays = {a: getattr(base, a) for a in ARRAYS}
    out = {}
    bumped_mono = mono * (1 + eps * rng.standard_normal(mono.shape))
    bumped_maps = tuple({layer: m * (1 + eps * rng.standard_normal(m.shape)).astype(m.dtype) for layer, m in side.items()}
                        for side in maps)
    for name, kwargs in (("depth x (1 + 1e-6 noise)", {"maps": maps, "mono": bumped_mono}),
                         ("maps x (1 + 1e-6 noise)", {"maps": bumped_maps, "mono": mono})):
        feats = pipeline.compute_features(pair, backend, cfg, view=view, **kwargs)
        out[name] = compare(arrays, {a: getattr(feats, a) for a in ARRAYS}, _outcome(pair, base, cfg),
                            _outcome(pair, feats, cfg))
    return out


def _line(name: str, c: dict) -> str:
    d, m = c["max_diff"], c["matches_differ"]
    return (f"  {name:24s} depth {d['mono_depth']:.1e}  diffusion {max(d['diff_image'], d['diff_depth']):.1e}  "
            f"FPFH image {d['geo_image']:.1e} cloud {d['geo_depth']:.1e}  matches differ: D {100 * m['1.0']:4.1f} %, "
            f"G {100 * m['0.0']:4.1f} %, fused {100 * m['0.5']:4.1f} %  flips {c['outcomes_flipped']} of 6")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, nargs="+", default=[0, 33, 66], help="test-split pair indices")
    ap.add_argument("--out", default="runs/bench_cross_cpu")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        child(args.child, Path(args.child_out))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("Part 1: each kernel setting in its own process, against this CPU's default (largest |difference|)")
    for k in args.pairs:
        print(f"test pair {k}:")
        results = {}
        for name, env in SETTINGS.items():
            path = out / f"pair{k}_{name.replace(' ', '_')}.npz"
            subprocess.run([sys.executable, __file__, "--child", str(k), "--child-out", str(path)], check=True,
                           env={**os.environ, "OPENBLAS_NUM_THREADS": "1", **env}, stderr=subprocess.DEVNULL)
            with np.load(path) as z:
                results[name] = ({a: z[a] for a in ARRAYS}, json.loads(path.with_suffix(".json").read_text()))
        base, base_out = results["default"]
        print(f"  default: features {base_out['seconds']:.1f} s")
        for name, (arrays, outcome) in results.items():
            if name != "default":
                print(_line(name, compare(base, arrays, base_out, outcome)) + f"  ({outcome['seconds']:.1f} s)")
    print("\nPart 2: the default chain with one input perturbed by a relative 1e-6")
    for k in args.pairs:
        print(f"test pair {k}:")
        for name, c in perturbed(k).items():
            print(_line(name, c))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
