"""Train the micro monocular depth (:mod:`.depth`) from scratch on the synthetic rooms.

    python -m freereg_lib.training.train_depth [--out runs/micro/train] [--scenes 500]
        [--backbone beit] [--steps 1500] [--batch 8] [--lr 5e-4] [--threads 1]
        [--export freereg_lib/models/micro/weights/depth]

Data: the cached training views (:mod:`.views`, the same ``views_indoor.npz`` the diffusion
models use; rooms from a training stream evaluation seeds are kept off). The last 20 rooms'
views are held out for validation, as in :mod:`.train_diffusion`.

Pre- and post-processing are the inference path's
(:class:`~freereg_lib.models.zoedepth.ZoeDepthEstimator`):

* each 128 x 192 view is brought back to the render size 480 x 640 (bicubic), so the
  processor's reflection padding ``int(sqrt(h / 2) * 3)`` is the same fraction of the image as
  at inference, then the processor (padding, aspect-keeping resize to 96 x 128, normalisation)
  runs once and its pixel values are cached (``OUT/depth/pixel_values.npy``);
* the predicted 96 x 128 depth is resized bicubically to the padded size (572 x 746) and the
  padding is cropped, exactly as at inference, and compared with the true depth where it was
  sampled (the views keep the true depth at 120 x 160, nearest, i.e. every 4th pixel of the
  480 x 640 render). The bicubic resize is linear, so it is applied as two matrices that
  ``torch.nn.functional.interpolate`` itself produces (the same numbers, evaluated only at the
  sampled pixels).

Loss, on valid pixels (true depth > 0): ZoeDepth's scale-invariant log loss
``10 * sqrt(Var(g) + 0.15 * mean(g)^2)``, ``g = log(pred) - log(true)`` pooled over the batch,
plus the mean absolute error in metres (``--l1-weight``, default 1), which is what the
acceptance measures; ``--grad-weight`` adds MiDaS's multi-scale gradient matching on log depth
(:func:`gradient_loss`, default 0: off). Augmentation: horizontal flips (the prediction is flipped back before
the loss, as the flip average does at inference).

Seeded (a step's batch, flips and dropout draws depend only on ``(seed, step)``), checkpoints every
``--checkpoint-every`` steps to ``OUT/depth/checkpoint.pt`` and resumes from it when run again.
AdamW, linear warm-up then cosine decay to 10 %. ``--init-from FOLDER`` continues an exported model
from its step count (a warm restart; the export's ``schedule_history`` records it). ``--export`` writes the weights
(:func:`.depth.save`) and ``training.json`` (arguments, steps, seconds, losses, validation MAE).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib.models.micro import depth as MD
from freereg_lib.training.views import DEPTH_HW, RENDER_HW, WORLD_KINDS, load_or_render
from freereg_lib.training.provenance import machine_record

VAL_SCENES = 20
GRADIENT_SCALES = (1, 2, 4)
SILOG_BETA = 0.15  # ZoeDepth's SILogLoss: Dg = Var(g) + beta * mean(g)^2 (beta = 1 - lambda, lambda = 0.85)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="runs/micro/train", help="checkpoints (OUT/depth/) and the pixel cache")
    p.add_argument("--views", default=None, help="the rendered views (.npz); default OUT/../views_indoor.npz")
    p.add_argument("--scenes", type=int, default=500, help="training rooms")
    p.add_argument("--views-per-scene", type=int, default=4)
    p.add_argument("--world", default="indoor", choices=WORLD_KINDS,
                   help="the synthetic world: indoor (blocks, the committed weights') or rooms (calibrated)")
    p.add_argument("--backbone", default="beit", choices=MD.BACKBONES,
                   help="the micro ZoeDepth's backbone (models.micro.depth): beit (the committed weights') or "
                        "swinv2 (hierarchical, stride-4 features)")
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=5e-4)
    p.add_argument("--warmup", type=int, default=100, help="linear learning-rate warm-up steps")
    p.add_argument("--l1-weight", type=float, default=1.0, help="weight of the L1 (metres) term beside SILog")
    p.add_argument("--grad-weight", type=float, default=0.0,
                   help="weight of the multi-scale gradient term on log depth (0: none)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared: 1)")
    p.add_argument("--export", default=None, help="write the trained weights to this folder")
    p.add_argument("--init-from", default=None,
                   help="continue an exported folder (its weights and training.json) from its step count to "
                        "--steps, with a fresh AdamW: warm-up again, then cosine to 10 %% over the new steps")
    args = p.parse_args(argv)
    from freereg_lib.training.command_inputs import weights_fault

    if args.init_from and (fault := weights_fault(args.init_from)):  # before any view is rendered
        p.error(f"--init-from {args.init_from}: {fault}")
    return args


# ------------------------------------------------------------------------------- data

def pad_size(hw=RENDER_HW) -> tuple[int, int]:
    """The processor's reflection padding of an image of size ``hw`` (ZoeDepth's rule)."""
    return int(math.sqrt(hw[0] / 2) * 3), int(math.sqrt(hw[1] / 2) * 3)


def pixel_values(rgb: np.ndarray, proc=None, progress: bool = True) -> np.ndarray:
    """The processor's pixel values ``(N, 3, 96, 128) float32`` of views ``rgb (N, 3, h, w) uint8``,
    each first resized (bicubic) to the render size 480 x 640 as at inference."""
    import cv2

    proc = proc or MD.processor()
    H, W = RENDER_HW
    out = []
    for k in tqdm(range(len(rgb)), desc="processing views", unit="view", disable=not progress, leave=False):
        img = cv2.resize(np.ascontiguousarray(rgb[k].transpose(1, 2, 0)), (W, H), interpolation=cv2.INTER_CUBIC)
        out.append(proc(images=[img], return_tensors="np")["pixel_values"][0].astype(np.float32))
    return np.stack(out)


def resize_matrices(pred_hw: tuple[int, int], image_hw=RENDER_HW, target_hw=DEPTH_HW):
    """Row and column matrices ``A (th, ph)``, ``B (tw, pw)`` with ``A @ d @ B.T`` equal to the
    estimator's post-processing of a ``pred_hw`` depth ``d`` (bicubic to the padded image size,
    padding cropped) read at the pixels where the views sampled the true depth
    (``cv2.INTER_NEAREST`` from ``image_hw`` to ``target_hw``: every ``image / target``-th pixel)."""
    import torch
    import torch.nn.functional as F

    ph, pw = pad_size(image_hw)

    def axis(n_in, n_img, pad, n_t):
        eye = torch.eye(n_in, dtype=torch.float64)[:, None, :, None]  # n_in deltas along one axis
        up = F.interpolate(eye, size=(n_img + 2 * pad, 1), mode="bicubic", align_corners=False)[:, 0, :, 0]
        rows = pad + np.floor(np.arange(n_t) * (n_img / n_t)).astype(np.int64)
        return up[:, rows].T.contiguous().float()  # (n_t, n_in)

    return (axis(pred_hw[0], image_hw[0], ph, target_hw[0]),
            axis(pred_hw[1], image_hw[1], pw, target_hw[1]))


class Data:
    """Cached pixel values and true depths; train / validation split by room."""

    def __init__(self, pixels: np.ndarray, depth: np.ndarray, views_per_scene: int):
        import torch

        n_val = min(VAL_SCENES * views_per_scene, len(pixels) // 5)
        self.pixels = torch.from_numpy(np.asarray(pixels, dtype=np.float32))
        self.depth = torch.from_numpy(np.asarray(depth, dtype=np.float32))
        self.n_train = len(self.pixels) - n_val
        self.val = np.arange(self.n_train, len(self.pixels))
        self.A, self.B = resize_matrices(tuple(self.pixels.shape[2:]), RENDER_HW, tuple(self.depth.shape[1:]))

    def batch_index(self, rng: np.random.Generator, size: int):
        return rng.integers(0, self.n_train, size), rng.random(size) < 0.5

    def predict(self, model, idx, flips=None):
        """The post-processed depth ``(B, 120, 160)`` of views ``idx`` (flipped ones flipped back)."""
        import torch

        x = self.pixels[idx]
        if flips is not None and flips.any():
            f = torch.from_numpy(flips)
            x = x.clone()
            x[f] = torch.flip(x[f], dims=[-1])
        pred = model(pixel_values=x).predicted_depth  # (B, h, w)
        if flips is not None and flips.any():
            pred = torch.where(torch.from_numpy(flips)[:, None, None], torch.flip(pred, dims=[-1]), pred)
        return self.A @ pred @ self.B.T


def gradient_loss(pred, gt, scales=GRADIENT_SCALES):
    """MiDaS's multi-scale gradient matching on log depth: the mean of ``|d/dx r| + |d/dy r|``,
    ``r = log(pred) - log(true)``, over neighbouring valid pixels at strides ``scales``. Scale-free,
    it weighs the local shape (the surfaces' orientations) that SILog and L1 average away."""
    import torch

    valid = gt > 0
    r = torch.where(valid, torch.log(pred.clamp_min(1e-3)) - torch.log(gt.clamp_min(1e-3)), 0.0)
    total = pred.new_zeros(())
    for s in scales:
        rs, vs = r[:, ::s, ::s], valid[:, ::s, ::s]
        vx, vy = vs[:, :, 1:] & vs[:, :, :-1], vs[:, 1:, :] & vs[:, :-1, :]
        gx, gy = (rs[:, :, 1:] - rs[:, :, :-1]).abs(), (rs[:, 1:, :] - rs[:, :-1, :]).abs()
        total = total + (gx[vx].sum() + gy[vy].sum()) / (vx.sum() + vy.sum()).clamp_min(1)
    return total / len(scales)


def depth_loss(pred, gt, l1_weight: float = 1.0, grad_weight: float = 0.0):
    """SILog (ZoeDepth's, pooled over the batch) + ``l1_weight`` x mean |pred - gt| (m), valid pixels,
    + ``grad_weight`` x :func:`gradient_loss`."""
    import torch

    valid = gt > 0
    p = pred[valid].clamp_min(1e-3)
    t = gt[valid]
    g = torch.log(p) - torch.log(t)
    silog = 10.0 * torch.sqrt(g.var(unbiased=False) + SILOG_BETA * g.mean() ** 2 + 1e-12)
    loss = silog + l1_weight * (p - t).abs().mean()
    return loss + grad_weight * gradient_loss(pred, gt) if grad_weight else loss


def val_mae(model, data: Data, batch: int = 16) -> float:
    """Mean absolute error (m) over the validation views' valid pixels, no flip."""
    import torch

    err, n = 0.0, 0
    with torch.no_grad():
        for k in range(0, len(data.val), batch):
            idx = data.val[k:k + batch]
            pred, gt = data.predict(model, idx), data.depth[idx]
            v = gt > 0
            err += float((pred[v].clamp_min(0) - gt[v]).abs().sum())
            n += int(v.sum())
    return err / max(n, 1)


# ------------------------------------------------------------------------- training

def step_rng(seed: int, step: int) -> np.random.Generator:
    """The step's numpy generator; also seeds torch's global generator, which BEiT's stochastic
    depth and the metric head's patch-transformer dropout draw from, so a resumed run draws
    what an uninterrupted one draws."""
    import torch

    ss = np.random.SeedSequence([seed, 0xD3E7, step])
    torch.manual_seed(int(ss.generate_state(1, dtype=np.uint64)[0] >> 1))
    return np.random.default_rng(ss)


def lr_factor(step: int, steps: int, warmup: int) -> float:
    if step < warmup:
        return (step + 1) / max(warmup, 1)
    frac = (step - warmup) / max(steps - warmup, 1)
    return 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0)))


