"""The micro monocular depth: transformers' ``ZoeDepthForDepthEstimation`` in miniature.

The class, the image processor and the inference path are the ones the ``real`` backend uses
(:class:`~freereg_lib.models.zoedepth.ZoeDepthEstimator`: reflection padding of
``int(sqrt(h / 2) * 3)`` pixels, resize keeping the aspect ratio to a multiple of the patch
size, flip averaging, bicubic resize back, padding cropped); only the sizes are small:

* backbone, one of ``BACKBONES``:

  - ``beit`` (the committed weights'): BEiT with relative position bias (as ZoeDepth's BEiT-L),
    4 layers x 128 channels, patch 16, its four stages read after layers 1..4; at 96 x 128 that is
    a 6 x 8 grid of tokens, so every detail finer than 16 pixels has to be decoded from a token;
  - ``swinv2``: a hierarchical Swin V2 (as ZoeDepth's Swin2 variants), patch 4, 32 channels,
    depths 2, 2, 2, 2, windows of 8, its stages at strides 4, 8, 16 and 32 handed to the neck
    without reassembling (transformers' ZoeDepth neck does this for ``swinv2``);
* neck: DPT (reassemble for BEiT) + fusion at 32 channels;
* head: one metric bin configuration for indoor ranges, 32 bins over 0.1..10 m (ZoeDepth's
  NYU head: 64 bins over 1e-3..10 m), attractors 8, 4, 2, 1;
* input: a 480 x 640 image padded to 572 x 746 is processed at 96 x 128 (ZoeDepth's NYU
  processor: 384 x 512), so the model predicts 96 x 128 depth that the estimator resizes back.

Weights live in ``weights/depth/`` as a ``from_pretrained`` folder (``config.json``,
``model.safetensors`` in float16 to keep the package small, ``preprocessor_config.json``);
:func:`load` reads them as float32 (ZoeDepth always runs in float32).
"""
from __future__ import annotations

import copy
from pathlib import Path

from freereg_lib.models.base import MissingWeightsError
from freereg_lib.models.weightcheck import WeightsError, load_pretrained, write_manifest
from freereg_lib.models.zoedepth import ZoeDepthEstimator, _processor_class

WEIGHTS_DIR = Path(__file__).parent / "weights" / "depth"
INPUT_HW = (96, 128)
MIN_DEPTH, MAX_DEPTH = 0.1, 10.0

BACKBONE = dict(
    image_size=96,
    patch_size=16,
    hidden_size=128,
    num_hidden_layers=4,
    num_attention_heads=4,
    intermediate_size=256,
    use_relative_position_bias=True,
    use_absolute_position_embeddings=False,
    reshape_hidden_states=False,
    out_features=["stage1", "stage2", "stage3", "stage4"],
)
SWINV2 = dict(
    image_size=96,
    patch_size=4,
    embed_dim=32,
    depths=[2, 2, 2, 2],
    num_heads=[1, 2, 4, 8],
    window_size=8,
    out_features=["stage1", "stage2", "stage3", "stage4"],
)
BACKBONES = ("beit", "swinv2")
NECK_SIZES = {"beit": [32, 64, 128, 128], "swinv2": [32, 64, 128, 256]}  # swinv2: its stages' channels
ZOE = dict(
    fusion_hidden_size=32,
    bottleneck_features=32,
    bin_embedding_dim=32,
    num_relative_features=16,
    num_attractors=[8, 4, 2, 1],
    bin_configurations=[{"n_bins": 32, "min_depth": MIN_DEPTH, "max_depth": MAX_DEPTH}],
    num_patch_transformer_layers=2,
    patch_transformer_hidden_size=32,
    patch_transformer_intermediate_size=64,
    patch_transformer_num_attention_heads=2,
)
PROCESSOR = dict(
    size={"height": INPUT_HW[0], "width": INPUT_HW[1]},
    keep_aspect_ratio=True,
    ensure_multiple_of=BACKBONE["patch_size"],
    do_pad=True,
)
FILES = ("config.json", "model.safetensors", "preprocessor_config.json")


