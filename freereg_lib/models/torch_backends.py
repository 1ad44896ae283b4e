"""The ``tiny`` and ``real`` backends: the same code path, different weights.

Models are built or loaded lazily, on the first call that needs them (diffusion models on
the first ``diffusion_*`` call, ZoeDepth on the first ``mono_depth``), so a notebook that only
needs depth never loads Stable Diffusion. The ``real`` backend checks at construction that
every weight folder it will need exists, so a missing one fails at once with
:class:`~.base.MissingWeightsError`.

Device: ``device=None`` picks CUDA when available, else the CPU. Precision: float32 on every
device, as the official code runs; ``cfg.dtype = "float16"`` or ``"bfloat16"`` is a speed-up
on CUDA that changes the features (docs/performance.md, "Faster runs"); the ``dtype=`` argument of the
backends, when given, wins over ``cfg.dtype``. ZoeDepth always runs in float32. Asking for CUDA
without CUDA raises a ``RuntimeError``.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from freereg_lib.models import weights as W
from freereg_lib.models import zoedepth  # called through the module: tests replace its loaders
from freereg_lib.models.base import Backend, MissingWeightsError, check_device, on_cpu_threads
from freereg_lib.models.diffusion import (
    DiffusionFeatures,
    build_tiny_diffusion,
    load_real_diffusion,
    wake_zero_convolutions,
)
from freereg_lib.models.micro import depth as MD
from freereg_lib.models.micro import diffusion as M
from freereg_lib.models.micro import fcgf as MF
from freereg_lib.models.stub import StubBackend

DTYPES = ("float32", "float16", "bfloat16")


def resolve_device(device: str | None = None, dtype=None):
    """``(torch.device, torch.dtype)``: CUDA when present, else the CPU; float32 unless
    ``dtype`` (a ``torch.dtype`` or one of ``DTYPES``) says otherwise, on CUDA too."""
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
        dtype = torch.float32
    elif isinstance(dtype, str):
        if dtype not in DTYPES:
            raise ValueError(f"unsupported dtype {dtype!r}; use one of {DTYPES} (float32 is the "
                             "official precision)")
        dtype = getattr(torch, dtype)
    elif dtype not in (torch.float32, torch.float16, torch.bfloat16):
        raise ValueError(f"unsupported dtype {dtype!r}; use one of {DTYPES}")
    return dev, dtype


def tiny_resize_hw(resize_hw: tuple[int, int]) -> tuple[int, int]:
    """The tiny backend's default input size: a quarter of ``resize_hw``, each side rounded to
    a multiple of 64 (at least 64): (512, 704) -> (128, 192), (512, 1280) -> (128, 320)."""
    return tuple(max(64, int(round(v / 4 / 64)) * 64) for v in resize_hw)


class _TorchBackend(Backend):
    def __init__(self, cfg, device=None, dtype=None, resize_hw=None):
        super().__init__(cfg, resize_hw)
        if dtype is None:
            dtype = getattr(cfg, "dtype", None)
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

    @on_cpu_threads
    def mono_depth(self, image: np.ndarray, depth_gt: np.ndarray | None = None) -> np.ndarray:
        return self.zoe(image)

    @on_cpu_threads
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

        return build_tiny_diffusion(self.cfg, self.device, self.dtype, self.resize_hw, self.seed)

    def _build_zoe(self):

        return zoedepth.build_tiny_zoedepth(self.device, self.seed, self.zoe_input_hw)


class RealBackend(_TorchBackend):
    """Stable Diffusion v1.5 + a depth ControlNet + ZoeDepth from local weights.

    Model ids: ``stable-diffusion-v1-5/stable-diffusion-v1-5`` (the old
    ``runwayml/stable-diffusion-v1-5`` is accepted too), its NON-EMA UNet
    (``cfg.sd_unet_variant = "non_ema"``, the official weights; ``"ema"`` opts into diffusers'
    default files); the ControlNet ``cfg.controlnet``: ``lllyasviel/control_v11f1p_sd15_depth``
    (Table 1), another model id, or a single-file original checkpoint such as the official
    fine-tuned ``control_v11f1p_sd15_depth_ft.pth`` (FreeReg-Ft; read with diffusers'
    ``ControlNetModel.from_single_file``, its architecture taken from the v1.1 depth folder's
    ``config.json``); ``Intel/zoedepth-nyu`` (indoor) or ``Intel/zoedepth-nyu-kitti``
    (``cfg.outdoor``). Where they are looked for: :mod:`freereg_lib.models.weights`.
    Nothing is downloaded.

    Args:
        cfg: the config.
        device, dtype: see :func:`resolve_device` (``dtype`` default: ``cfg.dtype``).
        weights_dir: folder holding the model folders (else ``cfg.extra["weights_dir"]``,
            ``$FREEREG_WEIGHTS``, then the Hugging Face cache); a relative single-file
            ``cfg.controlnet`` is also looked for there.
        load: which parts will be used, a subset of ``("diffusion", "mono")``; only those
            weights are required.
        zoe_id: override of the ZoeDepth model id.
        resize_hw: override of ``cfg.resize_hw``.
    """

    name = "real"

    def __init__(self, cfg, device=None, dtype=None, weights_dir=None,
                 load=("diffusion", "mono"), zoe_id: str | None = None, resize_hw=None):
        super().__init__(cfg, device, dtype, resize_hw)
        unknown = set(load) - {"diffusion", "mono"}
        if unknown:
            raise ValueError(f"unknown load parts {sorted(unknown)}; use 'diffusion', 'mono'")
        self.weights_dir = W.default_weights_dir(cfg, weights_dir)
        self.zoe_id = zoe_id or (W.ZOEDEPTH_OUTDOOR_ID if cfg.outdoor else W.ZOEDEPTH_INDOOR_ID)
        self.unet_variant = W.check_sd_unet_variant(getattr(cfg, "sd_unet_variant", "non_ema"))
        cn = str(getattr(cfg, "controlnet", None) or W.CONTROLNET_DEPTH_ID)
        self.controlnet_file = W.is_single_file(cn)
        # A single file needs the v1.1 depth folder for its architecture (config.json).
        self.controlnet_id = W.CONTROLNET_DEPTH_ID if self.controlnet_file else cn
        specs = {}
        if "diffusion" in load:
            specs["sd"] = (W.SD15_ID, W.SD15_OLD_IDS)
            specs["controlnet"] = (self.controlnet_id, ())
        if "mono" in load:
            specs["zoe"] = (self.zoe_id, ())
        self.load = tuple(load)
        self.paths = W.resolve_all(specs, self.weights_dir)
        if "diffusion" in load:
            W.require_sd_unet_variant(self.paths["sd"], self.unet_variant)
            if self.controlnet_file:
                self.paths["controlnet_file"] = W.resolve_single_file(cn, self.weights_dir)
        cn_label = (f"ControlNet {Path(cn).name}" if self.controlnet_file
                    else "ControlNet v1.1 depth" if cn == W.CONTROLNET_DEPTH_ID else f"ControlNet {cn}")
        dt = str(self.dtype).replace("torch.", "")
        self.label = (f"real backend (SD v1.5 {'non-EMA' if self.unet_variant == 'non_ema' else 'EMA'} UNet + "
                      f"{cn_label} + ZoeDepth, {dt})")

    def _need(self, key: str, part: str) -> str:
        if key not in self.paths:
            raise RuntimeError(f"this RealBackend was built with load={self.load}; "
                               f"pass load including {part!r} to use it")
        return self.paths[key]

    def _build_diffusion(self):

        sd, cn = self._need("sd", "diffusion"), self._need("controlnet", "diffusion")
        cn_file = self.paths.get("controlnet_file")
        try:
            return load_real_diffusion(sd, cn_file or cn, self.cfg, self.device, self.dtype, self.resize_hw,
                                       unet_variant=self.unet_variant,
                                       controlnet_config=cn if cn_file else None)
        except (OSError, ValueError, EnvironmentError) as e:
            if isinstance(e, MissingWeightsError):
                raise
            raise W.missing_weights_error(
                [(W.SD15_ID, [sd]), (self.controlnet_id, [cn_file or cn])], self.weights_dir,
                reason=f"{type(e).__name__}: {e}") from e

    def _build_zoe(self):

        path = self._need("zoe", "mono")
        try:
            return zoedepth.load_real_zoedepth(path, self.device)
        except (OSError, ValueError) as e:
            if isinstance(e, MissingWeightsError):
                raise
            raise W.missing_weights_error([(self.zoe_id, [path])], self.weights_dir,
                                          reason=f"{type(e).__name__}: {e}") from e


class MicroBackend(_TorchBackend):
    """The micro models (:mod:`freereg_lib.models.micro`): SD-layout diffusion models and a ZoeDepth
    trained here on the synthetic rooms, run by the same feature and depth code as the ``real``
    backend.

    The weights are committed in the package (``freereg_lib/models/micro/weights``, the depth model in
    its ``depth/`` folder; model cards beside them). The VAE halves the 128 x 192 input twice,
    so the nine decoder layers are 4 x 6, 8 x 12 and 16 x 24 (strides 32, 16, 8 instead of SD's
    64, 32, 16). Monocular depth is the micro ZoeDepth (:mod:`freereg_lib.models.micro.depth`:
    transformers' ``ZoeDepthForDepthEstimation`` with a 4-layer BEiT, run through
    :class:`~.zoedepth.ZoeDepthEstimator` with padding and flip averaging as the real one), so
    it needs no ``depth_gt``; ``mono_depth="stub"`` keeps the stub's designed error instead (the
    true depth with a scale error and smooth distortion; it needs ``depth_gt``).

    Args:
        cfg: the config (indoor: the micro models were trained on rooms only).
        device, dtype: see :func:`resolve_device` (ZoeDepth always runs in float32).
        weights_dir: another folder of micro weights (default: ``$FREEREG_MICRO_WEIGHTS``, else
            the committed ones), e.g. the ``--export`` folder of a retraining.
        random_weights: the same architectures with seeded random weights instead (zero
            convolutions drawn small, as the tiny backend's, so the hint still acts; the depth
            model Kaiming-initialised as :func:`freereg_lib.models.micro.depth.build`): the baseline
            that shows what the training contributes.
        seed: the random weights' seed (default ``cfg.seed``).
        mono_depth: ``"micro"`` (default, the trained micro ZoeDepth) or ``"stub"`` (the stub's
            designed error, for comparison).
        depth_weights_dir: the micro ZoeDepth folder (default: ``weights_dir/depth`` when it
            holds one, else the committed ``freereg_lib/models/micro/weights/depth``).
        mono_mae: with ``mono_depth="stub"``, the stub's error size in metres (its
            ``mono_mae``; a controlled sweep of the depth error, notebook 02).
        fcgf_weights_dir: a micro FCGF folder (``train_fcgf --export``) for ``cfg.geometric =
            "fcgf"`` (default: ``weights_dir/fcgf``, else the package's, where none is committed).
    """

    name = "micro"
    strides = (32, 32, 32, 16, 16, 16, 8, 8, 8)
    MONO_DEPTHS = ("micro", "stub")

    def __init__(self, cfg, device=None, dtype=None, weights_dir=None, random_weights: bool = False,
                 seed: int | None = None, mono_depth: str = "micro", depth_weights_dir=None,
                 mono_mae: float | None = None, fcgf_weights_dir=None):

        if getattr(cfg, "outdoor", False):
            raise ValueError("the micro models were trained on the synthetic indoor world only; "
                             "use backend='stub' (or 'real' with weights) for outdoor scenes")
        if mono_depth not in self.MONO_DEPTHS:
            raise ValueError(f"mono_depth must be one of {self.MONO_DEPTHS}, got {mono_depth!r}")
        super().__init__(cfg, device, dtype, M.MICRO_RESIZE_HW)
        weights_dir = weights_dir or os.environ.get("FREEREG_MICRO_WEIGHTS") or None
        self.weights_dir = Path(weights_dir) if weights_dir else M.WEIGHTS_DIR
        self.random_weights = bool(random_weights)
        self.seed = cfg.seed if seed is None else int(seed)
        self.mono_kind = mono_depth
        if mono_mae is not None and mono_depth != "stub":
            raise ValueError("mono_mae sets the stub's designed depth error: pass mono_depth='stub' with it")
        self.mono_mae = mono_mae
        self.fcgf_weights_dir = fcgf_weights_dir
        if not self.random_weights and M.missing_parts(self.weights_dir):
            raise MissingWeightsError(
                f"micro weights missing in {self.weights_dir}: {', '.join(M.missing_parts(self.weights_dir))}; "
                "retrain them with `python -m freereg_lib.training.retrain --export "
                f"{self.weights_dir}`")
        if depth_weights_dir is None:
            own = self.weights_dir / "depth"
            depth_weights_dir = own if not MD.missing_files(own) else MD.WEIGHTS_DIR
        self.depth_weights_dir = Path(depth_weights_dir)
        if mono_depth == "micro" and not self.random_weights and MD.missing_files(self.depth_weights_dir):
            raise MissingWeightsError(
                f"micro depth weights missing in {self.depth_weights_dir}: "
                f"{', '.join(MD.missing_files(self.depth_weights_dir))}; retrain them with "
                f"`python -m freereg_lib.training.train_depth --export {self.depth_weights_dir}` "
                "(or pass mono_depth='stub')")
        self._stub = None
        kind = "random weights, same architectures" if self.random_weights else "trained on synthetic rooms"
        if mono_depth == "micro":
            mono = "the micro ZoeDepth"
        elif mono_mae == 0:
            mono = "the true depth (the stub's error at 0 m)"
        else:
            mono = "the stub's designed error" + ("" if mono_mae is None else f", MAE {mono_mae:g} m")
        self.label = f"micro backend (SD-layout diffusion models + ZoeDepth, {kind}; monocular depth: {mono})"

    def layer_shapes(self) -> list[tuple[int, int]]:
        h, w = self.resize_hw
        return [(h // s, w // s) for s in self.strides]

    def _build_diffusion(self):
        import torch


        if self.random_weights:
            mods = M.build(self.seed)
            wake_zero_convolutions(mods["controlnet"])
        else:
            mods = M.load(self.weights_dir, device="cpu")
        nets = [torch.nn.Module.to(mods[k], device=self.device, dtype=self.dtype).eval()
                for k in ("unet", "controlnet", "vae", "text_encoder")]
        return DiffusionFeatures(*nets[:3], nets[3], mods["tokenizer"], self.cfg, self.device,
                                 self.dtype, self.resize_hw)

    def _build_zoe(self):

        if self.random_weights:
            return MD.estimator(MD.build(self.seed), self.device)
        return MD.load(self.depth_weights_dir, self.device)

    @on_cpu_threads
    def mono_depth(self, image: np.ndarray, depth_gt: np.ndarray | None = None) -> np.ndarray:
        """Metric depth ``(H, W)`` of ``image``: the micro ZoeDepth (``depth_gt`` unused), or
        the stub's designed error of ``depth_gt`` with ``mono_depth="stub"``."""
        if self.mono_kind == "micro":
            return self.zoe(image)
        if self._stub is None:

            self._stub = StubBackend(self.cfg, mono_mae=self.mono_mae)
        return self._stub.mono_depth(image, depth_gt)

    @on_cpu_threads
    def mono_depth_batch(self, images, depth_gts=None) -> list[np.ndarray]:
        """The micro ZoeDepth on all ``images`` in one call per size (flips included), or the
        stub per image."""
        if self.mono_kind == "micro":
            return self.zoe.batch(list(images))
        return Backend.mono_depth_batch(self, images, depth_gts)

    def fcgf_model(self):
        """The micro FCGF (``fcgf_weights_dir``, else ``weights_dir/fcgf``, else the package's;
        loaded by the official checkpoints' loader) for ``cfg.geometric = "fcgf"``, or the same
        network with seeded random weights when ``random_weights``. A missing file raises
        ``MissingWeightsError`` with the command that trains one."""
        if getattr(self, "_fcgf", None) is None:

            if self.random_weights:
                self._fcgf = MF.build(self.seed).to(self.device).eval()
            else:
                folder = self.fcgf_weights_dir or MF.folder_of(self.weights_dir)
                self._fcgf = MF.load(folder, device=self.device)
        return self._fcgf
