"""Train the micro diffusion models from scratch: VAE, then UNet, then depth ControlNet.

    python -m freereg_lib.training.train_diffusion [--out runs/micro/train] [--scenes 500]
        [--steps-vae 700] [--steps-unet 2000] [--steps-controlnet 1200] [--batch 16]
        [--export freereg_lib/models/micro/weights]
    python -m freereg_lib.training.train_diffusion --init-from freereg_lib/models/micro/weights \
        --stages controlnet --steps-controlnet 3000 --export runs/micro/weights_next

The stages follow Stable Diffusion's recipe in miniature:

* ``vae``: an ``AutoencoderKL`` trained on random half-size crops, reconstruction (L1) plus
  the KL term with SD's weight (1e-6 per summed pixel); its ``scaling_factor`` is then set to 1 / std of the
  training latents, as SD's 0.18215 was;
* ``unet``: epsilon prediction under SD v1.5's noise schedule (1000 steps, scaled-linear betas
  0.00085..0.012), timesteps uniform, the text (the world's prompt + ", best quality", the
  pipeline's conditional text) replaced by the pipeline's unconditional text 10 % of the time
  so that classifier-free guidance has something to extrapolate from;
* ``controlnet``: ``ControlNetModel.from_unet`` (the UNet's encoder, zero convolutions at
  zero), trained with the UNet frozen on (hint, image) pairs whose hint is made as the
  pipeline makes it at inference (:mod:`.views`).

Every stage is seeded (a step's batch, flips, noise and timesteps depend only on the seed and
the step number), checkpoints every ``--checkpoint-every`` steps and resumes from its last
checkpoint when run again; a finished stage is skipped. ``--init-from`` continues an exported
folder instead of starting from scratch: the stages named in ``--stages`` train on from their
weights and step counts there (float16 weights, a fresh optimizer), the others are kept as they
are; ``--restart-controlnet`` instead builds the ControlNet afresh from the UNet at hand, as the
retraining schedule does once the UNet is final; ``--restart-unet`` likewise trains a fresh UNet
on the folder's VAE, for trying a UNet recipe without retraining the autoencoder. ``--export``
writes the weights and ``training.json`` (arguments, steps, times, loss curves) for the model card.

``--device cuda`` trains on a GPU. Every random draw is still made by the step's CPU generators
and then moved, so a GPU run sees the batches, flips, noise and timesteps of the CPU run; only
the arithmetic's rounding differs. ``--mixed-precision bf16`` runs the training steps under
bfloat16 autocast, as diffusers' training scripts do. ``--snr-gamma`` weights the UNet's loss by Min-SNR-gamma
(Hang et al. 2023; diffusers' ``--snr_gamma``); the default, off, is SD's plain MSE.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib.models.micro import diffusion as M
from freereg_lib.training.views import WORLD_KINDS, load_or_render
from freereg_lib.training.provenance import machine_record

STAGES = ("vae", "unet", "controlnet")
KL_WEIGHT = 1e-6  # SD's autoencoder (kl-f8): the KL weight against a per-image summed NLL
TEXT_DROP = 0.1
VAL_SCENES = 20  # the last rooms' views are held out for the validation losses


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="runs/micro/train", help="checkpoints and logs")
    p.add_argument("--views", default=None, help="the rendered views (.npz); default OUT/../views_indoor.npz")
    p.add_argument("--scenes", type=int, default=500, help="training rooms")
    p.add_argument("--views-per-scene", type=int, default=4)
    p.add_argument("--world", default="indoor", choices=WORLD_KINDS,
                   help="the synthetic world: indoor (blocks, the committed weights') or rooms (calibrated)")
    p.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    p.add_argument("--steps-vae", type=int, default=700)
    p.add_argument("--steps-unet", type=int, default=2000)
    p.add_argument("--steps-controlnet", type=int, default=1200)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr-vae", type=float, default=1e-3)
    p.add_argument("--lr-unet", type=float, default=5e-4)
    p.add_argument("--lr-controlnet", type=float, default=5e-4)
    p.add_argument("--warmup", type=int, default=100, help="linear learning-rate warm-up steps")
    p.add_argument("--lr-schedule", default="constant", choices=("constant", "cosine"),
                   help="after the warm-up: constant (the committed rounds 1-4), or a cosine from --lr-* "
                        "to 0 over this run's steps (its last step trains at lr 0)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    p.add_argument("--export", default=None, help="write the trained weights to this folder")
    p.add_argument("--init-from", default=None,
                   help="continue from an exported weights folder (its training.json gives each stage's "
                        "steps and log): stages left out of --stages are taken from it as they are; a "
                        "stage in --stages starts from its weights there and trains on from its step "
                        "count with a fresh optimizer (a warm restart: warm-up again, then --lr-*)")
    p.add_argument("--restart-controlnet", action="store_true",
                   help="with --init-from and the controlnet stage: build the ControlNet afresh from the "
                        "UNet at hand (ControlNetModel.from_unet, step 0) instead of continuing the folder's")
    p.add_argument("--restart-unet", action="store_true",
                   help="with --init-from and the unet stage: a fresh UNet (seeded random weights, step 0) "
                        "on the folder's VAE; needs --restart-controlnet when the controlnet stage is trained")
    p.add_argument("--snr-gamma", type=float, default=None,
                   help="weight the UNet's loss by min(SNR(t), gamma) / SNR(t) (Min-SNR; 5 is the paper's "
                        "choice); default off: SD's unweighted MSE")
    p.add_argument("--device", default="cpu", help="torch device to train on (cpu, cuda); draws stay on the CPU")
    p.add_argument("--mixed-precision", default="no", choices=("no", "bf16"),
                   help="no: float32 throughout (rounds 1-6); bf16: the training steps' forward and backward "
                        "under bfloat16 autocast, weights and optimizer in float32 (diffusers' "
                        "--mixed_precision; 1.26-1.42x faster steps on this AVX512-BF16 EPYC); validation "
                        "stays float32")
    args = p.parse_args(argv)
    if args.restart_controlnet and not (args.init_from and "controlnet" in args.stages):
        p.error("--restart-controlnet needs --init-from and the controlnet stage in --stages")
    if args.restart_unet and not (args.init_from and "unet" in args.stages):
        p.error("--restart-unet needs --init-from and the unet stage in --stages")
    if args.restart_unet and "controlnet" in args.stages and not args.restart_controlnet:
        p.error("--restart-unet: the folder's ControlNet was built on the old UNet; add --restart-controlnet")
    if args.snr_gamma is not None and not args.snr_gamma > 0:
        p.error(f"--snr-gamma {args.snr_gamma}: expected a positive number")
    from freereg_lib.training.command_inputs import weights_fault

    if args.init_from and (fault := weights_fault(args.init_from)):  # before any view is rendered
        p.error(f"--init-from {args.init_from}: {fault}")
    return args


# ------------------------------------------------------------------------------- data

class Data:
    """The views as tensors: images in [-1, 1], hints in [0, 1]; train / validation split by room."""

    def __init__(self, views: dict, views_per_scene: int, device="cpu"):
        import torch

        n_val = min(VAL_SCENES * views_per_scene, len(views["rgb"]) // 5)
        self.rgb = torch.from_numpy(views["rgb"]).to(device).float() / 127.5 - 1.0
        self.hint = torch.from_numpy(views["hint"]).to(device).float() / 255.0
        self.n_train = len(self.rgb) - n_val
        self.val = np.arange(self.n_train, len(self.rgb))

    def batch_index(self, rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Training indices and horizontal flips for one step."""
        return rng.integers(0, self.n_train, size), rng.random(size) < 0.5


