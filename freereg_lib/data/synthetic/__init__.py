"""Seeded synthetic scenes: an indoor room and an outdoor street, raycast with Open3D.

This package owns the synthetic data source of the library:

* building the scenes out of boxes, cylinders and spheres, baked once per scene into an
  Open3D ``RaycastingScene`` (CPU);
* rendering the image camera: RGB (procedural textures in object coordinates, Lambertian
  shading with cast shadows, ambient light, sky and haze outdoors), true depth and class ids;
* the depth side: a second depth camera indoors, a 64-line rotating LiDAR outdoors, whose
  pose is resampled until the pair's overlap lies in a requested range;
* :func:`overlap_ratio`, the overlap measure that range refers to, and ``CLASS_NAMES``.

Modules: :mod:`.render` (primitives, raycasting, shading), :mod:`.indoor` and :mod:`.outdoor`
(the scenes and their sensors), :mod:`.pairs` (the pairs and the overlap);
``python benchmarks/bench_synthetic.py`` times them.

Conventions are those of :mod:`freereg_lib.geometry.cameras`: world z up, the point cloud frame
``pc`` is the world frame, ``T_a_b`` maps frame ``b`` into frame ``a``, depth is the camera
z coordinate with 0 where a ray hits nothing. Every random choice is drawn from one
``numpy.random.Generator`` seeded by ``seed``, so the same arguments give bit-identical
pairs.
"""
from __future__ import annotations

from freereg_lib.data.synthetic.outdoor import (
           CAMERA_HEIGHT_OUTDOOR,
           LIDAR_AZIMUTH_STEPS,
           LIDAR_ELEVATIONS_DEG,
           LIDAR_HEIGHT,
)
from freereg_lib.data.synthetic.pairs import DEFAULT_IMAGE_SIZE, KINDS, MAX_POINTS, WORLDS, make_pair, make_pairs, overlap_ratio
from freereg_lib.data.synthetic.render import CLASS_NAMES
from freereg_lib.data.synthetic.seeds import TRAINING_STREAMS, TrainingSeedError, check_eval_seed

__all__ = ["CLASS_NAMES", "KINDS", "DEFAULT_IMAGE_SIZE", "MAX_POINTS", "LIDAR_HEIGHT", "LIDAR_ELEVATIONS_DEG",
           "LIDAR_AZIMUTH_STEPS", "CAMERA_HEIGHT_OUTDOOR", "WORLDS", "make_pair", "make_pairs", "overlap_ratio",
           "TRAINING_STREAMS", "TrainingSeedError", "check_eval_seed"]
