"""Models: the backends behind one interface, four kinds (layer 3, imports :mod:`freereg_lib.geometry`,
:mod:`freereg_lib.data` and :mod:`freereg_lib.config`).

>>> backend = get_backend("stub", cfg)            # synthetic scenes, no weights, instant
>>> backend = get_backend("tiny", cfg)            # real code path, random tiny weights
>>> backend = get_backend("micro", cfg)           # real code path, weights trained here (CPU)
>>> backend = get_backend("real", cfg, weights_dir="weights")   # SD v1.5 + ControlNet + ZoeDepth

Every backend has ``diffusion_rgb(image, ids=None)``, ``diffusion_depth(depth, ids=None)``
(the nine decoder layers 0..8, each ``(C, h, w) float32``) and
``mono_depth(image, depth_gt=None)`` (metric depth ``(H, W) float64``). See
:class:`~freereg_lib.models.base.Backend`.

The modules: :mod:`.base` (the interface and the official pre-processing), :mod:`.stub`,
:mod:`.diffusion` (SD + ControlNet with diffusers), :mod:`.zoedepth`, :mod:`.fcgf` (FCGF in plain
torch), :mod:`.weights` and :mod:`.weightcheck` (finding and checking weight files), the micro
models' architectures in :mod:`.micro`, and :mod:`.torch_backends`, the only module that builds
backends from them (``micro`` imports the pieces below it, never the backends).
"""
from __future__ import annotations

from freereg_lib.config import FreeRegConfig
from freereg_lib.models.base import (
    LAYER_STRIDES,
    N_LAYERS,
    SD15_LAYER_CHANNELS,
    Backend,
    MissingWeightsError,
    depth_hint,
    depth_to_uint8,
    feature_timestep,
    layer_sizes,
    n_guided_steps,
    official_resize_hw,
)
from freereg_lib.models.stub import StubBackend
from freereg_lib.models.torch_backends import (  # torch imported lazily
    MicroBackend,
    RealBackend,
    TinyBackend,
    resolve_device,
)
from freereg_lib.models.weightcheck import WeightsError  # a weight file that is there but unusable

BACKENDS = ("stub", "tiny", "micro", "real")
_ALIASES = {"diffusers": "real", "zoedepth": "real"}


def get_backend(name: str, cfg=None, device: str | None = None, **kw) -> Backend:
    """Build a backend by name: ``"stub"``, ``"tiny"``, ``"micro"`` or ``"real"``.

    Args:
        name: the kind (``"diffusers"`` and ``"zoedepth"`` are accepted for ``"real"``).
        cfg: a :class:`~freereg_lib.config.FreeRegConfig` (default: the paper's indoor one).
        device: ``None`` (CUDA if present, else CPU), ``"cpu"`` or ``"cuda[:N]"``; the stub
            ignores it.
        **kw: passed to the backend class (:class:`StubBackend`, ``TinyBackend``,
            ``MicroBackend``, ``RealBackend``), e.g. ``random_weights=`` (micro), ``noise=`` (stub), ``resize_hw=`` (tiny),
            ``weights_dir=`` (real), ``dtype=`` (tiny, real: overrides ``cfg.dtype``, whose
            default is the official float32 on every device).

    The real backend raises :class:`MissingWeightsError` at once when its weights are not
    on this machine.
    """
    if cfg is None:

        cfg = FreeRegConfig()
    key = _ALIASES.get(str(name).lower(), str(name).lower())
    if key == "stub":
        return StubBackend(cfg, **kw)
    if key == "tiny":
        return TinyBackend(cfg, device=device, **kw)
    if key == "micro":
        return MicroBackend(cfg, device=device, **kw)
    if key == "real":
        return RealBackend(cfg, device=device, **kw)
    raise ValueError(f"unknown backend {name!r}; expected one of {BACKENDS}")


__all__ = [
    "BACKENDS",
    "Backend",
    "LAYER_STRIDES",
    "MissingWeightsError",
    "N_LAYERS",
    "MicroBackend",
    "RealBackend",
    "SD15_LAYER_CHANNELS",
    "StubBackend",
    "TinyBackend",
    "WeightsError",
    "depth_hint",
    "depth_to_uint8",
    "feature_timestep",
    "get_backend",
    "layer_sizes",
    "n_guided_steps",
    "official_resize_hw",
    "resolve_device",
]