def _on(idx: np.ndarray, like):
    """``idx`` as a tensor on ``like``'s device, for indexing it."""
    import torch

    return torch.from_numpy(idx).to(like.device)


def _flip(x, flips):
    import torch

    x = x.clone()
    if flips.any():
        f = _on(flips, x)
        x[f] = torch.flip(x[f], dims=[-1])
    return x


# ------------------------------------------------------------------------- stage loop

def step_rng(seed: int, stage: str, step: int) -> tuple[np.random.Generator, "object"]:
    """The numpy and torch generators of one step: a function of (seed, stage, step) only,
    so a resumed run draws what an uninterrupted one draws."""
    import torch

    # The diffusion stages keep their index (the committed weights were drawn so); other
    # models' loops (e.g. ``train_fcgf``) are told apart by a checksum of their name.
    tag = STAGES.index(stage) if stage in STAGES else zlib.crc32(stage.encode())
    ss = np.random.SeedSequence([seed, tag, step])
    g = torch.Generator().manual_seed(int(ss.generate_state(1, dtype=np.uint64)[0] >> 1))
    return np.random.default_rng(ss), g


def lr_factor(s: int, span: int, warmup: int, schedule: str = "constant") -> float:
    """The learning rate's multiplier at step ``s`` of a run of ``span`` steps (from 0).

    A linear warm-up over ``warmup`` steps, then 1 (``"constant"``), or a half cosine reaching 0 at
    the run's last step (``"cosine"``), so the weights a continuation exports are not those of a
    high, noisy learning rate.
    """
    warm = min(1.0, (s + 1) / max(warmup, 1))
    if schedule == "constant":
        return warm
    if schedule != "cosine":
        raise ValueError(f"lr schedule {schedule!r}: expected 'constant' or 'cosine'")
    return warm * 0.5 * (1.0 + math.cos(math.pi * min(s, span - 1) / max(span - 1, 1)))


