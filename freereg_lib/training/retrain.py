"""Retrain the committed micro diffusion weights from scratch in one command: the three phases
of their schedule, then the total time.

    python -m freereg_lib.training.retrain [--out runs/micro/retrain]
        [--export runs/micro/retrain/weights] [--threads N]

The committed weights were made over rounds 1-6 (``weights/training.json``, "history"); the steps
that reach them are the UNet's of three phases and the ControlNet's of one (round 6 rebuilt it from
the final UNet), and this runs those phases in order with :mod:`.train_diffusion`:

1. from scratch on rooms 0-499: VAE 700, UNet 2,000 steps (round 2's; its ControlNet is not
   trained, ``--steps-controlnet 0``);
2. ``--init-from`` phase 1's export on rooms 0-1999: the UNet on to 4,000 steps (round 4's);
3. ``--init-from`` phase 2's export on the same rooms: the UNet on to 6,000 steps (round 5's), then
   a ControlNet built afresh from it (``--restart-controlnet``) and trained 2,600 steps (round 6's),
   each with a cosine decay of the learning rate to 0.

The ControlNets that rounds 2, 4 and 5 trained on the intermediate UNets are left out: round 6
replaced them, and only their UNet steps reach the committed weights.

The 2,000 rooms are rendered once; phase 1 reads their first 500 (a room's views depend on its
index alone, so they are the views a 500-room render makes). Each phase resumes from its
checkpoints when the command is run again, and a finished phase costs only reloading its views
and encoding the latents. Every phase prints its time, and the last line the total.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from freereg_lib.training import train_diffusion
from freereg_lib.training.views import load_or_render, save_views

VIEWS_PER_SCENE = 4
# (rooms, train_diffusion arguments) of each phase, as the committed weights were made.
PHASES = (
    (500, ["--steps-vae", "700", "--steps-unet", "2000", "--steps-controlnet", "0"]),
    (2000, ["--stages", "unet", "--steps-unet", "4000"]),
    (2000, ["--stages", "unet", "controlnet", "--restart-controlnet", "--steps-unet", "6000",
            "--steps-controlnet", "2600", "--lr-schedule", "cosine"]),
)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="runs/micro/retrain", help="views, checkpoints and phase 1's weights")
    p.add_argument("--export", default=None, help="the retrained weights (default OUT/weights)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    return p.parse_args(argv)


def first_rooms(views: dict, n_scenes: int, views_per_scene: int = VIEWS_PER_SCENE) -> dict:
    """The views of the first ``n_scenes`` rooms of a render (views are stored in room order)."""
    n = n_scenes * views_per_scene
    if n > len(views["rgb"]):
        raise ValueError(f"{n_scenes} rooms asked for, the render holds {len(views['rgb']) // views_per_scene}")
    return {k: v[:n] for k, v in views.items()}


def phase_argv(out: Path, export: Path, threads: int | None) -> list[list[str]]:
    """The ``train_diffusion`` command line of each phase; phase ``i + 1`` continues phase ``i``'s export."""
    argvs, previous = [], None
    for i, (rooms, extra) in enumerate(PHASES):
        exported = export if i == len(PHASES) - 1 else out / f"phase{i + 1}_weights"
        argv = ["--out", str(out / f"phase{i + 1}"), "--views", str(out / f"views_indoor_{rooms}.npz"),
                "--scenes", str(rooms), "--views-per-scene", str(VIEWS_PER_SCENE), "--export", str(exported), *extra]
        if previous is not None:
            argv += ["--init-from", str(previous)]
        if threads:
            argv += ["--threads", str(threads)]
        previous = exported
        argvs.append(argv)
    return argvs


def prepare_views(out: Path) -> None:
    """Render the largest phase's rooms once and cut every smaller phase's file from them."""
    rooms = sorted({r for r, _ in PHASES})
    largest = load_or_render(out / f"views_indoor_{rooms[-1]}.npz", rooms[-1], VIEWS_PER_SCENE)
    for r in rooms[:-1]:
        path = out / f"views_indoor_{r}.npz"
        if not path.exists():
            save_views(first_rooms(largest, r), path, r, VIEWS_PER_SCENE)


def main(argv=None) -> int:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    export = Path(args.export) if args.export else out / "weights"
    t0 = time.perf_counter()
    prepare_views(out)
    times = [("rendering", time.perf_counter() - t0)]
    print(f"views ready in {times[0][1] / 60:.1f} min", flush=True)
    for i, phase in enumerate(phase_argv(out, export, args.threads), 1):
        t = time.perf_counter()
        train_diffusion.main(phase)
        times.append((f"phase {i}", time.perf_counter() - t))
        print(f"phase {i} of {len(PHASES)} done in {times[-1][1] / 60:.1f} min", flush=True)
    total = time.perf_counter() - t0
    print("retraining: " + ", ".join(f"{name} {s / 60:.1f} min" for name, s in times)
          + f"; total {total / 60:.1f} min; weights in {export}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
