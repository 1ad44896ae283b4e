"""The ``tiny`` and ``real`` backends: the same code path, different weights.

Models are built or loaded lazily, on the first call that needs them (diffusion models on
the first ``diffusion_*`` call, ZoeDepth on the first ``mono_depth``), so a notebook that only
needs depth never loads Stable Diffusion. The ``real`` backend checks at construction that
every weight folder it will need exists, so a missing one fails at once with
:class:`~.base.MissingWeightsError`.

Device: ``device=None`` picks CUDA when available, else the CPU; float16 on CUDA, float32 on
the CPU (``dtype=`` overrides). Asking for CUDA without CUDA raises a ``RuntimeError``.
"""
from __future__ import annotations

import numpy as np

from .base import Backend, MissingWeightsError, check_device
from . import weights as W


def resolve_device(device: str | None = None, dtype=None):
    """``(torch.device, torch.dtype)``: CUDA + float16 when present, else CPU + float32."""
    import torch

    check_device(device)
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(
            f"device={device!r} was requested but CUDA is not available "
            f"(torch {torch.__version__}, torch.cuda.is_available() is False). "
            "Use device='cpu' or device=None (auto)."
        )
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise RuntimeError(
            f"device={device!r} was requested but this machine has {torch.cuda.device_count()} CUDA "
            f"device(s), numbered from 0. Use device='cuda:0', 'cuda' or None (auto)."
        )
    if dev.type not in ("cuda", "cpu"):
        raise ValueError(f"unsupported device {device!r}; use 'cuda', 'cuda:N' or 'cpu'")
    if dtype is None:
        dtype = torch.float16 if dev.type == "cuda" else torch.float32
    elif isinstance(dtype, str):
        dtype = getattr(torch, dtype)
    return dev, dtype


def tiny_resize_hw(resize_hw: tuple[int, int]) -> tuple[int, int]:
    """The tiny backend's default input size: a quarter of ``resize_hw``, each side rounded to
    a multiple of 64 (at least 64): (512, 704) -> (128, 192), (512, 1280) -> (128, 320)."""
    return tuple(max(64, int(round(v / 4 / 64)) * 64) for v in resize_hw)


class _TorchBackend(Backend):
    def __init__(self, cfg, device=None, dtype=None, resize_hw=None):
        super().__init__(cfg, resize_hw)
        self.device, self.dtype = resolve_device(device, dtype)
        self._diffusion = None
        self._zoe = None

    # Subclasses build these.
    def _build_diffusion(self):
        raise NotImplementedError

    def _build_zoe(self):
        raise NotImplementedError

    @property
    def diffusion(self):
        """The :class:`~.diffusion.DiffusionFeatures` (built on first use)."""
        if self._diffusion is None:
            self._diffusion = self._build_diffusion()
        return self._diffusion

    @property
    def zoe(self):
        """The :class:`~.zoedepth.ZoeDepthEstimator` (built on first use)."""
        if self._zoe is None:
            self._zoe = self._build_zoe()
        return self._zoe

    def diffusion_rgb(self, image: np.ndarray, ids: np.ndarray | None = None,
                      xyz: np.ndarray | None = None) -> list[np.ndarray]:
        return self.diffusion.rgb(image)

    def diffusion_depth(self, depth: np.ndarray, ids: np.ndarray | None = None,
                        xyz: np.ndarray | None = None) -> list[np.ndarray]:
        return self.diffusion.depth(depth)

    def diffusion_rgb_batch(self, images, hints=None, layers=None) -> list[dict[int, np.ndarray]]:
        """One batched VAE + UNet pass for all ``images``, stopped after the last of ``layers``."""
        return self.diffusion.rgb_batch(list(images), layers)

    def diffusion_depth_batch(self, depths, hints=None, layers=None) -> list[dict[int, np.ndarray]]:
        """The DDIM steps of all ``depths`` batched, stopped after the last of ``layers``."""
        return self.diffusion.depth_batch(list(depths), layers)

    def mono_depth(self, image: np.ndarray, depth_gt: np.ndarray | None = None) -> np.ndarray:
        return self.zoe(image)

    def mono_depth_batch(self, images, depth_gts=None) -> list[np.ndarray]:
        """ZoeDepth on all ``images``, same-size images (and their flips) in one call."""
        return self.zoe.batch(list(images))