def train(model, data: Data, args, out: Path, progress: bool = True, initial_log: dict | None = None) -> dict:
    """Seeded, resumable training; returns the log (losses per step, validation MAE, seconds).

    ``initial_log`` (the log of the training that made ``model``'s weights) continues it: the
    steps go on from ``len(initial_log["loss"])`` (the log's ``continued_from``), drawing what an
    uninterrupted run draws at those steps, under a new warm-up and cosine over the new steps."""
    import torch

    folder = Path(out) / "depth"
    folder.mkdir(parents=True, exist_ok=True)
    ckpt = folder / "checkpoint.pt"
    log = {"loss": [], "val_mae": [], "seconds": 0.0, "steps": args.steps}
    if initial_log is not None:
        log = {**initial_log, "loss": list(initial_log["loss"]), "val_mae": list(initial_log["val_mae"]),
               "steps": args.steps, "continued_from": len(initial_log["loss"])}
    start = len(log["loss"])
    state = torch.load(ckpt, map_location="cpu", weights_only=False) if ckpt.exists() else None
    if state is not None:
        log, start = state["log"], state["step"]
        log["steps"] = args.steps
    first = log.get("continued_from", 0)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-2)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, args.steps - first, args.warmup))
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
    if start >= args.steps:
        return log

    def save_checkpoint(step):
        tmp = ckpt.with_suffix(".tmp")
        torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(),
                    "scheduler": sched.state_dict(), "log": log, "step": step}, tmp)
        os.replace(tmp, ckpt)

    model.train()
    bar = tqdm(range(start, args.steps), desc="depth", initial=start, total=args.steps, unit="step",
               disable=not progress)
    t0 = time.perf_counter()
    for step in bar:
        rng = step_rng(args.seed, step)
        idx, flips = data.batch_index(rng, args.batch)
        loss = depth_loss(data.predict(model, idx, flips), data.depth[idx], args.l1_weight, args.grad_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        log["loss"].append(float(loss.detach()))
        bar.set_postfix(loss=f"{np.mean(log['loss'][-50:]):.4f}")
        done = step + 1
        if done % args.checkpoint_every == 0 or done == args.steps:
            model.eval()
            log["val_mae"].append([done, val_mae(model, data)])
            model.train()
            bar.write(f"step {done}: loss {np.mean(log['loss'][-args.checkpoint_every:]):.4f}, "
                      f"validation MAE {log['val_mae'][-1][1]:.3f} m")
            log["seconds"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            save_checkpoint(done)
    model.eval()
    return log


def cached_pixels(views: dict, out: Path) -> np.ndarray:
    """The processor's pixel values of every view, cached in ``OUT/depth/pixel_values.npy``
    (recomputed when the view count or the processor settings differ)."""
    folder = Path(out) / "depth"
    folder.mkdir(parents=True, exist_ok=True)
    path, meta = folder / "pixel_values.npy", folder / "pixel_values.json"
    key = {"n": int(len(views["rgb"])), "processor": MD.PROCESSOR, "render_hw": list(RENDER_HW)}
    if path.exists() and meta.exists() and json.loads(meta.read_text()) == json.loads(json.dumps(key)):
        return np.load(path)
    pix = pixel_values(views["rgb"])
    np.save(path, pix)
    meta.write_text(json.dumps(key))
    return pix


def main(argv=None) -> int:
    import torch

    args = parse_args(argv)
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    t_start = time.perf_counter()
    out = Path(args.out)
    views = load_or_render(args.views or out.parent / f"views_{args.world}.npz", args.scenes, args.views_per_scene,
                           kind=args.world)
    data = Data(cached_pixels(views, out), views["depth"], args.views_per_scene)
    print(f"{len(data.pixels)} views ({data.n_train} training, {len(data.val)} validation), pixel values "
          f"{tuple(data.pixels.shape[1:])}, true depth {tuple(data.depth.shape[1:])}", flush=True)
    earlier = None
    if args.init_from:
        import torch
        from transformers import ZoeDepthForDepthEstimation

        model = ZoeDepthForDepthEstimation.from_pretrained(args.init_from, torch_dtype=torch.float32)
        earlier = json.loads(Path(args.init_from, "training.json").read_text())
        print(f"continuing {args.init_from} from step {len(earlier['loss_per_step'])}", flush=True)
        initial = {"loss": earlier["loss_per_step"], "val_mae": earlier["val_mae"],
                   "seconds": earlier["step_seconds"]}
    else:
        model, initial = MD.build(args.seed, args.backbone), None
    log = train(model, data, args, out, initial_log=initial)
    seconds = time.perf_counter() - t_start
    if args.export:
        MD.save(model, args.export)
        facts = {
            "arguments": {k: v for k, v in vars(args).items() if k not in ("out", "views", "export", "threads")},
            "train_stream": "numpy.random.default_rng((0xF3EE0001, room)) for rooms 0..scenes-1",
            "validation_rooms": VAL_SCENES,
            "loss": f"SILog (ZoeDepth, beta {SILOG_BETA}) + {args.l1_weight} x L1 (m)"
                    + (f" + {args.grad_weight} x log-depth gradients" if args.grad_weight else ""),
            "parameters_millions": round(sum(p.numel() for p in model.parameters()) / 1e6, 3),
            "step_seconds": round(log["seconds"], 1),
            "last_run_seconds": round(seconds, 1),
            "steps": log["steps"],
            "loss_per_step": log["loss"],
            "val_mae": log["val_mae"],
        }
        if earlier is not None:
            before = earlier.get("schedule_history") or (
                f"steps 0-{log['continued_from']} on {earlier['arguments']['scenes']} rooms")
            facts["schedule_history"] = (
                f"{before}; then steps {log['continued_from']}-{log['steps']} continued with --init-from on "
                f"{args.scenes} rooms x {args.views_per_scene} views, a fresh AdamW (warm-up {args.warmup}, "
                f"cosine to 10 % over the {log['steps'] - log['continued_from']} new steps)")
        Path(args.export, "training.json").write_text(json.dumps({**facts, "provenance": machine_record()}) + "\n")
        print(f"weights written to {args.export}", flush=True)
    print(f"total time {seconds / 60:.1f} min", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
