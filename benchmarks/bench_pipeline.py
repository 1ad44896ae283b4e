#!/usr/bin/env python
"""Where the time and memory of one FreeReg pair go, stage by stage.

    python benchmarks/bench_pipeline.py [--mode cpu|gpu|ci] [--pairs N] [--reps R]
                                        [--threads T] [--json PATH]

Modes
    cpu  The whole chain with the ``stub`` backend on synthetic indoor pairs of 512 x 704
         (the paper's indoor configuration: both solvers at 50k RANSAC iterations), then
         the ``tiny`` backend's diffusion and monocular-depth stages (the real diffusers /
         transformers code path with miniature random-weight models), then the matching
         micro-benchmark: mutual nearest neighbours of 10k x 10k keypoints, C = 384 + 33.
    gpu  The same chain with full-size Stable Diffusion v1.5 UNet, depth ControlNet v1.1,
         VAE, CLIP ViT-L/14 text encoder and ZoeDepth (ZoeD_N, BEiT-L 384), all built from
         their published configurations with random weights (speed does not depend on the
         weights, and nothing is downloaded), float16 on CUDA (``--dtype``; the library's
         default is the paper's float32); the stub chain and the
         matching micro-benchmark (CPU and CUDA) on the same machine. Random weights give
         meaningless features, so the solvers there run all their iterations: a worst case.
    micro The whole chain with the ``micro`` backend (the models trained here: diffusion and
         monocular depth) on synthetic indoor pairs of 480 x 640 with FPFH (and with a micro
         FCGF when one is in the package), both solvers at 50k iterations: "one micro FreeReg pair"
         on this machine.
    ci   Tiny sizes (a 96 x 128 pair, 500 RANSAC iterations, a 64 x 64 tiny backend with 5
         DDIM steps, 1k x 1k matching), one repetition, torch on one thread: a check that
         the script works, in seconds. Its numbers mean nothing.

Each stage is timed inside ``pipeline.run_pair`` itself: the library functions the pipeline
calls (``pipeline.depth_view``, the backend's ``diffusion_rgb_batch`` /
``diffusion_depth_batch`` / ``mono_depth``, ``features.pca_reduce`` + ``sample_features``, ``geometric.geometric_features``
+ ``pixel_features``, ``pipeline.match``, ``pose.pnp_ransac``, ``pose.kabsch_ransac``,
``pipeline.evaluate``) are wrapped for the duration of the run, so the table measures exactly
what the pipeline does; "other" is the rest of ``run_pair`` (keypoints, lifting, validation).
Times are medians over pairs x repetitions after one warm-up run, with min and max.

Memory is measured in one extra run per chain (so the tracing does not slow the timed runs):

* ``py peak MiB``: the largest increase of memory traced by ``tracemalloc`` during a call of
  the stage (Python objects and every NumPy / OpenCV array; not torch CPU tensors or
  Open3D's C++ buffers);
* ``RSS peak MiB``: the largest increase of the process's peak resident set (``VmHWM``,
  reset through ``/proc/self/clear_refs`` before each call, after ``malloc_trim``): every
  allocator, but memory the allocator still holds from earlier stages is reused without
  showing up, so it is a lower bound;
* ``GPU peak MiB`` (gpu mode): ``torch.cuda.max_memory_allocated`` during the stage,
  absolute (model weights included, as the paper's 12.7 GB is).

Record measured figures in ``benchmarks/README.md`` with the device and the date.
"""
from __future__ import annotations

import os

# The project's default (see the Makefile): OpenBLAS threads spinning on small matrices
# slow a 2-core machine down. Set before NumPy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import json
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
from bench_meter import Meter, device_info, format_device  # noqa: E402  (this folder is on sys.path when run as a script)
from fullsize_models import build_fullsize_backend  # noqa: E402

# The paper's solvers for the full method; ``--variants all`` adds FreeReg-D / FreeReg-G.
PAPER_VARIANTS = (("FreeReg", "pnp"), ("FreeReg", "kabsch"))

# Stage label -> the (module attribute | backend method) the pipeline calls.
STAGES = (
    "projection + densify",
    "stub scene hints",
    "diffusion RGB",
    "diffusion depth",
    "PCA + keypoint sampling",
    "monocular depth",
    "geometric features",
    "matching",
    "solver PnP-RANSAC",
    "solver Kabsch-RANSAC",
    "metrics",
)


# ---------------------------------------------------------------------------------------
# Instrumenting run_pair.

