"""The backend interface and the helpers every backend shares.

A backend turns an image or a depth map into the nine diffusion decoder layers, and an image
into a metric depth map. Four kinds exist (docs/backends.md):

* ``stub``: no weights; synthetic scenes only (it reads class ids and true depth);
* ``tiny``: the real diffusers / transformers classes with small random-weight configs;
* ``real``: Stable Diffusion v1.5 + ControlNet v1.1 depth + ZoeDepth from local weights.

This module holds the pieces that do not depend on torch: the interface, the official
resize rule, the official depth-to-ControlNet normalisation, the DDIM step arithmetic and
the one exception for missing weights.
"""
from __future__ import annotations

import functools
import re
import zlib
from contextlib import contextmanager
from typing import Sequence

import cv2
import numpy as np

N_LAYERS = 9  # decoder layers 0..8
# Spatial stride of each decoder layer w.r.t. the resized input (Table 2 of the paper).
LAYER_STRIDES = (64, 64, 64, 32, 32, 32, 16, 16, 16)
# SD v1.5 channel counts of the nine layers (Table 2).
SD15_LAYER_CHANNELS = (1280, 1280, 1280, 1280, 1280, 1280, 1280, 640, 640)
# ``a_prompt`` of the official code: appended as ``prompt + ", " + a_prompt`` to the
# conditional text of both the RGB pass and the depth branch.
A_PROMPT = "best quality"


class MissingWeightsError(FileNotFoundError):
    """Pretrained weights are not on this machine.

    The message names every missing model id, the places searched, the command that
    downloads it on a machine with internet, and ``backend="stub"`` as the offline choice.
    ``model_ids`` and ``searched`` hold the same facts as attributes.
    """

    def __init__(self, message: str, model_ids: list[str] | None = None,
                 searched: list[str] | None = None):
        super().__init__(message)
        self.model_ids = list(model_ids or [])
        self.searched = list(searched or [])

    def __str__(self) -> str:  # FileNotFoundError would prefix an errno otherwise
        return self.args[0]


