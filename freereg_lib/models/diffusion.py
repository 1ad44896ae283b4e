"""Diffusion features with ``diffusers``: one code path for the ``tiny`` and ``real`` backends.

RGB branch (Stable Diffusion v1.5)
    resize to ``resize_hw`` (the official rule: Lanczos up / area down), scale to [-1, 1],
    VAE-encode, one posterior sample (fixed seed) x ``vae.config.scaling_factor`` (0.18215),
    forward-noise once to the feature timestep (fixed seed), one UNet pass with the
    conditional text; the nine decoder layers are collected by hooks.

Depth branch (ControlNet v1.1 depth guiding SD v1.5)
    depth -> official hint (2nd / 85th percentile, inverted, uint8, 3 channels, resized,
    /255); DDIM (``cfg.ddim_steps``, eta ``cfg.ddim_eta``, the ldm schedule: timesteps
    951, 901, ..., 1 at 20 steps) from pure Gaussian noise with classifier-free guidance
    ``eps = (w + 1) U(z, t, c) - w U(z, t, c_u)`` (:func:`guidance`), the hint conditioning
    both branches through ControlNet (all 13 residual scales 1.0). Only the
    ``n_guided_steps(t_hat, steps)`` steps the features need are run (17 at the defaults:
    2 x 17 UNet calls, each with its ControlNet call), then ONE conditional ControlNet + UNet
    pass at the feature timestep collects the nine layers. No later steps, no VAE decode.

Text: the conditional text is ``cfg.prompt + ", best quality"`` (the official ``a_prompt``)
for the guided steps, the feature passes and the RGB pass; the unconditional text is
``cfg.negative_prompt``. Both embeddings are computed once per backend and reused.

Timesteps: the feature timestep is the official one, ``int((steps - index) * 1000 / steps)``
with ``index = round((1000 - t_hat) / (1000 / steps))`` (:func:`~.base.feature_timestep`):
``t_hat`` = 150 at the defaults, 200 at 5 steps. The RGB pass uses the same timestep.

Layers 0..8: see :class:`DecoderTap`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from freereg_lib.models.base import (
    A_PROMPT,
    N_LAYERS,
    check_layers,
    depth_hint,
    feature_timestep,
    n_guided_steps,
    on_cpu_threads,
    rgb_to_unit,
    seed_from,
)
from freereg_lib.models.weights import check_sd_unet_variant

# SD v1.5 UNet (unet/config.json of the official weights), for shape checks and docs.
SD15_UNET_CONFIG = dict(
    sample_size=64,
    in_channels=4,
    out_channels=4,
    block_out_channels=(320, 640, 1280, 1280),
    layers_per_block=2,
    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                      "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D",
                    "CrossAttnUpBlock2D"),
    cross_attention_dim=768,
    attention_head_dim=8,
    norm_num_groups=32,
)

# The tiny mirror: the same block structure (4 down, 4 up, 2 layers per block, the same
# block types), so the nine layers come out at input/64, /32, /16 like SD v1.5.
TINY_UNET_CONFIG = dict(
    SD15_UNET_CONFIG,
    sample_size=16,
    block_out_channels=(32, 32, 64, 64),
    cross_attention_dim=32,
    attention_head_dim=8,
    norm_num_groups=8,
)
TINY_CONTROLNET_EXTRA = dict(conditioning_embedding_out_channels=(8, 8, 16, 16))
TINY_VAE_CONFIG = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=("DownEncoderBlock2D",) * 4,  # 3 downsamplers: latent = input / 8
    up_block_types=("UpDecoderBlock2D",) * 4,
    block_out_channels=(8, 8, 16, 16),
    layers_per_block=1,
    latent_channels=4,
    norm_num_groups=4,
    sample_size=128,
)
TINY_TEXT_CONFIG = dict(
    hidden_size=32,
    intermediate_size=64,
    num_hidden_layers=2,
    num_attention_heads=4,
    max_position_embeddings=77,
    projection_dim=32,
)

# The ldm DDIM schedule of SD v1.5 in diffusers terms (timesteps 951, 901, ..., 1 at 20 steps).
LDM_DDIM_SCHEDULER = dict(
    num_train_timesteps=1000,
    beta_start=0.00085,
    beta_end=0.012,
    beta_schedule="scaled_linear",
    clip_sample=False,
    set_alpha_to_one=False,
    steps_offset=1,
    timestep_spacing="leading",
    prediction_type="epsilon",
)


def guidance(eps_cond, eps_uncond, w: float):
    """Classifier-free guidance of the paper: ``eps = (w + 1) eps_cond - w eps_uncond``.

    (The official code's ``eps_u + s (eps_c - eps_u)`` with ``s = w + 1 = 5``.) Works on
    numpy arrays and torch tensors alike.
    """
    return (w + 1.0) * eps_cond - w * eps_uncond


class StopForward(Exception):
    """Raised by :class:`DecoderTap` once layer 8 is stored: the rest of the UNet is skipped."""


class DecoderTap:
    """Forward hooks that collect decoder layers 0..8 of a diffusers ``UNet2DConditionModel``.

    The official code (ldm ``cldm.py``, ``per_layers``) lists ``[middle block, output_blocks[0],
    output_blocks[1], ...]``. In diffusers terms, for SD v1.5 (3 resnets per up block):

    ===== ========================================================== ===============
    layer module output (diffusers)                                    512 x 704 input
    ===== ========================================================== ===============
    0     input of ``up_blocks[0]`` = ``mid_block`` output + the       1280 x 8 x 11
          ControlNet mid residual (a forward *pre*-hook, so the
          residual added by the UNet forward is included)
    1, 2  ``up_blocks[0].resnets[0]``, ``[1]`` outputs                 1280 x 8 x 11
    3     ``up_blocks[0]`` output (``resnets[2]`` + its upsampler)     1280 x 16 x 22
    4, 5  ``up_blocks[1].attentions[0]``, ``[1]`` outputs              1280 x 16 x 22
          (i.e. after ``resnets[i]`` + ``attentions[i]``)
    6     ``up_blocks[1]`` output (after its upsampler)                1280 x 32 x 44
    7, 8  ``up_blocks[2].attentions[0]``, ``[1]`` outputs              640 x 32 x 44
    ===== ========================================================== ===============

    Generically: layer 0 = the input of the first up block; then, per up block, the output
    of each sub-layer but the last (the attention when the block has attentions, else the
    resnet) followed by the block's own output; the first nine are kept.

    With ``stop=True`` a :class:`StopForward` is raised once layer 8 is stored (the caller
    catches it), which skips ``up_blocks[2]``'s last sub-layer, ``up_blocks[3]`` (the
    full-resolution, most expensive block) and the output convolution.

    Use as a context manager: ``with DecoderTap(unet) as tap: ...; tap.layers()``.
    """

    def __init__(self, unet, n_layers: int = N_LAYERS, stop: bool = True):
        self.unet = unet
        self.n_layers = n_layers
        self.stop = stop
        self.maps: dict[int, object] = {}
        self._handles: list = []

    def _store(self, idx: int, tensor) -> None:
        if idx >= self.n_layers:
            return
        if isinstance(tensor, (tuple, list)):
            tensor = tensor[0]
        self.maps[idx] = tensor.detach()
        if self.stop and len(self.maps) == self.n_layers:
            raise StopForward

    def __enter__(self) -> "DecoderTap":
        self.maps = {}
        up = self.unet.up_blocks

        def pre_hook(module, args, kwargs):
            hs = kwargs["hidden_states"] if "hidden_states" in kwargs else args[0]
            self._store(0, hs)

        self._handles.append(up[0].register_forward_pre_hook(pre_hook, with_kwargs=True))
        idx = 1
        for block in up:
            if idx >= self.n_layers:
                break
            attns = getattr(block, "attentions", None)
            subs = list(attns) if attns is not None and len(attns) > 0 else list(block.resnets)
            for sub in subs[:-1]:
                self._handles.append(sub.register_forward_hook(self._make_hook(idx)))
                idx += 1
            self._handles.append(block.register_forward_hook(self._make_hook(idx)))
            idx += 1
        return self

    def _make_hook(self, idx: int):
        def hook(module, args, output):
            self._store(idx, output)

        return hook

    def __exit__(self, *exc) -> bool:
        for h in self._handles:
            h.remove()
        self._handles = []
        return False

    def layers(self, keep=None) -> list[dict[int, np.ndarray]]:
        """``{layer: (C, h, w) float32 numpy}`` per batch item, for the ``keep`` layers (all
        collected ones when None); only these cross to the host, one copy per layer."""
        keep = range(self.n_layers) if keep is None else keep
        missing = [i for i in keep if i not in self.maps]
        if missing:
            raise RuntimeError(f"decoder layers {missing} were not produced by the UNet pass")
        host = {i: self.maps[i].float().cpu().numpy() for i in keep}
        batch = len(next(iter(host.values())))
        return [{i: host[i][b] for i in keep} for b in range(batch)]


def run_tapped(unet, *args, layers=None, **kwargs) -> list[dict[int, np.ndarray]]:
    """One UNet forward with a :class:`DecoderTap` that stops after the last of ``layers``
    (all nine when None); returns ``{layer: map}`` per batch item as numpy."""
    keep = check_layers(layers)
    with DecoderTap(unet, n_layers=keep[-1] + 1) as tap:
        try:
            unet(*args, **kwargs)
        except StopForward:
            pass
    return tap.layers(keep)


def make_ddim_scheduler():
    from diffusers import DDIMScheduler

    return DDIMScheduler(**LDM_DDIM_SCHEDULER)


class DiffusionFeatures:
    """SD v1.5 (+ depth ControlNet) decoder features for one model bundle.

    Args:
        unet, controlnet, vae, text_encoder, tokenizer: diffusers / transformers modules
            (already on ``device`` in ``dtype``, eval mode).
        cfg: the :class:`~freereg_lib.config.FreeRegConfig` (t_hat, ddim_steps, ddim_eta,
            guidance_w, prompt, negative_prompt, seed).
        device, dtype: torch device and dtype of the modules.
        resize_hw: the diffusion input size (multiples of 64).
        a_prompt: appended to ``cfg.prompt`` as ``prompt + ", " + a_prompt`` ("best quality").
    """

    def __init__(self, unet, controlnet, vae, text_encoder, tokenizer, cfg, device, dtype,
                 resize_hw, a_prompt: str = A_PROMPT):
        self.unet = unet
        self.controlnet = controlnet
        self.vae = vae
        self.text_encoder = text_encoder
        self.tokenizer = tokenizer
        self.cfg = cfg
        self.device = device
        self.dtype = dtype
        self.resize_hw = tuple(resize_hw)
        self.a_prompt = a_prompt
        self._text_cache: dict[str, object] = {}
        self.scheduler = make_ddim_scheduler()

    # ---- text -------------------------------------------------------------------------
    @property
    def cond_text(self) -> str:
        return f"{self.cfg.prompt}, {self.a_prompt}" if self.a_prompt else self.cfg.prompt

    def encode_text(self, text: str):
        """CLIP last hidden state ``(1, 77, D)`` of ``text``, cached per string."""
        import torch

        if text not in self._text_cache:
            tok = self.tokenizer(
                [text],
                padding="max_length",
                max_length=self.tokenizer.model_max_length,
                truncation=True,
                return_tensors="pt",
            )
            with torch.inference_mode():
                emb = self.text_encoder(tok.input_ids.to(self.device))[0]
            self._text_cache[text] = emb.to(self.dtype)
        return self._text_cache[text]

    def text_embeddings(self):
        """``(cond, uncond)`` embeddings, computed once and reused."""
        return self.encode_text(self.cond_text), self.encode_text(self.cfg.negative_prompt)

    # ---- helpers ----------------------------------------------------------------------
    def _randn(self, shape, generator):
        import torch

        # Drawn on the CPU so results do not depend on the device.
        return torch.randn(shape, generator=generator, dtype=torch.float32).to(
            self.device, self.dtype
        )

    def _latent_shape(self):
        f = 2 ** (len(self.vae.config.block_out_channels) - 1)
        h, w = self.resize_hw
        return (1, self.unet.config.in_channels, h // f, w // f)

    def _timestep(self, t):
        import torch

        return torch.tensor([int(t)], device=self.device, dtype=torch.long)

    def eps(self, z, t, text_emb, hint):
        """Noise prediction of ControlNet + UNet (one ControlNet call, one UNet call)."""
        down, mid = self.controlnet(
            z, t, encoder_hidden_states=text_emb, controlnet_cond=hint,
            conditioning_scale=self.cfg.controlnet_scale, return_dict=False,
        )
        return self.unet(
            z, t, encoder_hidden_states=text_emb,
            down_block_additional_residuals=down, mid_block_additional_residual=mid,
            return_dict=False,
        )[0]

    # ---- the two branches -------------------------------------------------------------
    # Every item of a batch gets the noise a single call draws (the same seeded (1, ...)
    # draws, repeated over the batch), so a batch gives each item the features it gets alone.
    def rgb(self, image: np.ndarray) -> list[np.ndarray]:
        """Nine decoder layers of an RGB image ``(H, W, 3) uint8``."""
        maps = self.rgb_batch([image])[0]
        return [maps[i] for i in range(N_LAYERS)]

    def depth(self, depth: np.ndarray) -> list[np.ndarray]:
        """Nine decoder layers of a depth map ``(H, W)`` (metres, 0 = none)."""
        maps = self.depth_batch([depth])[0]
        return [maps[i] for i in range(N_LAYERS)]

    def _noised_latents(self, images, noise_tag: str, t_hat: int | None = None):
        """VAE posterior samples of ``images`` forward-noised to the feature timestep of ``t_hat``
        (default ``cfg.t_hat``), with the seeded draws of ``noise_tag``; ``(latents, timestep)``."""
        import torch

        cfg = self.cfg
        x = torch.from_numpy(np.stack([rgb_to_unit(im, self.resize_hw) for im in images])).to(self.device, self.dtype)
        g = torch.Generator("cpu").manual_seed(seed_from(cfg.seed, noise_tag) % (1 << 63))
        post = self.vae.encode(x).latent_dist
        one = (1,) + tuple(post.mean.shape[1:])
        z = post.mean + post.std * self._randn(one, g)
        z = z * self.vae.config.scaling_factor
        noise = self._randn(one, g).expand_as(z)
        t = self._timestep(feature_timestep(cfg.t_hat if t_hat is None else t_hat, cfg.ddim_steps))
        return self.scheduler.add_noise(z, noise, t.cpu()).to(self.dtype), t

    @on_cpu_threads
    def rgb_batch(self, images, layers=None, noise_tag: str = "rgb-latent",
                  t_hat: int | None = None) -> list[dict[int, np.ndarray]]:
        """Decoder ``layers`` (all nine when None) of RGB images ``(H, W, 3) uint8``, one VAE
        and one UNet call for the whole list; ``{layer: (C, h, w) float32}`` per image.
        ``noise_tag`` names the seeded noise draws (a diagnostic gives a second image its own);
        ``t_hat`` replaces ``cfg.t_hat``."""
        import torch

        cond, _ = self.text_embeddings()
        with torch.inference_mode():
            zt, t = self._noised_latents(images, noise_tag, t_hat)
            return run_tapped(self.unet, zt, t, layers=layers, encoder_hidden_states=cond.repeat(len(images), 1, 1),
                              return_dict=False)

    @on_cpu_threads
    def depth_pass_on_images(self, images, depths, layers=None,
                             noise_tag: str = "depth-camera-image") -> list[dict[int, np.ndarray]]:
        """A diagnostic: the depth branch's feature pass (ControlNet with the hints of
        ``depths`` + UNet at the feature timestep) on the forward-noised latents of the true
        ``images`` of the depth cameras, as if the DDIM sampling had generated exactly them."""
        import torch

        hint = torch.from_numpy(np.stack([depth_hint(d, self.resize_hw) for d in depths])).to(self.device, self.dtype)
        cond, _ = self.text_embeddings()
        cond = cond.repeat(len(images), 1, 1)
        with torch.inference_mode():
            zt, t = self._noised_latents(images, noise_tag)
            down, mid = self.controlnet(zt, t, encoder_hidden_states=cond, controlnet_cond=hint,
                                        conditioning_scale=self.cfg.controlnet_scale, return_dict=False)
            return run_tapped(self.unet, zt, t, layers=layers, encoder_hidden_states=cond,
                              down_block_additional_residuals=down, mid_block_additional_residual=mid,
                              return_dict=False)

    def _sample(self, hint, cond, uncond, n_steps: int, seed: int, stops=()):
        """The first ``n_steps`` guided DDIM steps from seeded Gaussian noise, every item of the
        batch on the draws a single call makes; the latent after them, or with ``stops`` a dict
        of the latents after each of those step counts (a shorter run is a prefix of this one:
        the same start and the same step noise in the same order)."""
        import torch

        cfg = self.cfg
        g = torch.Generator("cpu").manual_seed(seed_from(seed, "depth-ddim") % (1 << 63))
        one = self._latent_shape()
        sched = make_ddim_scheduler()
        sched.set_timesteps(cfg.ddim_steps)
        z = self._randn(one, g).repeat(len(hint), 1, 1, 1)
        kept = {0: z} if 0 in stops else {}
        # Every step's noise drawn up front, in the order the steps use it, and the
        # timesteps made once: one host-to-device copy each instead of one per step.
        draws = [torch.randn(one, generator=g, dtype=torch.float32) for _ in range(n_steps)]
        step_noise = torch.cat(draws or [torch.empty((0,) + one[1:])]).to(self.device, self.dtype)  # none above t_hat 975
        timesteps = sched.timesteps[:n_steps].to(self.device)
        for i, t in enumerate(sched.timesteps[:n_steps].tolist()):
            tt = timesteps[i:i + 1]
            if cfg.batched_guidance:  # one call of batch 2B instead of two of batch B
                e_c, e_u = self.eps(torch.cat([z, z]), tt, torch.cat([cond, uncond]),
                                    torch.cat([hint, hint])).chunk(2)
            else:
                e_c = self.eps(z, tt, cond, hint)
                e_u = self.eps(z, tt, uncond, hint)
            e = guidance(e_c, e_u, cfg.guidance_w)
            z = sched.step(e, t, z, eta=cfg.ddim_eta,
                           variance_noise=step_noise[i:i + 1].expand_as(z)).prev_sample.to(self.dtype)
            if i + 1 in stops:
                kept[i + 1] = z
        return kept if stops else z

    def _hints_and_texts(self, depths):
        import torch

        hint = torch.from_numpy(np.stack([depth_hint(d, self.resize_hw) for d in depths])).to(self.device, self.dtype)
        cond, uncond = self.text_embeddings()
        return hint, cond.repeat(len(depths), 1, 1), uncond.repeat(len(depths), 1, 1)

    @on_cpu_threads
    def depth_batch(self, depths, layers=None) -> list[dict[int, np.ndarray]]:
        """Decoder ``layers`` (all nine when None) of depth maps ``(H, W)`` (metres, 0 = none),
        the DDIM steps of the whole list batched; ``{layer: (C, h, w) float32}`` per map."""
        return self.depth_batch_over_t_hats(depths, [self.cfg.t_hat], layers)[self.cfg.t_hat]

    @on_cpu_threads
    def depth_batch_over_t_hats(self, depths, t_hats, layers=None) -> dict[int, list[dict[int, np.ndarray]]]:
        """:meth:`depth_batch` at each of ``t_hats`` from ONE DDIM trajectory (Table 3's sweep):
        each t_hat's feature pass reads the latent after its own number of steps, so its maps
        are those of a model built with ``cfg.t_hat`` = that t_hat; ``{t_hat: maps}``."""
        import torch

        steps = {int(t): n_guided_steps(int(t), self.cfg.ddim_steps) for t in t_hats}
        hint, cond, uncond = self._hints_and_texts(depths)
        with torch.inference_mode():
            z = self._sample(hint, cond, uncond, max(steps.values()), self.cfg.seed, stops=set(steps.values()))
            out = {}
            for t, n in steps.items():
                tt = self._timestep(feature_timestep(t, self.cfg.ddim_steps))
                down, mid = self.controlnet(z[n], tt, encoder_hidden_states=cond, controlnet_cond=hint,
                                            conditioning_scale=self.cfg.controlnet_scale, return_dict=False)
                out[t] = run_tapped(self.unet, z[n], tt, layers=layers, encoder_hidden_states=cond,
                                    down_block_additional_residuals=down, mid_block_additional_residual=mid,
                                    return_dict=False)
            return out

    @on_cpu_threads
    def generate(self, depth: np.ndarray, seeds=(0,)) -> list[np.ndarray]:
        """Images ``(h, w, 3) uint8`` at the diffusion input size that the ControlNet-guided DDIM
        sampling (all ``cfg.ddim_steps`` steps, the feature path's guidance and eta) draws from
        the depth map ``(H, W)``, one per seed. FreeReg never decodes them (the features are read
        at t_hat); the seed of ``cfg.seed`` continues the very trajectory whose latent at t_hat
        the depth side's features come from."""
        import torch

        hint, cond, uncond = self._hints_and_texts([depth])
        out = []
        with torch.inference_mode():
            for seed in seeds:
                z = self._sample(hint, cond, uncond, self.cfg.ddim_steps, int(seed))
                x = self.vae.decode(z / self.vae.config.scaling_factor).sample[0]
                x = ((x.float().clamp(-1, 1) + 1) * 127.5).round().byte()
                out.append(x.permute(1, 2, 0).cpu().numpy())
        return out


# --------------------------------------------------------------------------------------
# Building the bundles.

def tiny_tokenizer(model_max_length: int = 77):
    """A character-level CLIP BPE tokenizer built in memory (no files): the 256 byte-level
    symbols, each also with the end-of-word mark, and no merges."""
    from tokenizers import pre_tokenizers
    from transformers import CLIPTokenizer

    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet())
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for ch in alphabet:
        vocab[ch] = len(vocab)
    for ch in alphabet:
        vocab[ch + "</w>"] = len(vocab)
    return CLIPTokenizer(vocab=vocab, merges=[], model_max_length=model_max_length)


def wake_zero_convolutions(controlnet):
    """Give a random-weight ControlNet's zero convolutions small random weights (std 0.02,
    bias 0, drawn from torch's global generator), so that its hint changes the features: with
    zeros, as a fresh ControlNet has them, it would be a no-op. Returns ``controlnet``."""
    import torch

    with torch.no_grad():
        for m in [*controlnet.controlnet_down_blocks, controlnet.controlnet_mid_block,
                  controlnet.controlnet_cond_embedding.conv_out]:
            m.weight.normal_(0.0, 0.02)
            m.bias.zero_()
    return controlnet


def build_tiny_diffusion(cfg, device, dtype, resize_hw, seed: int = 0) -> DiffusionFeatures:
    """Random-weight (seeded) tiny UNet, ControlNet, VAE and CLIP text encoder with SD v1.5's
    block structure. ControlNet's zero convolutions get small random weights so the hint
    actually changes the features (with zeros it would be a no-op)."""
    import torch
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    tok = tiny_tokenizer()
    torch.manual_seed(seed)
    unet = UNet2DConditionModel(**TINY_UNET_CONFIG)
    cn_cfg = {k: v for k, v in TINY_UNET_CONFIG.items() if k not in ("out_channels",
                                                                      "up_block_types",
                                                                      "sample_size")}
    controlnet = wake_zero_convolutions(ControlNetModel(**cn_cfg, **TINY_CONTROLNET_EXTRA))
    vae = AutoencoderKL(**TINY_VAE_CONFIG)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=len(tok), bos_token_id=0, eos_token_id=1,
                                        pad_token_id=1, **TINY_TEXT_CONFIG))
    mods = [_to(m, device, dtype) for m in (unet, controlnet, vae, text)]
    return DiffusionFeatures(*mods[:3], mods[3], tok, cfg, device, dtype, resize_hw)