class Recorder:
    """Times (and, with a meter, memory) of every wrapped call, grouped by stage."""

    def __init__(self, meter: Meter | None = None, cuda: bool = False):
        self.meter = meter
        self.cuda = cuda
        self.calls: dict[str, list[dict]] = {}
        self._active: str | None = None

    @contextlib.contextmanager
    def stage(self, name: str):
        if self._active is not None:  # a stage inside another one is counted there
            yield
            return
        self._active = name
        rec: dict = {}
        mem = self.meter.measure(rec) if self.meter else contextlib.nullcontext()
        try:
            with mem:
                t0 = time.perf_counter()
                try:
                    yield
                finally:
                    if self.cuda:
                        import torch

                        torch.cuda.synchronize()
                    rec["s"] = time.perf_counter() - t0
        finally:
            self._active = None
            self.calls.setdefault(name, []).append(rec)

    def wrap(self, name: str, fn):
        def wrapped(*args, **kw):
            with self.stage(name):
                return fn(*args, **kw)

        wrapped.__wrapped__ = fn
        return wrapped


@contextlib.contextmanager
def instrumented(rec: Recorder, backend):
    """Wrap the functions ``pipeline.run_pair`` calls, for the duration of the block."""
    from freereg_lib import features
    from freereg_lib.features import geometric
    from freereg_lib.geometry import pose
    from freereg_lib.pipeline import steps

    targets = [
        (steps, "depth_view", "projection + densify"),
        (steps, "scene_hints", "stub scene hints"),
        (backend, "diffusion_rgb_batch", "diffusion RGB"),
        (backend, "diffusion_depth_batch", "diffusion depth"),
        (features, "pca_reduce", "PCA + keypoint sampling"),
        (features, "sample_features", "PCA + keypoint sampling"),
        (backend, "mono_depth", "monocular depth"),
        (geometric, "geometric_features", "geometric features"),
        (geometric, "pixel_features", "geometric features"),
        (steps, "match", "matching"),
        (pose, "pnp_ransac", "solver PnP-RANSAC"),
        (pose, "kabsch_ransac", "solver Kabsch-RANSAC"),
        (steps, "evaluate", "metrics"),
    ]
    saved = []
    try:
        for obj, attr, stage in targets:
            had_own = attr in vars(obj)
            saved.append((obj, attr, had_own, getattr(obj, attr)))
            setattr(obj, attr, rec.wrap(stage, getattr(obj, attr)))
        yield
    finally:
        for obj, attr, had_own, orig in reversed(saved):
            if had_own:
                setattr(obj, attr, orig)
            else:  # a method wrapped on an instance: drop the instance attribute
                delattr(obj, attr)


def run_chain(pair, backend, cfg, variants, rec: Recorder) -> tuple[float, list[dict]]:
    """One instrumented ``run_pair``; returns its wall time and rows (errors raise)."""
    from freereg_lib import pipeline

    with instrumented(rec, backend):
        t0 = time.perf_counter()
        rows = pipeline.run_pair(pair, backend, cfg, variants)
        if rec.cuda:
            import torch

            torch.cuda.synchronize()
        total = time.perf_counter() - t0
    errors = [f"{r['method']}/{r['solver']}: {r['error']}" for r in rows if r["error"] and r["n_matches"] == 0]
    if errors:
        raise RuntimeError(f"run_pair failed on {pair.name}: " + "; ".join(errors))
    return total, rows


def measure_chain(label: str, pairs, backend, cfg, variants, reps: int, warmup: int,
                  cuda: bool = False, memory: bool = True) -> dict:
    """Per-stage times over ``pairs`` x ``reps`` (after ``warmup`` runs) and memory of one run."""
    for _ in range(warmup):
        run_chain(pairs[0], backend, cfg, variants, Recorder(cuda=cuda))
    stage_times: dict[str, list[float]] = {}
    stage_calls: dict[str, int] = {}
    totals, last_rows = [], []
    for pair in pairs:
        for _ in range(reps):
            rec = Recorder(cuda=cuda)
            total, last_rows = run_chain(pair, backend, cfg, variants, rec)
            totals.append(total)
            for name, calls in rec.calls.items():
                stage_times.setdefault(name, []).append(sum(c["s"] for c in calls))
                stage_calls[name] = len(calls)
            stage_times.setdefault("other (keypoints, lifting, checks)", []).append(
                total - sum(sum(c["s"] for c in calls) for calls in rec.calls.values()))
    mem: dict[str, dict] = {}
    if memory:
        tracemalloc.start()
        try:
            rec = Recorder(Meter(cuda=cuda), cuda=cuda)
            run_chain(pairs[0], backend, cfg, variants, rec)
        finally:
            tracemalloc.stop()
        for name, calls in rec.calls.items():
            mem[name] = {
                k: max((c[k] for c in calls if c.get(k) is not None), default=None)
                for k in ("py_peak_mib", "rss_peak_mib", "gpu_peak_mib")
            }
    return {
        "label": label,
        "backend": getattr(backend, "name", type(backend).__name__),
        "variants": [list(v) for v in variants],
        "times": stage_times,
        "calls": stage_calls,
        "total": totals,
        "memory": mem,
        "rows": [{k: (v if not isinstance(v, float) or np.isfinite(v) else None) for k, v in r.items()}
                 for r in last_rows],
    }


