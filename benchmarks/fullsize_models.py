"""The gpu mode's full-size models for ``bench_pipeline.py``: SD v1.5 UNet, depth ControlNet
v1.1, VAE, CLIP ViT-L/14 text encoder and ZoeD_N, built from their published configurations
with random weights (speed does not depend on the weights, and nothing is downloaded).
"""
from __future__ import annotations

import warnings

import numpy as np

# Stable Diffusion v1.5 ``vae/config.json``.
SD15_VAE_CONFIG = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=("DownEncoderBlock2D",) * 4,
    up_block_types=("UpDecoderBlock2D",) * 4,
    block_out_channels=(128, 256, 512, 512),
    layers_per_block=2,
    act_fn="silu",
    latent_channels=4,
    norm_num_groups=32,
    sample_size=512,
    scaling_factor=0.18215,
)
# Stable Diffusion v1.5 ``text_encoder/config.json`` (CLIP ViT-L/14 text tower).
SD15_TEXT_CONFIG = dict(
    vocab_size=49408,
    hidden_size=768,
    intermediate_size=3072,
    num_hidden_layers=12,
    num_attention_heads=12,
    max_position_embeddings=77,
    hidden_act="quick_gelu",
    projection_dim=768,
)
# ``lllyasviel/control_v11f1p_sd15_depth`` ``config.json``: the SD v1.5 encoder half plus
# the hint encoder below (the rest of its fields are ``ControlNetModel``'s defaults).
CONTROLNET_V11_DEPTH_EXTRA = dict(
    conditioning_embedding_out_channels=(16, 32, 96, 256),
    controlnet_conditioning_channel_order="rgb",
)
# ZoeD_M12_N (``Intel/zoedepth-nyu``): BEiT-L/16 at 384, DPT neck, one 64-bin NYU head
# (transformers' ``convert_zoedepth_to_hf.get_zoedepth_config("ZoeD_N")``).
ZOE_N_BACKBONE = dict(
    image_size=384,
    num_hidden_layers=24,
    hidden_size=1024,
    intermediate_size=4096,
    num_attention_heads=16,
    use_relative_position_bias=True,
    reshape_hidden_states=False,
    out_features=["stage6", "stage12", "stage18", "stage24"],
)
ZOE_N = dict(
    neck_hidden_sizes=[256, 512, 1024, 1024],
    bin_centers_type="softplus",
    bin_configurations=[{"name": "nyu", "n_bins": 64, "min_depth": 1e-3, "max_depth": 10.0}],
)


class _Sanitized:
    """A backend whose diffusion maps have non-finite values replaced by 0 (random float16
    weights can overflow; the values do not matter for speed). Counts what it replaced."""

    def __init__(self, inner):
        self._inner = inner
        self.nonfinite = 0

    def __getattr__(self, attr):
        return getattr(self._inner, attr)

    def _clean(self, maps):
        out = []
        for m in maps:
            bad = ~np.isfinite(m)
            if bad.any():
                self.nonfinite += int(bad.sum())
                m = np.where(bad, np.float32(0.0), m)
            out.append(m)
        return out

    def diffusion_rgb(self, image, ids=None, xyz=None):
        return self._clean(self._inner.diffusion_rgb(image))

    def diffusion_depth(self, depth, ids=None, xyz=None):
        return self._clean(self._inner.diffusion_depth(depth))

    def diffusion_rgb_batch(self, images, hints=None, layers=None):
        return [dict(zip(m, self._clean(m.values()))) for m in self._inner.diffusion_rgb_batch(images, None, layers)]

    def diffusion_depth_batch(self, depths, hints=None, layers=None):
        return [dict(zip(m, self._clean(m.values()))) for m in self._inner.diffusion_depth_batch(depths, None, layers)]

    def mono_depth(self, image, depth_gt=None):
        return self._inner.mono_depth(image)


def build_fullsize_backend(cfg, device: str, resize_hw):
    """A ``tiny``-kind backend whose models are full-size SD v1.5 / ControlNet v1.1 depth /
    VAE / CLIP text / ZoeD_N with random weights in ``cfg.dtype`` on CUDA (the gpu mode's
    ``--dtype``, float16 by default), float32 on the CPU; ZoeDepth always float32, as the
    library runs it)."""
    import torch
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import BeitConfig, CLIPTextConfig, CLIPTextModel, ZoeDepthConfig, ZoeDepthForDepthEstimation

    from freereg_lib.models.diffusion import SD15_UNET_CONFIG, DiffusionFeatures, tiny_tokenizer
    from freereg_lib.models.torch_backends import TinyBackend, resolve_device
    from freereg_lib.models.zoedepth import ZoeDepthEstimator, _processor_class

    dev, _ = resolve_device(device)
    dev, dtype = resolve_device(device, cfg.dtype if dev.type == "cuda" else "float32")
    torch.manual_seed(cfg.seed)
    tok = tiny_tokenizer()  # ids < 514 < 49408: fine for a speed test, no vocabulary file
    cn_cfg = {k: v for k, v in SD15_UNET_CONFIG.items()
              if k not in ("out_channels", "up_block_types", "sample_size")}
    with torch.device(dev), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        unet = UNet2DConditionModel(**SD15_UNET_CONFIG)
        controlnet = ControlNetModel(**cn_cfg, **CONTROLNET_V11_DEPTH_EXTRA)
        vae = AutoencoderKL(**SD15_VAE_CONFIG)
        text = CLIPTextModel(CLIPTextConfig(bos_token_id=0, eos_token_id=1, pad_token_id=1,
                                            **SD15_TEXT_CONFIG))
        zoe = ZoeDepthForDepthEstimation(ZoeDepthConfig(backbone_config=BeitConfig(**ZOE_N_BACKBONE),
                                                        **ZOE_N))
    mods = [torch.nn.Module.to(m, device=dev, dtype=dtype).eval() for m in (unet, controlnet, vae, text)]
    diff = DiffusionFeatures(*mods[:3], mods[3], tok, cfg, dev, dtype, resize_hw)
    be = TinyBackend(cfg, device=str(dev), dtype=dtype, resize_hw=resize_hw)
    be._diffusion = diff
    be._zoe = ZoeDepthEstimator(zoe.to(dev).eval(), _processor_class()(), dev)
    be.name = "full-size random"
    n_params = {k: sum(p.numel() for p in m.parameters())
                for k, m in (("unet", unet), ("controlnet", controlnet), ("vae", vae),
                             ("text", text), ("zoedepth", zoe))}
    return _Sanitized(be), n_params

