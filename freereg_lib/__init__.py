"""freereg_lib: the library behind the FreeReg companion notebooks.

Modules, in pipeline order: ``cameras`` (SE(3), projection), ``projection`` (cloud ->
depth map), ``densify`` (IP-Basic), ``backends`` (diffusion features, monocular depth),
``features`` (PCA, sampling, fusion), ``geometric`` (FPFH / FCGF), ``keypoints``,
``matching`` (mutual NN), ``pose`` (Kabsch / PnP RANSAC), ``metrics``; ``pipeline`` strings
them together; ``synthetic`` and ``datasets`` make pairs; ``config`` holds the paper's
hyper-parameters.
"""
from .config import FreeRegConfig, config_for
from .pair import Pair

__all__ = ["FreeRegConfig", "config_for", "Pair"]
__version__ = "0.1.0"