def measure_calls(label: str, backend, calls: list[tuple[str, object]], reps: int, warmup: int,
                  cuda: bool = False, memory: bool = True) -> dict:
    """Stand-alone stages: ``calls`` = [(stage name, zero-argument function)]."""
    times: dict[str, list[float]] = {}
    mem: dict[str, dict] = {}
    for name, fn in calls:
        for _ in range(warmup):
            fn()
        for _ in range(reps):
            rec = Recorder(cuda=cuda)
            with rec.stage(name):
                fn()
            times.setdefault(name, []).append(rec.calls[name][0]["s"])
        if memory:
            tracemalloc.start()
            try:
                rec = Recorder(Meter(cuda=cuda), cuda=cuda)
                with rec.stage(name):
                    fn()
            finally:
                tracemalloc.stop()
            c = rec.calls[name][0]
            mem[name] = {k: c.get(k) for k in ("py_peak_mib", "rss_peak_mib", "gpu_peak_mib")}
    return {"label": label, "backend": getattr(backend, "name", ""), "times": times,
            "calls": {k: 1 for k in times}, "memory": mem}


def measure_pair_batch(backend, pair, cfg, B: int, reps: int, warmup: int, cuda: bool, device: str) -> dict:
    """The diffusion stages of ``B`` pairs in one batch (``cfg.pair_batch = B``, the layers of
    ``cfg.layers``), as ``pipeline.run_pairs`` calls them; times per pair (divided by ``B``)."""
    from freereg_lib import pipeline

    view = pipeline.depth_view(pair, cfg)
    name_rgb = f"diffusion RGB, {B} pairs per call (per pair)"
    name_dep = f"diffusion depth, {B} pairs per call (per pair)"
    calls = [
        (name_rgb, lambda: backend.diffusion_rgb_batch([pair.image] * B, None, cfg.layers)),
        (name_dep, lambda: backend.diffusion_depth_batch([view.dense] * B, None, cfg.layers)),
    ]
    res = measure_calls(f"batch of {B}", backend, calls, reps=reps, warmup=warmup, cuda=cuda)
    res["times"] = {k: [t / B for t in v] for k, v in res["times"].items()}
    res["device"] = device
    print(f"... diffusion stages with {B} pairs per call done", flush=True)
    return res


# ---------------------------------------------------------------------------------------
# The matching micro-benchmark.

def matching_micro(n: int, dim: int, reps: int, device: str, cuda: bool) -> dict:
    """Mutual NN of ``n`` x ``n`` unit descriptors of ``dim`` channels (the depth side a noisy
    permutation of the image side, so about 90 % of the keypoints have a true partner)."""
    from freereg_lib.features import matching

    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, dim)).astype(np.float32)
    b = a[rng.permutation(n)] + 0.7 * rng.standard_normal((n, dim)).astype(np.float32)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    name = f"mutual NN {n // 1000}k x {n // 1000}k, C={dim} ({device})" if n >= 1000 else \
        f"mutual NN {n} x {n}, C={dim} ({device})"
    out = measure_calls("matching micro-benchmark", None,
                        [(name, lambda: matching.mutual_nn(a, b, device=device))],
                        reps=reps, warmup=1, cuda=cuda)
    out["n_mutual"] = int(len(matching.mutual_nn(a, b, device=device)[0]))
    return out


# ---------------------------------------------------------------------------------------
# The table.

def _fmt(x, nd=3):
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{nd}f}"
    return str(x)


def _variants(variants) -> str:
    if [tuple(v) for v in variants] == list(PAPER_VARIANTS):
        return "FreeReg: PnP + Kabsch"
    return f"{len(variants)} variants"