class TinyBackend(_TorchBackend):
    """The real architectures (diffusers UNet, ControlNet, VAE, CLIP text; transformers
    ZoeDepth) from small configs with random, seeded weights: the real code path in CI
    in seconds. Its numbers mean nothing.

    Args:
        cfg: the config.
        device, dtype: see :func:`resolve_device`.
        resize_hw: diffusion input size; default :func:`tiny_resize_hw` of ``cfg.resize_hw``
            (a quarter, so layers are 2 x 3, 4 x 6, 8 x 12 for the indoor default).
        seed: weight seed (default ``cfg.seed``).
        zoe_input_hw: the tiny ZoeDepth's processing size.
    """

    name = "tiny"
    label = "tiny backend (random-weight miniature models; numbers mean nothing)"

    def __init__(self, cfg, device=None, dtype=None, resize_hw=None, seed: int | None = None,
                 zoe_input_hw=(64, 96)):
        super().__init__(cfg, device, dtype, resize_hw or tiny_resize_hw(cfg.resize_hw))
        self.seed = cfg.seed if seed is None else int(seed)
        self.zoe_input_hw = tuple(zoe_input_hw)

    def _build_diffusion(self):
        from .diffusion import build_tiny_diffusion

        return build_tiny_diffusion(self.cfg, self.device, self.dtype, self.resize_hw, self.seed)

    def _build_zoe(self):
        from .zoedepth import build_tiny_zoedepth

        return build_tiny_zoedepth(self.device, self.seed, self.zoe_input_hw)


class RealBackend(_TorchBackend):
    """Stable Diffusion v1.5 + ControlNet v1.1 depth + ZoeDepth from local weights.

    Model ids: ``stable-diffusion-v1-5/stable-diffusion-v1-5`` (the old
    ``runwayml/stable-diffusion-v1-5`` is accepted too), ``lllyasviel/control_v11f1p_sd15_depth``,
    ``Intel/zoedepth-nyu`` (indoor) or ``Intel/zoedepth-nyu-kitti`` (``cfg.outdoor``).
    Where they are looked for: :mod:`freereg_lib.backends.weights`. Nothing is downloaded.

    Args:
        cfg: the config.
        device, dtype: see :func:`resolve_device`.
        weights_dir: folder holding the model folders (else ``cfg.extra["weights_dir"]``,
            ``$FREEREG_WEIGHTS``, then the Hugging Face cache).
        load: which parts will be used, a subset of ``("diffusion", "mono")``; only those
            weights are required.
        zoe_id: override of the ZoeDepth model id.
        resize_hw: override of ``cfg.resize_hw``.
    """

    name = "real"
    label = "real backend (SD v1.5 + ControlNet v1.1 depth + ZoeDepth)"

    def __init__(self, cfg, device=None, dtype=None, weights_dir=None,
                 load=("diffusion", "mono"), zoe_id: str | None = None, resize_hw=None):
        super().__init__(cfg, device, dtype, resize_hw)
        unknown = set(load) - {"diffusion", "mono"}
        if unknown:
            raise ValueError(f"unknown load parts {sorted(unknown)}; use 'diffusion', 'mono'")
        self.weights_dir = W.default_weights_dir(cfg, weights_dir)
        self.zoe_id = zoe_id or (W.ZOEDEPTH_OUTDOOR_ID if cfg.outdoor else W.ZOEDEPTH_INDOOR_ID)
        specs = {}
        if "diffusion" in load:
            specs["sd"] = (W.SD15_ID, W.SD15_OLD_IDS)
            specs["controlnet"] = (W.CONTROLNET_DEPTH_ID, ())
        if "mono" in load:
            specs["zoe"] = (self.zoe_id, ())
        self.load = tuple(load)
        self.paths = W.resolve_all(specs, self.weights_dir)

    def _need(self, key: str, part: str) -> str:
        if key not in self.paths:
            raise RuntimeError(f"this RealBackend was built with load={self.load}; "
                               f"pass load including {part!r} to use it")
        return self.paths[key]

    def _build_diffusion(self):
        from .diffusion import load_real_diffusion

        sd, cn = self._need("sd", "diffusion"), self._need("controlnet", "diffusion")
        try:
            return load_real_diffusion(sd, cn, self.cfg, self.device, self.dtype, self.resize_hw)
        except (OSError, ValueError, EnvironmentError) as e:
            if isinstance(e, MissingWeightsError):
                raise
            raise W.missing_weights_error(
                [(W.SD15_ID, [sd]), (W.CONTROLNET_DEPTH_ID, [cn])], self.weights_dir,
                reason=f"{type(e).__name__}: {e}") from e

    def _build_zoe(self):
        from .zoedepth import load_real_zoedepth

        path = self._need("zoe", "mono")
        try:
            return load_real_zoedepth(path, self.device)
        except (OSError, ValueError) as e:
            if isinstance(e, MissingWeightsError):
                raise
            raise W.missing_weights_error([(self.zoe_id, [path])], self.weights_dir,
                                          reason=f"{type(e).__name__}: {e}") from e