class Backend:
    """Base class and protocol of every backend.

    Attributes:
        name: ``"stub"``, ``"tiny"`` or ``"real"``.
        cfg: the :class:`~freereg_lib.config.FreeRegConfig` it was built with.
        resize_hw: the ``(H, W)`` the diffusion inputs are resized to; the nine layers have
            sizes ``resize_hw / LAYER_STRIDES[i]``.
        label: a one-line description for figure titles and captions.
    """

    name: str = "base"
    label: str = "base backend"

    def __init__(self, cfg, resize_hw: tuple[int, int] | None = None):
        self.cfg = cfg
        self.resize_hw = tuple(int(v) for v in (resize_hw or cfg.resize_hw))
        check_resize_hw(self.resize_hw)

    def layer_shapes(self) -> list[tuple[int, int]]:
        """``(h, w)`` of the nine layers for this backend's ``resize_hw``."""
        return layer_sizes(self.resize_hw)

    def diffusion_rgb(self, image: np.ndarray, ids: np.ndarray | None = None,
                      xyz: np.ndarray | None = None) -> list[np.ndarray]:
        """Nine decoder layers ``(C, h, w) float32`` of an RGB image ``(H, W, 3) uint8``."""
        raise NotImplementedError

    def diffusion_depth(self, depth: np.ndarray, ids: np.ndarray | None = None,
                        xyz: np.ndarray | None = None) -> list[np.ndarray]:
        """Nine decoder layers of a (densified) depth map ``(H, W)`` in metres, 0 = none."""
        raise NotImplementedError

    def mono_depth(self, image: np.ndarray, depth_gt: np.ndarray | None = None) -> np.ndarray:
        """Metric depth ``(H, W) float64`` of an RGB image, at the image's resolution."""
        raise NotImplementedError

    def diffusion_rgb_batch(self, images: Sequence[np.ndarray], hints: Sequence[dict] | None = None,
                            layers: Sequence[int] | None = None) -> list[dict[int, np.ndarray]]:
        """The decoder layers of several images, ``{layer: (C, h, w) float32}`` per image.

        ``hints``: one keyword dict per image for :meth:`diffusion_rgb` (the stub's scene
        hints; real models ignore them). ``layers``: only these layers (all nine when None);
        a backend may then stop its network after the last one. This default calls
        :meth:`diffusion_rgb` per image; the torch backends run the whole list as one batch.
        """
        return [_pick(self.diffusion_rgb(im, **h), layers) for im, h in zip(images, _hints(hints, len(images)))]

    def diffusion_depth_batch(self, depths: Sequence[np.ndarray], hints: Sequence[dict] | None = None,
                              layers: Sequence[int] | None = None) -> list[dict[int, np.ndarray]]:
        """As :meth:`diffusion_rgb_batch` for depth maps (:meth:`diffusion_depth`)."""
        return [_pick(self.diffusion_depth(d, **h), layers) for d, h in zip(depths, _hints(hints, len(depths)))]

    def fcgf_model(self):
        """The FCGF network this backend brings (e.g. the micro backend's, trained on the
        synthetic rooms), or None: ``cfg.geometric = "fcgf"`` then loads the official
        checkpoint (:func:`freereg_lib.features.geometric.fcgf_checkpoint_path`)."""
        return None

    def mono_depth_batch(self, images: Sequence[np.ndarray],
                         depth_gts: Sequence[np.ndarray | None] | None = None) -> list[np.ndarray]:
        """:meth:`mono_depth` of several images (``depth_gts``: the stub's true depths); this
        default calls it per image, the torch backends batch the model."""
        gts = [None] * len(images) if depth_gts is None else list(depth_gts)
        return [self.mono_depth(im, depth_gt=gt) for im, gt in zip(images, gts)]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, resize_hw={self.resize_hw})"


def check_layers(layers: Sequence[int] | None) -> list[int]:
    """The sorted, distinct layer indices of ``layers`` (all nine when None); ``ValueError``
    for an index outside 0..8 or an empty choice."""
    if layers is None:
        return list(range(N_LAYERS))
    chosen = sorted({int(i) for i in layers})
    if not chosen or chosen[0] < 0 or chosen[-1] >= N_LAYERS:
        raise ValueError(f"layers must be a non-empty choice among 0..{N_LAYERS - 1}, got {tuple(layers)}")
    return chosen


def _pick(maps, layers: Sequence[int] | None) -> dict[int, np.ndarray]:
    return {i: maps[i] for i in check_layers(layers)}


def _hints(hints: Sequence[dict] | None, n: int) -> list[dict]:
    if hints is None:
        return [{}] * n
    hints = list(hints)
    if len(hints) != n:
        raise ValueError(f"got {len(hints)} hint dicts for {n} inputs")
    return hints


def check_device(device) -> None:
    """Raise ``ValueError`` unless ``device`` is None, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``
    (a ``torch.device`` of those kinds is fine too). Whether CUDA is there is checked by
    :func:`~freereg_lib.models.torch_backends.resolve_device`."""

    if device is not None and not re.fullmatch(r"cpu|cuda(:\d+)?", str(device)):
        raise ValueError(
            f"unsupported device {device!r}; use None (CUDA when present, else CPU), 'cpu', 'cuda' or "
            "'cuda:N' (the N-th GPU)"
        )


# --------------------------------------------------------------------------------------
# Sizes and the official resize rule.

def check_resize_hw(hw: tuple[int, int]) -> None:
    """Raise ``ValueError`` unless both sides are positive multiples of 64."""
    h, w = hw
    if h <= 0 or w <= 0 or h % 64 or w % 64:
        raise ValueError(
            f"resize_hw={hw} must be positive multiples of 64 (the UNet works on 1/8-size "
            "latents that are downsampled three more times); e.g. (512, 704)"
        )