def _stage_order(names):
    build = [s for s in names if s.startswith("model build")]
    known = [s for s in STAGES if s in names]
    rest = [s for s in names if s not in STAGES and s not in build and not s.startswith("other")]
    other = [s for s in names if s.startswith("other")]
    return build + known + rest + other


def format_table(results: list[dict], device: str, gpu: bool) -> str:
    head = ["stage", "backend", "device", "calls", "time median [s]", "min [s]", "max [s]",
            "py peak [MiB]", "RSS peak [MiB]"]
    if gpu:
        head.append("GPU peak [MiB]")
    rows = []
    for res in results:
        dev = res.get("device", device)
        for name in _stage_order(list(res["times"])):
            ts = res["times"][name]
            m = res.get("memory", {}).get(name, {})
            row = [name, res["backend"], dev, str(res.get("calls", {}).get(name, "")),
                   _fmt(statistics.median(ts)), _fmt(min(ts)), _fmt(max(ts)),
                   _fmt(m.get("py_peak_mib"), 1), _fmt(m.get("rss_peak_mib"), 1)]
            if gpu:
                row.append(_fmt(m.get("gpu_peak_mib"), 0))
            rows.append(row)
        if "total" in res:
            ts = res["total"]
            row = [f"END TO END run_pair ({_variants(res['variants'])})",
                   res["backend"], dev, "", _fmt(statistics.median(ts)), _fmt(min(ts)),
                   _fmt(max(ts)), "", ""]
            if gpu:
                row.append("")
            rows.append(row)
        rows.append(None)
    widths = [max(len(h), *(len(r[i]) for r in rows if r)) for i, h in enumerate(head)]
    line = "  ".join("-" * w for w in widths)

    def fmt_row(r):
        return "  ".join(c.ljust(w) if i < 4 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))

    out = [fmt_row(head), line]
    for r in rows:
        out.append(line if r is None else fmt_row(r))
    return "\n".join(out[:-1])


