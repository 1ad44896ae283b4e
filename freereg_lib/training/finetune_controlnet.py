"""The paper's fine-tuning (Table 11, fine-tuning: FreeReg-Ft) at micro scale: the committed micro
ControlNet trained on for a bounded number of steps on sensor-like depth hints.

    python -m freereg_lib.training.finetune_controlnet --scenes 120 --steps 300 \
        --out runs/micro/finetune --export runs/micro/finetune/weights --threads 1

The paper fine-tunes the depth ControlNet on the depth maps of real sensors, whose holes and
noise differ from the clean (estimated) depth it was trained on. Here the hint of every training
view is made as the pipeline makes it at inference (:mod:`.views`: the cloud projected on the
camera, densified, normalised) but from a *sensor-like* depth frame (:func:`sensor_depth`):

* axial noise of a structured-light sensor, ``sigma(z) = noise_scale * (0.0012 + 0.0019 (z - 0.4)^2)``
  metres (the Kinect model of Nguyen et al. 2012);
* holes at depth discontinuities (the projector's shadow): pixels next to a jump of more than
  ``EDGE_JUMP_M``, dilated by ``edge_px``;
* ``blobs`` random elliptical holes (dark or specular surfaces), and a far cut at ``far_m``.

The rooms are the training stream's (:func:`.views.room_rng`: rooms ``0 .. scenes-1``, never an
evaluation pair's), the cameras those :mod:`.views` draws; the artefacts draw from their own stream
(:data:`ARTEFACT_STREAM`, room ``k``), so the same arguments give the same views. The training
itself is :mod:`.train_diffusion`'s ControlNet stage with ``--init-from`` (seeded, resumable,
checkpointed, ``--export`` with ``training.json``): only the ControlNet changes.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freereg_lib.training import train_diffusion
from freereg_lib.training.views import _scene_views, progress_map, save_views

ARTEFACT_STREAM = 0xF3EE00F7  # the artefacts' draws, apart from the rooms' own stream
EDGE_JUMP_M = 0.10  # a neighbour this much nearer or farther: a shadowed edge pixel
DEFAULT_INIT = "freereg_lib/models/micro/weights"


def sensor_depth(depth: np.ndarray, rng: np.random.Generator, noise_scale: float = 2.0, edge_px: int = 2,
                 blobs: int = 3, far_m: float = 6.0) -> np.ndarray:
    """``depth (H, W)`` (metres, 0 = no return) as a structured-light sensor would return it:
    axial noise, holes at discontinuities and in random blobs, nothing beyond ``far_m``."""
    import cv2

    z = np.asarray(depth, dtype=np.float64).copy()
    valid = z > 0
    sigma = noise_scale * (0.0012 + 0.0019 * (z - 0.4) ** 2)
    z = np.where(valid, z + sigma * rng.standard_normal(z.shape), 0.0)
    holes = np.zeros(z.shape, dtype=np.uint8)
    if edge_px > 0:  # the jump is measured on the clean depth: the shadow follows the geometry
        d = np.asarray(depth, dtype=np.float32)
        jump = np.maximum(np.abs(np.diff(d, axis=0, prepend=d[:1])), np.abs(np.diff(d, axis=1, prepend=d[:, :1])))
        holes[jump > EDGE_JUMP_M] = 1
        holes = cv2.dilate(holes, np.ones((2 * edge_px + 1, 2 * edge_px + 1), np.uint8))
    H, W = z.shape
    for _ in range(int(rng.integers(0, blobs + 1))):
        c = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        axes = (int(rng.integers(8, 60)), int(rng.integers(8, 60)))
        cv2.ellipse(holes, c, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    z[(holes > 0) | (z > far_m) | (z <= 0)] = 0.0
    return z


@dataclass(frozen=True)
class SensorArtefacts:
    """The ``sense`` of :func:`.views._scene_views`: :func:`sensor_depth` with these settings, its draws
    from room ``k``'s artefact stream."""

    noise_scale: float = 2.0
    edge_px: int = 2
    blobs: int = 3
    far_m: float = 6.0

    def rng(self, k: int) -> np.random.Generator:
        return np.random.default_rng((ARTEFACT_STREAM, int(k)))

    def __call__(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return sensor_depth(depth, rng, self.noise_scale, self.edge_px, self.blobs, self.far_m)


def sensor_views(n_scenes: int, views_per_scene: int = 4, artefacts: dict | None = None, workers: int | None = 1,
                 progress: bool = True) -> dict[str, np.ndarray]:
    """Views of training rooms ``0 .. n_scenes-1`` with sensor-like hints, in the layout of
    :func:`.views.render_views` (the same arrays whatever ``workers`` is)."""
    sense = SensorArtefacts(**(artefacts or {}))
    jobs = [(k, views_per_scene, "indoor", sense) for k in range(n_scenes)]
    parts = progress_map(_scene_views, jobs, workers, "rendering sensor-like views", "room", progress)
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--init-from", default=DEFAULT_INIT, help="the exported weights to fine-tune")
    p.add_argument("--out", default="runs/micro/finetune", help="views, checkpoints and log")
    p.add_argument("--export", default=None, help="write the fine-tuned weights here")
    p.add_argument("--scenes", type=int, default=120, help="training rooms 0..scenes-1")
    p.add_argument("--views-per-scene", type=int, default=4)
    p.add_argument("--steps", type=int, default=300, help="fine-tuning steps after the folder's own")
    p.add_argument("--lr", type=float, default=1e-4, help="peak learning rate (a fifth of the training's)")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--checkpoint-every", type=int, default=50)
    p.add_argument("--noise-scale", type=float, default=2.0, help="times the Kinect axial noise model")
    p.add_argument("--edge-px", type=int, default=2, help="hole half-width at depth discontinuities")
    p.add_argument("--blobs", type=int, default=3, help="at most this many random elliptical holes a view")
    p.add_argument("--far-m", type=float, default=6.0, help="no return beyond this depth")
    p.add_argument("--seed", type=int, default=1, help="the steps' draws (0 drew the committed training)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--workers", type=int, default=1, help="rendering processes")
    args = p.parse_args(argv)
    if args.steps < 1 or args.scenes < 2 or args.views_per_scene < 1 or args.batch < 1:
        p.error("--steps, --batch and --views-per-scene must be >= 1 and --scenes >= 2")
    if not args.lr > 0 or args.noise_scale < 0 or args.edge_px < 0 or args.blobs < 0 or not args.far_m > 0:
        p.error("--lr and --far-m must be > 0; --noise-scale, --edge-px and --blobs >= 0")
    if not Path(args.init_from, "training.json").exists():
        p.error(f"--init-from {args.init_from}: no training.json there (an exported weights folder)")
    from freereg_lib.training.command_inputs import weights_fault

    if fault := weights_fault(args.init_from):  # before any view is rendered: one line, exit 2
        p.error(f"--init-from {args.init_from}: {fault}")
    return args


def train_argv(args: argparse.Namespace, views_path: Path, done_steps: int) -> list[str]:
    """The :mod:`.train_diffusion` arguments of the fine-tuning: the ControlNet stage only, from
    ``--init-from``, ``args.steps`` steps beyond the folder's ``done_steps``, a cosine to 0."""
    argv = ["--out", str(Path(args.out) / "train"), "--views", str(views_path), "--scenes", str(args.scenes),
            "--views-per-scene", str(args.views_per_scene), "--init-from", args.init_from, "--stages", "controlnet",
            "--steps-controlnet", str(done_steps + args.steps), "--lr-controlnet", str(args.lr),
            "--warmup", str(args.warmup), "--lr-schedule", "cosine", "--batch", str(args.batch),
            "--checkpoint-every", str(args.checkpoint_every), "--seed", str(args.seed)]
    if args.threads:
        argv += ["--threads", str(args.threads)]
    if args.export:
        argv += ["--export", args.export]
    return argv


def main(argv=None) -> int:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    artefacts = {"noise_scale": args.noise_scale, "edge_px": args.edge_px, "blobs": args.blobs, "far_m": args.far_m}
    views_path = out / "views_sensor.npz"
    meta_path = out / "views_sensor.json"
    if not (views_path.exists() and meta_path.exists()
            and json.loads(meta_path.read_text()) == {**artefacts, "scenes": args.scenes, "vps": args.views_per_scene}):
        views = sensor_views(args.scenes, args.views_per_scene, artefacts, args.workers)
        save_views(views, views_path, args.scenes, args.views_per_scene)
        meta_path.write_text(json.dumps({**artefacts, "scenes": args.scenes, "vps": args.views_per_scene}) + "\n")
    done = len(json.loads(Path(args.init_from, "training.json").read_text())["stages"]["controlnet"]["loss"])
    print(f"fine-tuning the ControlNet from step {done} to {done + args.steps} on sensor-like hints "
          f"({artefacts}) of {args.scenes} training rooms", flush=True)
    code = train_diffusion.main(train_argv(args, views_path, done))
    if args.export:
        facts_path = Path(args.export, "training.json")
        facts = json.loads(facts_path.read_text())
        facts["finetune"] = {"hints": "sensor-like (finetune_controlnet.sensor_depth)", **artefacts,
                             "scenes": args.scenes, "views_per_scene": args.views_per_scene, "steps": args.steps,
                             "from_step": done, "lr": args.lr, "warmup": args.warmup, "seed": args.seed}
        facts_path.write_text(json.dumps(facts) + "\n")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
