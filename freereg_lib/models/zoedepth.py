"""Monocular metric depth with the ``transformers`` port of ZoeDepth.

``ZoeDepthForDepthEstimation`` + ``ZoeDepthImageProcessor``: the processor pads the image
(reflection, ``int(sqrt(h / 2) * 3)`` pixels each side as the original ZoeDepth), resizes
and normalises it; the model runs on the image and on its horizontal flip, the two
predictions are averaged (the official inference's flip augmentation), the padding is
removed and the depth is resized (bicubic) to the input image's size.

The post-processing mirrors ``ZoeDepthImageProcessor.post_process_depth_estimation``; it is
re-implemented here with ``torch.nn.functional.interpolate`` because that method needs
torchvision, which this environment does not ship (transformers then falls back to the PIL
processor, whose post-processing is broken without torchvision).

ZoeDepth always runs in float32 (its metric bins are sensitive; the model is small).
"""
from __future__ import annotations

import math

import numpy as np

# A tiny ZoeDepth: BEiT backbone of 4 layers x 32 channels, one bin head; random weights.
TINY_BACKBONE = dict(
    image_size=64,
    patch_size=16,
    hidden_size=32,
    num_hidden_layers=4,
    num_attention_heads=2,
    intermediate_size=64,
    use_relative_position_bias=True,
    reshape_hidden_states=False,
    out_features=["stage1", "stage2", "stage3", "stage4"],
)
TINY_ZOE = dict(
    neck_hidden_sizes=[8, 16, 32, 64],
    fusion_hidden_size=16,
    bottleneck_features=16,
    bin_embedding_dim=16,
    num_relative_features=8,
    num_attractors=[4, 2, 2, 1],
    bin_configurations=[{"n_bins": 16, "min_depth": 0.001, "max_depth": 10.0}],
)
TINY_INPUT_HW = (64, 96)


def _processor_class():
    """The PIL image processor when torchvision is missing (no fallback warning)."""
    try:
        import torchvision  # noqa: F401
        from transformers import ZoeDepthImageProcessor

        return ZoeDepthImageProcessor
    except ImportError:
        try:
            from transformers import ZoeDepthImageProcessorPil

            return ZoeDepthImageProcessorPil
        except ImportError:  # pragma: no cover - older transformers
            from transformers import ZoeDepthImageProcessor

            return ZoeDepthImageProcessor


class ZoeDepthEstimator:
    """Metric depth ``(H, W) float64`` of an RGB image at its own resolution.

    Args:
        model: a ``ZoeDepthForDepthEstimation`` on ``device`` (float32, eval).
        processor: its image processor.
        device: torch device.
        flip: average with the prediction on the horizontally flipped image.
    """

    def __init__(self, model, processor, device, flip: bool = True):
        self.model = model
        self.processor = processor
        self.device = device
        self.flip = flip

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return self.batch([image])[0]

    def batch(self, images) -> list[np.ndarray]:
        """Metric depth of several images. Images of one size share one model call, their
        flips included (a batch of 2B), which gives the single-image result up to rounding."""
        import torch
        import torch.nn.functional as F

        imgs = [np.asarray(im) for im in images]
        for img in imgs:
            if img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(f"image must be (H, W, 3) RGB, got shape {img.shape}")
        groups: dict[tuple, list[int]] = {}
        for i, img in enumerate(imgs):
            groups.setdefault(img.shape, []).append(i)
        out: list = [None] * len(imgs)
        for (H, W, _), idx in groups.items():
            pv = self.processor(images=[imgs[i] for i in idx], return_tensors="pt")["pixel_values"]
            pv = pv.to(self.device, torch.float32)
            B = len(idx)
            # no_grad, not inference_mode: transformers' BEiT caches its relative position index
            # per window size process-wide, and an inference tensor in that cache breaks any later
            # training of a BEiT in the same process ("Inference tensors cannot be saved for backward").
            with torch.no_grad():
                x = torch.cat([pv, torch.flip(pv, dims=[3])]) if self.flip else pv
                pred = self.model(pixel_values=x).predicted_depth
                if self.flip:
                    pred = (pred[:B] + torch.flip(pred[B:], dims=[-1])) / 2
                d = pred[:, None].float()  # (B, 1, h, w)
                pad_h = pad_w = 0
                if getattr(self.processor, "do_pad", True):
                    pad_h = int(math.sqrt(H / 2) * 3)
                    pad_w = int(math.sqrt(W / 2) * 3)
                d = F.interpolate(d, size=(H + 2 * pad_h, W + 2 * pad_w), mode="bicubic",
                                  align_corners=False)
                d = d[:, 0, pad_h:pad_h + H, pad_w:pad_w + W]
            host = d.cpu().numpy().astype(np.float64)
            for k, i in enumerate(idx):
                out[i] = np.clip(host[k], 0.0, None)
        return out


def build_tiny_zoedepth(device, seed: int = 0, input_hw=TINY_INPUT_HW) -> ZoeDepthEstimator:
    """ZoeDepth with a 4-layer, 32-channel BEiT backbone and random (seeded) weights."""
    import torch
    from transformers import BeitConfig, ZoeDepthConfig, ZoeDepthForDepthEstimation

    torch.manual_seed(seed)
    cfg = ZoeDepthConfig(backbone_config=BeitConfig(**TINY_BACKBONE), **TINY_ZOE)
    model = ZoeDepthForDepthEstimation(cfg)
    # With transformers' default init (std 0.02) the signal vanishes in the small neck and
    # every image gets the same depth (softplus(0) = ln 2 everywhere); Kaiming weights in
    # the neck and heads keep the output dependent on the image.
    with torch.no_grad():
        for name, mod in model.named_modules():
            if not name.startswith("backbone") and isinstance(mod, (torch.nn.Conv2d, torch.nn.ConvTranspose2d,
                                                                    torch.nn.Linear)):
                torch.nn.init.kaiming_normal_(mod.weight, nonlinearity="relu")
    model = model.to(device).eval()
    proc = _processor_class()(
        size={"height": int(input_hw[0]), "width": int(input_hw[1])},
        keep_aspect_ratio=True,
        ensure_multiple_of=TINY_BACKBONE["patch_size"],
    )
    return ZoeDepthEstimator(model, proc, device)


def load_real_zoedepth(path: str, device) -> ZoeDepthEstimator:
    """``Intel/zoedepth-nyu`` (indoor) or ``Intel/zoedepth-nyu-kitti`` (outdoor) from a folder."""
    import torch
    from transformers import ZoeDepthForDepthEstimation

    model = ZoeDepthForDepthEstimation.from_pretrained(
        path, local_files_only=True, torch_dtype=torch.float32
    ).to(device).eval()
    proc = _processor_class().from_pretrained(path, local_files_only=True)
    return ZoeDepthEstimator(model, proc, device)