# ---------------------------------------------------------------------------------------
# Main.

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mode", choices=("cpu", "gpu", "ci", "micro"), default="cpu")
    p.add_argument("--pairs", type=int, default=1, help="synthetic indoor pairs (seeds 0..N-1)")
    p.add_argument("--reps", type=int, default=None,
                   help="timed repetitions per pair (default: 3 cpu/gpu, 1 ci)")
    p.add_argument("--warmup", type=int, default=None,
                   help="untimed warm-up runs before the timed ones (default: 1 cpu/gpu, 0 ci)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch and OpenCV threads (default: theirs; ci: 1)")
    p.add_argument("--variants", choices=("paper", "all"), default="paper",
                   help="paper: FreeReg with PnP and Kabsch; all: the 4 default variants")
    p.add_argument("--ddim-steps", type=int, default=None, help="override cfg.ddim_steps (gpu: 20)")
    p.add_argument("--pnp-method", default=None,
                   help="cfg.pnp_method: the PnP-RANSAC method of pose.PNP_METHODS (default: the "
                        "config's, \"iterative\", the paper's; \"usac\" is the CPU speed-up)")
    p.add_argument("--kabsch-scoring", default=None, choices=("official", "open3d"),
                   help="cfg.kabsch_scoring (default: the config's, \"official\", open3d 0.12's algorithm as the "
                        "paper ran it; \"open3d\": the installed Open3D's call)")
    p.add_argument("--pnp-workers", type=int, default=1,
                   help="cfg.pnp_workers: threads sharing the PnP-RANSAC iterations (default 1)")
    p.add_argument("--batched-guidance", action="store_true",
                   help="cfg.batched_guidance: both guidance branches in one UNet call")
    p.add_argument("--pca-device", default=None,
                   help="cfg.pca_device: the PCA in float32 torch on this device (e.g. cuda)")
    p.add_argument("--match-device", default=None,
                   help="cfg.match_device: the pipeline's mutual NN on this device (e.g. cuda)")
    p.add_argument("--pair-batch", type=int, default=1,
                   help="also time the diffusion stages on B copies of a pair in one call "
                        "(cfg.pair_batch = B), reported per pair (time / B)")
    p.add_argument("--device", default=None, help="gpu mode: the torch device (default cuda)")
    p.add_argument("--dtype", default="float16", choices=("float16", "bfloat16", "float32"),
                   help="gpu mode: dtype of the full-size diffusion models on CUDA (default float16, as "
                        "the recorded numbers; float32 is the library's and the paper's default)")
    p.add_argument("--resize", default=None,
                   help="gpu mode: diffusion input HxW (default 512x704); smaller sizes are "
                        "for smoke tests only")
    p.add_argument("--match-n", type=int, default=None,
                   help="matching micro-benchmark size (default 10000; ci 1000; 0 skips)")
    p.add_argument("--no-tiny", action="store_true", help="cpu mode: skip the tiny backend")
    p.add_argument("--json", default=None, help="also write the raw measurements here")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    import cv2
    import torch

    from freereg_lib import config_for
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    ci = args.mode == "ci"
    gpu = args.mode == "gpu"
    threads = args.threads if args.threads is not None else (1 if ci else None)
    if threads is not None:
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)
    reps = args.reps if args.reps is not None else (1 if ci else 3)
    warmup = args.warmup if args.warmup is not None else (0 if ci else 1)
    device = args.device or ("cuda" if gpu else "cpu")
    if gpu and device.startswith("cuda") and not torch.cuda.is_available():
        print(f"gpu mode: not measured: no GPU (torch {torch.__version__}, "
              "torch.cuda.is_available() is False). Run it on a CUDA machine, or pass "
              "--device cpu --resize 64x64 --ddim-steps 1 for a (slow) smoke test of the code path.",
              file=sys.stderr)
        return 2
    cuda = device.startswith("cuda")

    image_size = (96, 128) if ci else (480, 640) if args.mode == "micro" else (512, 704)
    overrides = dict(ransac_iters=500, keypoint_grid=(12, 16), ddim_steps=5) if ci else {}
    if args.ddim_steps is not None:
        overrides["ddim_steps"] = args.ddim_steps
    if args.pnp_method is not None:
        overrides["pnp_method"] = args.pnp_method
    overrides["pnp_workers"] = args.pnp_workers
    if args.kabsch_scoring is not None:
        overrides["kabsch_scoring"] = args.kabsch_scoring
    if args.batched_guidance:
        overrides["batched_guidance"] = True
    if args.pca_device is not None:
        overrides["pca_device"] = args.pca_device
    if args.match_device is not None:
        overrides["match_device"] = args.match_device
    if args.mode == "gpu":
        overrides["dtype"] = args.dtype
    cfg = config_for("synthetic_indoor", **overrides)
    variants = PAPER_VARIANTS if args.variants == "paper" else None
    if variants is None:
        from freereg_lib.pipeline import DEFAULT_VARIANTS

        variants = DEFAULT_VARIANTS
    info = device_info(args.mode, device)
    print(format_device(info), flush=True)
    pairs = [synthetic.make_pair("indoor", seed=s, image_size=image_size) for s in range(max(args.pairs, 1))]
    print(f"pairs:  {len(pairs)} synthetic indoor, {image_size[0]} x {image_size[1]}, "
          f"{len(pairs[0].points)} points; RANSAC {cfg.ransac_iters} iterations; PnP method {cfg.pnp_method} ({cfg.pnp_workers} worker(s)); "
          f"batched guidance {cfg.batched_guidance}; PCA on {cfg.pca_device or 'host (NumPy)'}; "
          f"matching on {cfg.match_device}; "
          f"keypoint grid {cfg.keypoint_grid[0]} x {cfg.keypoint_grid[1]}; "
          f"{reps} timed repetition(s) per pair after {warmup} warm-up", flush=True)

    results: list[dict] = []
    notes: list[str] = []

    if args.mode == "micro":
        from freereg_lib.models.micro import fcgf as MF

        # FCGF only when a micro FCGF exists (none is committed: README, "Micro FCGF").
        geos = ["fpfh"] + (["fcgf"] if (MF.folder_of(None) / MF.WEIGHTS_FILE).is_file() else [])
        for geo in geos:
            c = cfg.override(geometric=geo)
            micro = get_backend("micro", c)
            res = measure_chain(f"micro chain ({geo})", pairs, micro, c, variants, reps, warmup)
            res["device"] = "cpu"
            results.append(res)
            print(f"... micro chain ({geo}) done ({statistics.median(res['total']):.2f} s per pair)", flush=True)
        notes.append(f"micro backend: {micro.label}; diffusion input {micro.resize_hw[0]} x {micro.resize_hw[1]}, "
                     f"DDIM {cfg.ddim_steps} steps")
        return report(results, notes, info, device, gpu, results, args.json)

    # 1. The stub chain (CPU).
    stub = get_backend("stub", cfg, **({"resize_hw": (128, 192)} if ci else {}))
    res = measure_chain("stub chain", pairs, stub, cfg, variants, reps, warmup)
    res["device"] = "cpu"
    results.append(res)
    print(f"... stub chain done ({statistics.median(res['total']):.2f} s per pair)", flush=True)

    # 2. The tiny backend's model stages (CPU), or the full-size models (gpu mode).
    if gpu:
        rhw = tuple(int(v) for v in args.resize.lower().split("x")) if args.resize else cfg.resize_hw
        t0 = time.perf_counter()
        full, n_params = build_fullsize_backend(cfg, device, rhw)
        build_s = time.perf_counter() - t0
        notes.append(f"full-size models built in {build_s:.1f} s (random init); parameters: "
                     + ", ".join(f"{k} {v / 1e6:.0f}M" for k, v in n_params.items())
                     + f"; diffusion input {rhw[0]} x {rhw[1]}, DDIM {cfg.ddim_steps} steps, "
                     f"dtype {full.dtype}")
        res = measure_chain("full-size chain", pairs, full, cfg, variants, reps, warmup, cuda=cuda)
        res["device"] = device
        results.append(res)
        if full.nonfinite:
            notes.append(f"random float16 weights produced {full.nonfinite} non-finite feature "
                         "values over all runs; replaced by 0 (speed does not depend on them)")
        print(f"... full-size chain done ({statistics.median(res['total']):.2f} s per pair)", flush=True)
        if args.pair_batch > 1:
            results.append(measure_pair_batch(full, pairs[0], cfg, args.pair_batch, reps, warmup, cuda, device))
    elif not args.no_tiny:
        from freereg_lib import pipeline

        kw = dict(resize_hw=(64, 64), zoe_input_hw=(32, 48)) if ci else {}
        tiny = get_backend("tiny", cfg, device="cpu", **kw)
        pair = pairs[0]
        view = pipeline.depth_view(pair, cfg)
        calls = [
            ("model build (diffusion, once)", lambda: tiny.diffusion),
            ("model build (ZoeDepth, once)", lambda: tiny.zoe),
        ]
        t_build = measure_calls("tiny build", tiny, calls, reps=1, warmup=0, memory=False)
        calls = [
            # As run_pair calls them: a batch of one pair, the layers of cfg.layers.
            ("diffusion RGB", lambda: tiny.diffusion_rgb_batch([pair.image], None, cfg.layers)),
            ("diffusion depth", lambda: tiny.diffusion_depth_batch([view.dense], None, cfg.layers)),
            ("monocular depth", lambda: tiny.mono_depth(pair.image)),
        ]
        res = measure_calls("tiny stages", tiny, calls, reps=reps, warmup=warmup)
        for k in ("times", "calls"):
            res[k] = {**t_build[k], **res[k]}
        res["device"] = "cpu"
        results.append(res)
        if args.pair_batch > 1:
            results.append(measure_pair_batch(tiny, pair, cfg, args.pair_batch, reps, warmup, False, "cpu"))
        notes.append(f"tiny backend: diffusion input {tiny.resize_hw[0]} x {tiny.resize_hw[1]}, "
                     f"DDIM {cfg.ddim_steps} steps, random miniature models (numbers are not "
                     "those of SD v1.5)")
        print("... tiny stages done", flush=True)

    # 3. Matching micro-benchmark.
    n = args.match_n if args.match_n is not None else (1000 if ci else 10_000)
    if n > 0:
        devs = ["cpu"] + ([device] if cuda else [])
        for d in devs:
            res = matching_micro(n, 384 + 33, reps=reps, device=d, cuda=d.startswith("cuda"))
            res["backend"] = "-"
            res["device"] = d
            results.append(res)
            notes.append(f"mutual NN {n} x {n} on {d}: {res['n_mutual']} mutual pairs")
        print("... matching micro-benchmark done", flush=True)

    return report(results, notes, info, device, gpu, results[:1], args.json)


def report(results, notes, info, device, gpu, chains, json_path) -> int:
    """The stage table, the notes, each chain's end-to-end line and the optional JSON file."""
    print()
    print(format_table(results, device, gpu))
    for note in notes:
        print(f"note: {note}")
    for r in chains:
        print(f"{r['label']}, one pair end to end (run_pair, {_variants(r['variants'])}): "
              f"{statistics.median(r['total']):.2f} s median (min {min(r['total']):.2f}, max {max(r['total']):.2f})")
    if json_path:
        with open(json_path, "w") as fh:
            json.dump({"device": info, "notes": notes, "results": results}, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
