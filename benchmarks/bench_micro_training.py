#!/usr/bin/env python
"""Seconds per training step of each micro diffusion stage on this machine, and what the
committed schedule (``freereg_lib.training.retrain``) costs at those rates.

    python benchmarks/bench_micro_training.py [--rooms 20] [--steps 10] [--threads 2]

Renders ``--rooms`` training rooms (timed: rooms per second), then runs
``train_diffusion.main`` on them at the real size (128 x 192, batch 16) twice: 2 steps of each
stage, then resumed to ``2 + --steps``; a stage's rate is the seconds its checkpoint log gained
over those steps (each includes one validation, as every 100th step of a real run does). Both
precisions are timed: float32 and ``--mixed-precision bf16`` (bfloat16 autocast). The
latent encoding is timed on all the views. The estimate multiplies the steps every phase of
``retrain.PHASES`` trains by the rates of that phase's precision and adds the rendering and the
encoding; it leaves out
loading the views and models (seconds). Prints the machine's CPU and load average, since the
CPU may be shared.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_meter import cpu_model  # noqa: E402  (this folder is on sys.path when run as a script)

WARM = 2  # steps before the timed ones: the first steps of a stage pay for allocation
PRECISIONS = ("no", "bf16")  # train_diffusion --mixed-precision


def schedule_steps() -> list[dict[str, int]]:
    """Steps each phase of the committed schedule trains, per stage (a continued stage trains
    from the step the previous phase left it at, a restarted ControlNet from step 0)."""
    from freereg_lib.training import retrain
    from freereg_lib.training import train_diffusion as T

    done = {s: 0 for s in T.STAGES}
    phases = []
    for argv in retrain.phase_argv(Path("x"), Path("y"), None):
        a = T.parse_args(argv)
        if a.restart_controlnet:
            done["controlnet"] = 0
        target = {s: getattr(a, f"steps_{s}") for s in T.STAGES}
        phases.append({s: target[s] - done[s] for s in a.stages}
                      | {"rooms": a.scenes, "precision": a.mixed_precision})
        done.update({s: target[s] for s in a.stages})
    return phases


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rooms", type=int, default=20)
    p.add_argument("--steps", type=int, default=10, help="timed steps per stage")
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)

    import torch

    from freereg_lib.models.micro import diffusion as M
    from freereg_lib.training import retrain
    from freereg_lib.training import train_diffusion as T
    from freereg_lib.training.views import render_views, save_views

    torch.set_num_threads(a.threads)
    print(f"{cpu_model()}, {os.cpu_count()} cores, torch on {a.threads} threads, "
          f"load average {os.getloadavg()[0]:.2f}", flush=True)
    t = time.perf_counter()
    views = render_views(a.rooms, retrain.VIEWS_PER_SCENE, progress=False)
    rooms_per_s = a.rooms / (time.perf_counter() - t)

    vae = M.build(0)["vae"]
    rgb = torch.from_numpy(views["rgb"]).float() / 127.5 - 1.0
    t = time.perf_counter()
    T.encode_latents(vae, rgb)
    views_per_s = len(rgb) / (time.perf_counter() - t)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_views(views, tmp / "views.npz", a.rooms, retrain.VIEWS_PER_SCENE)
        common = ["--views", str(tmp / "views.npz"), "--scenes", str(a.rooms), "--threads", str(a.threads)]

        def run(steps: int, precision: str) -> dict[str, float]:
            out = tmp / f"run_{precision}"
            T.main(common + ["--out", str(out), "--steps-vae", str(steps), "--steps-unet", str(steps),
                             "--steps-controlnet", str(steps), "--checkpoint-every", str(steps),
                             "--mixed-precision", precision])
            return {s: torch.load(out / s / "checkpoint.pt", weights_only=False)["log"]["seconds"]
                    for s in T.STAGES}

        rates = {}
        for precision in PRECISIONS:
            before = run(WARM, precision)
            after = run(WARM + a.steps, precision)
            rates[precision] = {s: (after[s] - before[s]) / a.steps for s in T.STAGES}

    print(f"\nrendering: {rooms_per_s:.2f} rooms/s ({a.rooms} rooms); latent encoding: {views_per_s:.1f} views/s "
          f"(each view and its mirror image)")
    print("| stage | s per step, float32 (batch 16) | bf16 autocast | speed-up |\n|---|---|---|---|")
    for s in T.STAGES:
        f32, bf16 = rates["no"][s], rates["bf16"][s]
        print(f"| {s} | {f32:.3f} | {bf16:.3f} | {f32 / bf16:.2f}x |")

    phases = schedule_steps()
    biggest = max(ph["rooms"] for ph in phases)
    rows = [("rendering", f"{biggest} rooms", biggest / rooms_per_s)]
    for i, ph in enumerate(phases, 1):
        n_views = ph["rooms"] * retrain.VIEWS_PER_SCENE
        rows.append((f"phase {i}: encoding", f"{n_views} views", n_views / views_per_s))
        rate, tag = rates[ph["precision"]], "" if ph["precision"] == "no" else f" ({ph['precision']})"
        rows += [(f"phase {i}: {s}{tag}", f"{ph[s]} steps", ph[s] * rate[s]) for s in T.STAGES if s in ph]
    print("\nThe committed schedule (python -m freereg_lib.training.retrain) at these rates, estimated:")
    print("| part | work | min |\n|---|---|---|")
    for name, work, sec in rows:
        print(f"| {name} | {work} | {sec / 60:.1f} |")
    total = sum(sec for *_, sec in rows) / 60
    print(f"| **total** | | **{total:.0f}** |")
    print(f"\nestimated retraining from scratch: {total:.0f} min ({'within' if total <= 180 else 'over'} 3 hours)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