def layer_sizes(resize_hw: tuple[int, int]) -> list[tuple[int, int]]:
    """``(h, w)`` of decoder layers 0..8 for an input resized to ``resize_hw``."""
    h, w = resize_hw
    return [(h // s, w // s) for s in LAYER_STRIDES]


def official_resize_hw(height: int, width: int, short_side: int = 512,
                       max_aspect: float = 2.5) -> tuple[int, int]:
    """The official resize rule: short side to ``short_side``, each side rounded to a multiple
    of 64, the long side at most ``max_aspect`` x the short side.

    ``(480, 640) -> (512, 704)``; KITTI ``(225, 1242) -> (512, 1280)`` (aspect changes).
    Only the ratio ``width / height`` matters; a portrait image is handled symmetrically.
    """
    k = short_side / min(height, width)
    h = int(np.round(height * k / 64.0)) * 64
    w = int(np.round(width * k / 64.0)) * 64
    if w > max_aspect * h:
        w = int(max_aspect * h) // 64 * 64
    if h > max_aspect * w:
        h = int(max_aspect * w) // 64 * 64
    return max(h, 64), max(w, 64)


def resize_to(image: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Resize ``image`` to ``hw`` as the official ``resize_image`` does: Lanczos when
    enlarging, area averaging when shrinking (decided on the height scale)."""

    h, w = hw
    if image.shape[:2] == (h, w):
        return image
    k = h / image.shape[0]
    interp = cv2.INTER_LANCZOS4 if k > 1 else cv2.INTER_AREA
    return cv2.resize(image, (w, h), interpolation=interp)


# --------------------------------------------------------------------------------------
# Depth -> ControlNet hint.

def depth_to_uint8(depth: np.ndarray) -> np.ndarray:
    """The official depth normalisation for the depth ControlNet, ``(H, W) uint8``.

    ``d2``, ``d85`` = 2nd and 85th percentiles of the depth over ALL pixels, holes (0)
    included, as the official code; ``x = 1 - (d - d2) / (d85 - d2)``;
    ``uint8(clip(255 x))`` (near = bright, as ControlNet's depth maps). Holes therefore come
    out at 255 ("near") whenever ``d2 >= 0``, and many holes pull ``d2`` to 0. This matters on
    3DMatch, whose raw sensor depth keeps its holes.

    Non-finite depth (NaN, inf) is treated as a hole (0) before the percentiles; the official
    code never sees it. A flat map (``d85 == d2``, e.g. all holes or one constant depth) would
    divide by zero: then ``x = 1`` where ``d <= d2`` and ``x = 0`` above (the limit of the
    formula as the span shrinks to 0+), so the result is 255 / 0, never NaN.
    """
    d = np.asarray(depth, dtype=np.float64)
    d = np.where(np.isfinite(d), d, 0.0)
    d2, d85 = np.percentile(d, [2, 85])
    span = d85 - d2
    if span > 0:
        x = 1.0 - (d - d2) / span
    else:
        x = np.where(d <= d2, 1.0, 0.0)
    return np.clip(x * 255.0, 0, 255).astype(np.uint8)


def hint_image(depth: np.ndarray, resize_hw: tuple[int, int]) -> np.ndarray:
    """The official ``load_dpt`` hint ``(h, w, 3) uint8``: :func:`depth_to_uint8` of the map as
    it is (no clipping to a depth range; the PNG's values in the official code, whose scale
    does not matter), 3 channels, resized to ``resize_hw`` by :func:`resize_to`."""
    u8 = depth_to_uint8(depth)
    u8 = np.repeat(u8[:, :, None], 3, axis=2)
    return resize_to(u8, resize_hw)


def hint_to_unit(hint: np.ndarray) -> np.ndarray:
    """``(h, w, 3) uint8`` hint -> ``(3, h, w) float32`` ``hint / 255`` (the official ``control_input``)."""
    return np.ascontiguousarray(np.asarray(hint).transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)


def depth_hint(depth: np.ndarray, resize_hw: tuple[int, int]) -> np.ndarray:
    """ControlNet conditioning image ``(3, h, w) float32`` in [0, 1] for ``depth (H, W)``:
    :func:`hint_image` divided by 255 (:func:`hint_to_unit`)."""
    return hint_to_unit(hint_image(depth, resize_hw))


def rgb_to_unit(image: np.ndarray, resize_hw: tuple[int, int]) -> np.ndarray:
    """RGB ``(H, W, 3) uint8`` -> ``(3, h, w) float32`` in [-1, 1] at ``resize_hw``."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if img.dtype != np.uint8:
        raise ValueError(f"image must be uint8 RGB, got dtype {img.dtype}")
    img = resize_to(img, resize_hw)
    # (x - 127.5) / 127.5 in float32, as the official sd_input (x / 127.5 - 1 differs by an ulp).
    return (np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32) - np.float32(127.5)) / np.float32(127.5)


# --------------------------------------------------------------------------------------
# DDIM arithmetic of the official code.

def n_guided_steps(t_hat: int, ddim_steps: int, num_train_timesteps: int = 1000) -> int:
    """How many guided DDIM steps run before the feature pass.

    The official code logs the latent after every step and takes the one at index
    ``round((1000 - t_hat) / (1000 / steps))``: 17 at t_hat = 150, 20 steps; 4 at 5 steps.
    (Python's ``round``, as the official code.)
    """
    if ddim_steps < 1:
        raise ValueError(f"ddim_steps must be >= 1, got {ddim_steps}")
    idx = round((num_train_timesteps - t_hat) / (num_train_timesteps / ddim_steps))
    return int(min(max(idx, 0), ddim_steps))


def feature_timestep(t_hat: int, ddim_steps: int, num_train_timesteps: int = 1000,
                     clip: bool = True) -> int:
    """The timestep of the feature pass (RGB and depth), as the official code forces it:
    ``int((steps - index) * (1000 / steps))`` with ``index`` = :func:`n_guided_steps`.
    Equal to ``t_hat`` at the defaults (150 at 20 steps); 200 at 5 steps. ``clip``: at most
    999, the last timestep the noise schedule has (the official code gives 1000 for
    ``t_hat`` above 975, where its own forward noising has no schedule entry either)."""
    idx = n_guided_steps(t_hat, ddim_steps, num_train_timesteps)
    t = int((ddim_steps - idx) * (num_train_timesteps / ddim_steps))
    return int(min(max(t, 0), num_train_timesteps - 1)) if clip else t


def seed_from(*parts) -> int:
    """A 63-bit seed mixed from ints / strings / bytes (stable across runs and machines)."""

    h = 0x9E3779B97F4A7C15
    for p in parts:
        if isinstance(p, (bytes, bytearray, memoryview)):
            v = zlib.crc32(bytes(p))
        elif isinstance(p, str):
            v = zlib.crc32(p.encode())
        else:
            v = int(p) & 0xFFFFFFFFFFFF
        h = (h ^ v) * 0x100000001B3 % (1 << 63)
    return h


@contextmanager
def cpu_threads(device, n: int):
    """torch's intra-op thread count set to ``n`` for the block when ``device`` is the CPU, then
    restored (``n = 0`` or another device: left as it is). See ``FreeRegConfig.cpu_threads``."""
    import torch

    before = torch.get_num_threads()
    change = n > 0 and torch.device(device).type == "cpu" and before != n
    if change:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if change:
            torch.set_num_threads(before)


def on_cpu_threads(method):
    """Run a model method under ``cpu_threads(self.device, self.cfg.cpu_threads)`` (backends and
    :class:`~.diffusion.DiffusionFeatures` hold both attributes)."""
    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with cpu_threads(self.device, self.cfg.cpu_threads):
            return method(self, *args, **kwargs)
    return run