def config(backbone: str = "beit"):
    """The micro ``ZoeDepthConfig`` with ``backbone`` (one of ``BACKBONES``)."""
    from transformers import BeitConfig, Swinv2Config, ZoeDepthConfig

    if backbone not in BACKBONES:
        raise ValueError(f"backbone {backbone!r}: expected one of {', '.join(BACKBONES)}")
    backbone_config = BeitConfig(**BACKBONE) if backbone == "beit" else Swinv2Config(**SWINV2)
    return ZoeDepthConfig(backbone_config=backbone_config, neck_hidden_sizes=NECK_SIZES[backbone], **ZOE)


def processor():
    """The image processor, the same class the real path uses (PIL flavour without torchvision)."""

    return _processor_class()(**PROCESSOR)


def build(seed: int = 0, backbone: str = "beit"):
    """A fresh micro ``ZoeDepthForDepthEstimation`` (``backbone`` one of ``BACKBONES``) with
    seeded random weights (train mode).

    transformers' default init (std 0.02) leaves the small neck's signal near zero, so every
    image would start at one depth; Kaiming weights in the neck and heads (as
    :func:`~freereg_lib.models.zoedepth.build_tiny_zoedepth`) keep the output image-dependent.
    """
    import torch
    from transformers import ZoeDepthForDepthEstimation

    torch.manual_seed(seed)
    model = ZoeDepthForDepthEstimation(config(backbone))
    with torch.no_grad():
        for name, mod in model.named_modules():
            if not name.startswith("backbone") and isinstance(
                    mod, (torch.nn.Conv2d, torch.nn.ConvTranspose2d, torch.nn.Linear)):
                torch.nn.init.kaiming_normal_(mod.weight, nonlinearity="relu")
    return model


def estimator(model, device="cpu", flip: bool = True):
    """The :class:`~freereg_lib.models.zoedepth.ZoeDepthEstimator` of ``model`` (float32, eval)."""
    import torch


    model = model.to(device=device, dtype=torch.float32).eval()
    return ZoeDepthEstimator(model, processor(), torch.device(device), flip=flip)


def save(model, folder: str | Path) -> None:
    """``from_pretrained``-style folder: config.json, model.safetensors (float16), preprocessor_config.json."""

    import torch

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)

    half = copy.deepcopy(model).to(torch.float16)
    half.save_pretrained(folder, safe_serialization=True)
    processor().save_pretrained(folder)
    write_manifest(folder)


def missing_files(folder: str | Path = WEIGHTS_DIR) -> list[str]:
    folder = Path(folder)
    return [f for f in FILES if not (folder / f).is_file()]


def load(folder: str | Path = WEIGHTS_DIR, device="cpu", flip: bool = True):
    """The committed (or another exported) micro ZoeDepth as a ``ZoeDepthEstimator`` (float32).

    A truncated or damaged file (``SHA256SUMS``), or a ``config.json`` that does not fit the
    weights, raises :class:`~freereg_lib.models.weightcheck.WeightsError` naming it."""
    import torch
    from transformers import ZoeDepthForDepthEstimation


    missing = missing_files(folder)
    if missing:
        raise MissingWeightsError(
            f"micro depth weights missing in {folder}: {', '.join(missing)}; retrain them with "
            f"`python -m freereg_lib.training.train_depth --export {folder}`")
    model = load_pretrained(ZoeDepthForDepthEstimation, folder, "the micro ZoeDepth", local_files_only=True,
                            torch_dtype=torch.float32)
    try:
        proc = type(processor()).from_pretrained(str(folder), local_files_only=True)
    except Exception as exc:  # noqa: BLE001 - named, in one line
        raise WeightsError(f"{Path(folder) / 'preprocessor_config.json'} does not load: {type(exc).__name__}: "
                           f"{(str(exc).splitlines() or [''])[0][:300]}") from None

    return ZoeDepthEstimator(model.to(device).eval(), proc, torch.device(device), flip=flip)
