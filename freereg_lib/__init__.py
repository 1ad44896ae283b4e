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
from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.data.pair import Pair

__all__ = ["FreeRegConfig", "config_for", "Pair"]
__version__ = "0.1.0"
