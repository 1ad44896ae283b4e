"""The micro models' architectures and the loading of their committed weights.

The classes are the ones the ``real`` backend loads (diffusers ``AutoencoderKL``,
``UNet2DConditionModel``, ``ControlNetModel``, transformers ``CLIPTextModel``); only the sizes
are small. The UNet keeps SD v1.5's block layout (four levels, two layers per block, no
attention at the lowest level, three resnets per up block), so the nine decoder layers come out
at three resolutions as in SD v1.5 and :class:`~freereg_lib.models.diffusion.DecoderTap`,
the layer choice (0, 4, 6), PCA and the keypoint grid work unchanged. Departures for a 2-core
CPU: the VAE halves twice, not three times (a 32 x 48 latent for a 128 x 192 input, so the
decoder layers are 4 x 6, 8 x 12 and 16 x 24), and cross-attention sits only in the mid block
and at 8 x 12 (SD has it at every level but the lowest), so layers 7 and 8 are resnet outputs.

The text encoder is a small CLIP text model with random, frozen weights and a character-level
tokenizer (:func:`~freereg_lib.models.diffusion.tiny_tokenizer`): the micro world has two
texts, the prompt and the negative prompt, and the UNet learns from their embeddings as SD's
UNet learns from a frozen CLIP.

Weights live in ``weights/`` as diffusers / transformers folders (``config.json`` +
``*.safetensors`` in float16 to keep the package small; loaded as float32), each with a
``SHA256SUMS`` manifest that :func:`load` verifies and :func:`save` rewrites
(:mod:`freereg_lib.models.weightcheck`).
"""
from __future__ import annotations

import copy
from pathlib import Path

from freereg_lib.models.base import MissingWeightsError
from freereg_lib.models.diffusion import tiny_tokenizer
from freereg_lib.models.weightcheck import WeightsError, check_folder, load_pretrained, write_manifest

WEIGHTS_DIR = Path(__file__).parent / "weights"
MICRO_RESIZE_HW = (128, 192)

VAE_CONFIG = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=("DownEncoderBlock2D",) * 3,  # two downsamplers: latent = input / 4
    up_block_types=("UpDecoderBlock2D",) * 3,
    block_out_channels=(16, 32, 64),
    layers_per_block=1,
    latent_channels=4,
    norm_num_groups=16,
    sample_size=128,
)
UNET_CONFIG = dict(
    sample_size=32,
    in_channels=4,
    out_channels=4,
    block_out_channels=(32, 64, 128, 128),
    layers_per_block=2,
    # Cross-attention at 8 x 12 and in the mid block (4 x 6) only: at 16 x 24 it cost 60 % more
    # per training step, at 32 x 48 11-35x.
    down_block_types=("DownBlock2D", "DownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D", "UpBlock2D"),
    cross_attention_dim=64,
    attention_head_dim=4,
    norm_num_groups=16,
)
# The hint is halved twice to meet the 32 x 48 latent (SD's ControlNet halves three times).
CONTROLNET_EMBEDDING = (16, 32, 64)
TEXT_CONFIG = dict(
    hidden_size=64,
    intermediate_size=128,
    num_hidden_layers=2,
    num_attention_heads=4,
    max_position_embeddings=77,
    projection_dim=64,
)
PARTS = ("vae", "unet", "controlnet", "text_encoder", "tokenizer")


def build(seed: int = 0):
    """Fresh micro models with seeded random weights: ``dict`` of ``vae``, ``unet``,
    ``controlnet`` (initialised from the UNet's encoder, zero convolutions at zero, as
    ``ControlNetModel.from_unet``), ``text_encoder`` and ``tokenizer``."""
    import torch
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel


    tok = tiny_tokenizer()
    torch.manual_seed(seed)
    vae = AutoencoderKL(**VAE_CONFIG)
    unet = UNet2DConditionModel(**UNET_CONFIG)
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=CONTROLNET_EMBEDDING)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=len(tok), bos_token_id=0, eos_token_id=1,
                                        pad_token_id=1, **TEXT_CONFIG))
    return dict(vae=vae, unet=unet, controlnet=controlnet, text_encoder=text, tokenizer=tok)


def save(models: dict, folder: str | Path, parts=PARTS) -> None:
    """Write ``parts`` of ``models`` as diffusers / transformers folders under ``folder``
    (weights in float16)."""

    import torch


    folder = Path(folder)
    for name in parts:
        m = models[name]
        if name == "tokenizer":
            m.save_pretrained(folder / name)
        else:
            # nn.Module.to: diffusers' own .to warns about float32-only modules these models lack.
            half = torch.nn.Module.to(copy.deepcopy(m), torch.float16)
            half.save_pretrained(folder / name, safe_serialization=True)
        write_manifest(folder / name)


def missing_parts(folder: str | Path = WEIGHTS_DIR) -> list[str]:
    folder = Path(folder)
    return [p for p in PARTS if not (folder / p).is_dir()]


def load(folder: str | Path = WEIGHTS_DIR, device="cpu", parts=PARTS) -> dict:
    """The micro models saved in ``folder`` (float32, eval mode, on ``device``).

    Each part's files are checked first: whole safetensors files, the ``SHA256SUMS`` manifest
    where there is one, a ``config.json`` that fits the weights; a problem raises
    :class:`~freereg_lib.models.weightcheck.WeightsError` naming the file."""
    import torch
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer


    folder = Path(folder)
    missing = [p for p in parts if not (folder / p).is_dir()]
    if missing:
        raise MissingWeightsError(
            f"micro model weights missing in {folder}: {', '.join(missing)} "
            "(retrain with `python -m freereg_lib.training.train_diffusion`)")
    classes = dict(vae=AutoencoderKL, unet=UNet2DConditionModel, controlnet=ControlNetModel,
                   text_encoder=CLIPTextModel, tokenizer=CLIPTokenizer)
    out = {}
    for name in parts:
        if name == "tokenizer":
            check_folder(folder / name)
            try:
                out[name] = CLIPTokenizer.from_pretrained(folder / name)
            except Exception as exc:  # noqa: BLE001 - named, in one line
                raise WeightsError(f"the micro tokenizer in {folder / name} does not load: {type(exc).__name__}: "
                                   f"{(str(exc).splitlines() or [''])[0][:300]}") from None
            continue
        m = load_pretrained(classes[name], folder / name, f"the micro {name}", torch_dtype=torch.float32)
        out[name] = m.to(device).eval()
    return out