def _to(module, device, dtype):
    """Move a freshly built module (plain ``nn.Module.to``: diffusers' override warns about
    modules to keep in float32, which these random-weight models do not have)."""
    import torch

    return torch.nn.Module.to(module, device=device, dtype=dtype).eval()


def load_real_diffusion(sd_path: str, controlnet_path: str, cfg, device, dtype,
                        resize_hw, unet_variant: str = "non_ema",
                        controlnet_config: str | None = None) -> DiffusionFeatures:
    """SD v1.5 (``unet``, ``vae``, ``text_encoder``, ``tokenizer`` sub-folders) and the
    depth ControlNet from local files (``local_files_only=True``), all in ``dtype``.

    ``unet_variant``: ``"non_ema"`` loads ``unet/diffusion_pytorch_model.non_ema.*``, the
    weights the official code uses; ``"ema"`` the folder's default (EMA) files.
    ``controlnet_path``: a diffusers folder, or a single original-format checkpoint file
    (``.pth`` / ``.ckpt`` / ``.safetensors``, e.g. the official ``control_v11f1p_sd15_depth_ft.pth``)
    read by ``ControlNetModel.from_single_file`` with the architecture of the diffusers folder
    ``controlnet_config`` (the v1.1 depth ControlNet's ``config.json``).
    """

    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    variant = None if check_sd_unet_variant(unet_variant) == "ema" else "non_ema"
    kw = dict(local_files_only=True)
    unet = UNet2DConditionModel.from_pretrained(sd_path, subfolder="unet", torch_dtype=dtype,
                                                variant=variant, **kw)
    vae = AutoencoderKL.from_pretrained(sd_path, subfolder="vae", torch_dtype=dtype, **kw)
    text = CLIPTextModel.from_pretrained(sd_path, subfolder="text_encoder", torch_dtype=dtype, **kw)
    tok = CLIPTokenizer.from_pretrained(sd_path, subfolder="tokenizer", **kw)
    if Path(controlnet_path).is_file():
        if controlnet_config is None:
            raise ValueError(f"{controlnet_path} is a single-file ControlNet checkpoint: give "
                             "controlnet_config, the diffusers folder whose config.json describes it")
        try:
            controlnet = ControlNetModel.from_single_file(str(controlnet_path), config=str(controlnet_config),
                                                          torch_dtype=dtype, **kw)
        except (TypeError, KeyError, RuntimeError, ValueError) as e:  # a file of another model
            raise ValueError(f"{controlnet_path} could not be read as a depth ControlNet with the architecture "
                             f"of {controlnet_config}: {type(e).__name__}: {e}") from e
        # diffusers skips ControlNet weights the file lacks, leaving them uninitialised (meta).
        missing = [n for n, t in controlnet.state_dict().items() if t.is_meta]
        if missing:
            raise ValueError(f"{controlnet_path} lacks {len(missing)} ControlNet weights of the architecture in "
                             f"{controlnet_config} (e.g. {missing[:3]}): not a depth ControlNet for SD v1.5?")
    else:
        controlnet = ControlNetModel.from_pretrained(controlnet_path, torch_dtype=dtype, **kw)
    mods = [m.to(device).eval() for m in (unet, controlnet, vae, text)]
    return DiffusionFeatures(*mods[:3], mods[3], tok, cfg, device, dtype, resize_hw)
