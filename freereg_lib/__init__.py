"""freereg_lib: FreeReg (ICLR 2024), image-to-point-cloud registration, as small functions of arrays.

The method, in layers (each imports only from those below it):

* :mod:`freereg_lib.config`: :class:`FreeRegConfig`, the paper's settings, and :func:`config_for`;
* :mod:`freereg_lib.geometry`: cameras and SE(3), projection, densification, keypoints,
  Kabsch- and PnP-RANSAC, the metrics;
* :mod:`freereg_lib.data`: :class:`Pair`, the synthetic scenes, the dataset loaders;
* :mod:`freereg_lib.models`: the backends (diffusion features, monocular depth, FCGF);
* :mod:`freereg_lib.features`: PCA, sampling and fusion of descriptors, FPFH / FCGF, matching;
* :mod:`freereg_lib.pipeline`: ``depth_view`` -> ``compute_features`` -> ``match`` ->
  ``solve`` -> ``evaluate`` on a pair, and a user's own image and cloud (``register``).

Beside it, never imported by it: :mod:`freereg_lib.report` (the notebooks' figures),
:mod:`freereg_lib.commands` (``freereg register``, ``freereg batch``, ...),
:mod:`freereg_lib.training` and :mod:`freereg_lib.teaching`.
"""
import importlib

from freereg_lib.config import FreeRegConfig, config_for

__all__ = ["FreeRegConfig", "config_for", "Pair"]
__version__ = "0.1.0"

# The modules a notebook uses, by their short names: ``from freereg_lib import cameras, plots``
# imports ``freereg_lib.geometry.cameras`` and ``freereg_lib.report.plots`` on first use (PEP 562),
# so a notebook's imports stay one line while the files keep their layer folders.
SHORT_NAMES = {
    **{m: f"freereg_lib.geometry.{m}" for m in ("cameras", "projection", "densify", "keypoints", "pose", "metrics")},
    **{m: f"freereg_lib.data.{m}" for m in ("synthetic", "datasets", "sources", "paper")},
    **{m: f"freereg_lib.features.{m}" for m in ("matching", "geometric", "baseline")},
    "register": "freereg_lib.pipeline.register",
    **{m: f"freereg_lib.report.{m}" for m in ("plots", "charts", "committed_charts", "params", "registration",
                                               "pair_files", "vocabulary", "claims")},
    **{m: f"freereg_lib.commands.{m}" for m in ("batch", "cache", "user_inputs")},
}


# ``Pair`` on first use too: its module needs SciPy, which the batch runner, a course's student
# processes and a notebook job that only writes rows do not (0.27 s of each such process's start).
LAZY_ATTRIBUTES = {"Pair": "freereg_lib.data.pair"}


def __getattr__(name: str):
    if name in SHORT_NAMES:
        value = importlib.import_module(SHORT_NAMES[name])
    elif name in LAZY_ATTRIBUTES:
        value = getattr(importlib.import_module(LAZY_ATTRIBUTES[name]), name)
    else:
        raise AttributeError(f"module 'freereg_lib' has no attribute {name!r}")
    globals()[name] = value
    return value
