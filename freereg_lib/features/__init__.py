"""Features: descriptors of the image and the cloud, and matching them (layer 4, imports
:mod:`freereg_lib.geometry`, :mod:`freereg_lib.data` and :mod:`freereg_lib.models`).

* :mod:`.descriptors`: per-layer PCA of the diffusion maps, sampling at keypoints, fusion
  (its functions are also this package's: ``features.fuse``, ``features.pca_layers``);
* :mod:`.geometric`: FPFH (Open3D) and FCGF descriptors of a cloud;
* :mod:`.matching`: mutual nearest neighbours;
* :mod:`.baseline`: the position-only baseline (matches without features).
"""
from freereg_lib.features.descriptors import (
                                              EPS,
                                              fuse,
                                              l2_normalize,
                                              pca_layers,
                                              pca_reduce,
                                              resize_bilinear,
                                              sample_features,
)

__all__ = ["EPS", "fuse", "l2_normalize", "pca_layers", "pca_reduce", "resize_bilinear", "sample_features"]