def run_stage(stage: str, trainable, loss_fn, val_fn, steps: int, lr: float, args, out: Path,
              initial_log: dict | None = None) -> dict:
    """Seeded, resumable training of ``trainable`` (an ``nn.Module``) for ``steps`` steps.

    ``loss_fn(rng, g)`` returns the training loss of one step; ``val_fn()`` the validation
    loss (or a dict of validation numbers). Returns the stage's log: losses per step, validation losses, seconds.
    ``initial_log`` (the log of earlier training of ``trainable``'s current weights) makes the
    run continue at step ``len(initial_log["loss"])`` with a fresh optimizer, when there is no
    checkpoint yet; the step's draws are those an uninterrupted run makes at that step.
    """
    import torch

    folder = out / stage
    folder.mkdir(parents=True, exist_ok=True)
    ckpt = folder / "checkpoint.pt"
    opt = torch.optim.AdamW([p for p in trainable.parameters() if p.requires_grad], lr=lr,
                            weight_decay=1e-2)
    log = {"loss": [], "val": [], "seconds": 0.0, "steps": steps}
    start = 0
    if initial_log is not None:
        log = {**initial_log, "loss": list(initial_log["loss"]), "val": list(initial_log["val"]), "steps": steps}
        start = len(log["loss"])
    span = max(steps - start, 1)
    # train_fcgf runs its stage here with its own arguments, which have no --lr-schedule.
    schedule = getattr(args, "lr_schedule", "constant")
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, span, args.warmup, schedule))
    if ckpt.exists():
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        trainable.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        log, start = state["log"], state["step"]
        log["steps"] = steps
    if start >= steps:
        return log

    def save_checkpoint(step):
        tmp = ckpt.with_suffix(".tmp")
        torch.save({"model": trainable.state_dict(), "optimizer": opt.state_dict(),
                    "scheduler": sched.state_dict(), "log": log, "step": step}, tmp)
        os.replace(tmp, ckpt)

    trainable.train()
    device = next(trainable.parameters()).device
    autocast = torch.autocast(device.type, dtype=torch.bfloat16,
                              enabled=getattr(args, "mixed_precision", "no") == "bf16")
    bar = tqdm(range(start, steps), desc=f"{stage}", initial=start, total=steps, unit="step")
    t0 = time.perf_counter()
    for step in bar:
        rng, g = step_rng(args.seed, stage, step)
        with autocast:
            loss = loss_fn(rng, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(trainable.parameters(), 1.0)
        opt.step()
        sched.step()
        log["loss"].append(float(loss.detach()))
        bar.set_postfix(loss=f"{np.mean(log['loss'][-50:]):.4f}")
        done = step + 1
        if done % args.checkpoint_every == 0 or done == steps:
            trainable.eval()
            with torch.no_grad():
                val = val_fn()
                log["val"].append([done, val if isinstance(val, dict) else float(val)])
            shown = ", ".join(f"{k} {v:.4f}" for k, v in val.items()) if isinstance(val, dict) else f"{float(val):.4f}"
            bar.write(f"{stage} step {done}: validation {shown}")
            trainable.train()
            log["seconds"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            save_checkpoint(done)
    trainable.eval()
    return log


# ----------------------------------------------------------------------------- stages

def noise_schedule():
    """SD v1.5's training schedule (the DDIM sampler at inference uses the same betas)."""
    from diffusers import DDPMScheduler

    return DDPMScheduler(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012,
                         beta_schedule="scaled_linear", prediction_type="epsilon", clip_sample=False)


def train_vae(models, data: Data, args, out: Path, initial_log: dict | None = None) -> dict:
    import torch

    vae = models["vae"]
    n_pix = float(np.prod(data.rgb.shape[1:]))

    def loss_of(x, g):
        post = vae.encode(x).latent_dist
        z = post.mean + post.std * torch.randn(post.mean.shape, generator=g).to(x.device)
        rec = vae.decode(z).sample
        return (rec - x).abs().mean() + KL_WEIGHT / n_pix * post.kl().mean()

    def loss_fn(rng, g):
        # Random half-size crops, as SD's autoencoder was trained on crops: the model is
        # convolutional, and a quarter of the pixels is a quarter of the step time.
        idx, flips = data.batch_index(rng, args.batch)
        H, W = data.rgb.shape[2:]
        y, x = int(rng.integers(0, H // 2 + 1)), int(rng.integers(0, W // 2 + 1))
        return loss_of(_flip(data.rgb[_on(idx, data.rgb)], flips)[:, :, y:y + H // 2, x:x + W // 2], g)

    def val_fn():
        g = torch.Generator().manual_seed(args.seed)
        return np.mean([float(loss_of(data.rgb[i:i + 16], g)) for i in data.val[::16]])

    log = run_stage("vae", vae, loss_fn, val_fn, args.steps_vae, args.lr_vae, args, out, initial_log)
    return log


def encode_latents(vae, rgb, batch: int = 32):
    """Posterior mean and std of every image and of its mirror image: ``(2, N, 4, h, w)`` each
    (index 0 plain, 1 flipped)."""
    import torch

    means, stds = [], []
    with torch.no_grad():
        for flip in (False, True):
            m, s = [], []
            for i in tqdm(range(0, len(rgb), batch), desc="encoding latents" + (" (mirrored)" if flip else ""),
                          leave=False):
                x = rgb[i:i + batch]
                post = vae.encode(torch.flip(x, dims=[-1]) if flip else x).latent_dist
                m.append(post.mean)
                s.append(post.std)
            means.append(torch.cat(m))
            stds.append(torch.cat(s))
    return torch.stack(means), torch.stack(stds)


def set_scaling_factor(vae, mean, std) -> float:
    """SD's rule: 1 / the standard deviation of the (sampled) training latents."""
    import torch

    g = torch.Generator().manual_seed(0)
    z = mean[0] + std[0] * torch.randn(mean[0].shape, generator=g).to(mean.device)
    factor = float(1.0 / z.std())
    vae.register_to_config(scaling_factor=factor)
    return factor


def min_snr_weight(snr, gamma: float):
    """Min-SNR-gamma loss weights for epsilon prediction: ``min(SNR, gamma) / SNR`` per sample
    (1 where the noise dominates, ``gamma / SNR`` on the nearly clean steps)."""
    import torch

    return torch.clamp(snr, max=gamma) / snr


class Denoising:
    """One epsilon-prediction loss for the UNet and ControlNet stages."""

    def __init__(self, models, data: Data, latents, args):
        import torch

        from freereg_lib.config import FreeRegConfig
        from freereg_lib.models.base import A_PROMPT

        cfg = FreeRegConfig()
        self.unet, self.controlnet = models["unet"], models["controlnet"]
        self.data, self.args = data, args
        self.mean, self.std = latents
        self.factor = models["vae"].config.scaling_factor
        self.sched = noise_schedule()
        tok, text = models["tokenizer"], models["text_encoder"]

        def embed(t):
            ids = tok([t], padding="max_length", max_length=tok.model_max_length, truncation=True,
                      return_tensors="pt").input_ids
            with torch.no_grad():
                return text(ids)[0]

        device = self.mean.device
        self.cond = embed(f"{cfg.prompt}, {A_PROMPT}").to(device)
        self.uncond = embed(cfg.negative_prompt).to(device)
        # SNR(t) = alpha_bar / (1 - alpha_bar), for Min-SNR weighting
        ab = self.sched.alphas_cumprod
        self.snr = (ab / (1.0 - ab)).to(device)

    def loss(self, idx, flips, g, with_controlnet: bool, drop, snr_gamma: float | None = None):
        """The batch's epsilon MSE; with ``snr_gamma``, each sample's weighted by
        ``min(SNR(t), gamma) / SNR(t)`` (Min-SNR for epsilon prediction)."""
        import torch

        device = self.mean.device
        f = _on(flips.astype(np.int64), self.mean)
        i = _on(idx, self.mean)
        mean, std = self.mean[f, i], self.std[f, i]
        # Drawn on the CPU generator, in the CPU run's order, then moved.
        eps_z = torch.randn(mean.shape, generator=g)
        noise = torch.randn(mean.shape, generator=g)
        t = torch.randint(0, self.sched.config.num_train_timesteps, (len(idx),), generator=g)
        z = (mean + std * eps_z.to(device)) * self.factor
        noise, t = noise.to(device), t.to(device)
        zt = self.sched.add_noise(z, noise, t)
        emb = torch.where(_on(drop, self.cond)[:, None, None], self.uncond, self.cond)
        kw = {}
        if with_controlnet:
            hint = _flip(self.data.hint[i], flips)
            down, mid = self.controlnet(zt, t, encoder_hidden_states=emb, controlnet_cond=hint,
                                        return_dict=False)
            kw = dict(down_block_additional_residuals=down, mid_block_additional_residual=mid)
        pred = self.unet(zt, t, encoder_hidden_states=emb, **kw).sample
        if snr_gamma is None:
            return torch.nn.functional.mse_loss(pred, noise)
        weight = min_snr_weight(self.snr[t], snr_gamma)
        per_sample = torch.nn.functional.mse_loss(pred, noise, reduction="none").mean(dim=(1, 2, 3))
        return (per_sample * weight).mean()

    def train_loss(self, rng, g, with_controlnet):
        idx, flips = self.data.batch_index(rng, self.args.batch)
        drop = rng.random(len(idx)) < TEXT_DROP
        gamma = None if with_controlnet else self.args.snr_gamma
        return self.loss(idx, flips, g, with_controlnet, drop, gamma)

    def val_loss(self, with_controlnet):
        import torch

        g = torch.Generator().manual_seed(self.args.seed)
        idx = self.data.val
        no = np.zeros(len(idx), dtype=bool)
        return np.mean([float(self.loss(idx[k:k + 16], no[k:k + 16], g, with_controlnet, no[k:k + 16]))
                        for k in range(0, len(idx), 16)])


def freeze(module):
    for p in module.parameters():
        p.requires_grad_(False)
    return module.eval()


def load_stage_weights(stage: str, module, out: Path) -> None:
    import torch

    state = torch.load(out / stage / "checkpoint.pt", map_location="cpu", weights_only=False)
    module.load_state_dict(state["model"])


def export(models, logs: dict, args, out_dir: Path, seconds: float) -> None:
    """Weights (float16 safetensors folders) and ``training.json`` for the model card."""
    M.save(models, out_dir)
    facts = {
        "arguments": {k: v for k, v in vars(args).items() if k not in ("out", "views", "export", "threads")},
        "train_stream": "numpy.random.default_rng((0xF3EE0001, room)) for rooms 0..scenes-1",
        "validation_rooms": VAL_SCENES,
        "scaling_factor": models["vae"].config.scaling_factor,
        "parameters_millions": {k: round(sum(p.numel() for p in models[k].parameters()) / 1e6, 3)
                                for k in ("vae", "unet", "controlnet", "text_encoder")},
        # Stage seconds add up over resumed runs; the last run's wall time includes loading
        # the views and encoding the latents.
        "step_seconds": round(sum(v["seconds"] for v in logs.values()), 1),
        "last_run_seconds": round(seconds, 1),
        "stages": {k: {"steps": v["steps"], "seconds": round(v["seconds"], 1), "loss": v["loss"], "val": v["val"]}
                   for k, v in logs.items()},
    }
    if args.init_from:
        earlier = json.loads(Path(args.init_from, "training.json").read_text())

        def went(k):
            if k == "controlnet" and args.restart_controlnet:
                return f"{k} rebuilt from this UNet (ControlNetModel.from_unet) and trained from step 0 to {logs[k]['steps']}"
            if k == "unet" and args.restart_unet:
                return f"{k} rebuilt (seeded random weights) and trained from step 0 to {logs[k]['steps']}"
            return f"{k} from step {len(earlier['stages'][k]['loss'])} to {logs[k]['steps']}"

        went_on = ", ".join(went(k) for k in args.stages)
        if args.snr_gamma is not None:
            went_on += f" (the UNet's loss Min-SNR weighted, gamma {args.snr_gamma:g})"
        if args.mixed_precision != "no":
            went_on += f" (steps under {args.mixed_precision} autocast)"
        before = earlier.get("history", "").rstrip()
        facts["history"] = " ".join(filter(None, [
            before + ("." if before and not before.endswith(".") else ""),
            f"Continued with --init-from {args.init_from} on {args.scenes} rooms: {went_on} (the folder's float16 weights, "
            f"a fresh AdamW with a {args.warmup}-step warm-up"
            + ("" if args.lr_schedule == "constant" else ", then a cosine to 0")
            + f"; the steps drew what an uninterrupted run draws); "
            f"the other stages kept."]))
    (out_dir / "training.json").write_text(json.dumps({**facts, "provenance": machine_record()}) + "\n")


def init_from(folder: Path) -> tuple[dict, dict]:
    """The models and per-stage logs of an exported folder (``--init-from``)."""
    facts = json.loads((folder / "training.json").read_text())
    models = M.load(folder)
    return models, {k: facts["stages"][k] for k in STAGES}


def main(argv=None) -> int:
    import torch

    args = parse_args(argv)
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    views = load_or_render(args.views or out.parent / f"views_{args.world}.npz", args.scenes, args.views_per_scene,
                           kind=args.world)
    device = torch.device(args.device)
    data = Data(views, args.views_per_scene, device)
    print(f"{len(data.rgb)} views ({data.n_train} training, {len(data.val)} validation) of "
          f"{args.scenes} rooms, {tuple(data.rgb.shape[2:])} pixels", flush=True)
    if args.init_from:
        models, earlier = init_from(Path(args.init_from))
        print(f"continuing from {args.init_from}: " + ", ".join(
            f"{k} at step {len(v['loss'])}" for k, v in earlier.items()), flush=True)
        if args.restart_unet:
            fresh = M.build(args.seed)
            models["unet"], earlier["unet"] = fresh["unet"], None
    else:
        models, earlier = M.build(args.seed), {}
    for name in ("vae", "unet", "controlnet"):
        models[name].to(device)
    freeze(models["text_encoder"])
    # Stages not trained now come from --init-from, else from their checkpoints.
    logs = {k: v for k, v in earlier.items() if k not in args.stages}
    last = max(STAGES.index(s) for s in args.stages)

    if "vae" in args.stages:
        logs["vae"] = train_vae(models, data, args, out, earlier.get("vae"))
    elif not earlier:
        load_stage_weights("vae", models["vae"], out)
    freeze(models["vae"])
    if last == 0:
        return _finish(models, logs, args, t_start)
    latents = encode_latents(models["vae"], data.rgb)
    if "vae" in args.stages or not earlier:
        factor = set_scaling_factor(models["vae"], *latents)
    else:  # the UNet was trained on latents scaled by the folder's factor
        factor = models["vae"].config.scaling_factor
    print(f"VAE scaling factor {factor:.4f} (SD v1.5: 0.18215)", flush=True)

    den = Denoising(models, data, latents, args)
    if "unet" in args.stages:
        logs["unet"] = run_stage("unet", models["unet"], lambda r, g: den.train_loss(r, g, False),
                                 lambda: den.val_loss(False), args.steps_unet, args.lr_unet, args, out,
                                 earlier.get("unet"))
    elif not earlier:
        load_stage_weights("unet", models["unet"], out)
    freeze(models["unet"])
    if last == 1:
        return _finish(models, logs, args, t_start)

    if "controlnet" in args.stages:
        if "controlnet" not in earlier or args.restart_controlnet:
            # Built from the trained UNet's encoder, as ControlNet is from SD's.
            from diffusers import ControlNetModel

            models["controlnet"] = ControlNetModel.from_unet(
                models["unet"], conditioning_embedding_out_channels=M.CONTROLNET_EMBEDDING).to(device)
            den.controlnet = models["controlnet"]
        logs["controlnet"] = run_stage("controlnet", models["controlnet"], lambda r, g: den.train_loss(r, g, True),
                                       lambda: den.val_loss(True), args.steps_controlnet, args.lr_controlnet,
                                       args, out, None if args.restart_controlnet else earlier.get("controlnet"))
    elif not earlier:
        load_stage_weights("controlnet", models["controlnet"], out)
    freeze(models["controlnet"])
    return _finish(models, logs, args, t_start)


def _finish(models, logs, args, t_start) -> int:
    seconds = time.perf_counter() - t_start
    if args.export:
        if set(logs) != set(STAGES):
            raise SystemExit("--export needs all three stages in one run (finished ones are read from their "
                             "checkpoints): drop --stages")
        export(models, logs, args, Path(args.export), seconds)
        print(f"weights written to {args.export}", flush=True)
    print(f"total time {seconds / 60:.1f} min", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
