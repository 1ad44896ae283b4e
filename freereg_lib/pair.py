"""The ``Pair``: one image-to-point-cloud registration problem with its ground truth.

Every data source (synthetic scenes, the embedded ICL sample, dataset loaders) yields
``Pair`` objects, and every pipeline step reads them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Pair:
    """An RGB image, a point cloud, the depth view to project it on, and the true pose.

    Attributes:
        image: ``(H, W, 3) uint8`` RGB.
        K_image: ``(3, 3)`` intrinsics of the image.
        points: ``(N, 3) float64`` point cloud in its own frame ``pc``.
        K_depth: ``(3, 3)`` intrinsics of the virtual depth camera the cloud is projected on.
        depth_size: ``(H_d, W_d)`` of that depth map.
        T_pc_sensor: ``(4, 4)`` pose of the depth camera in the ``pc`` frame.
        T_cam_pc: ``(4, 4)`` ground truth, maps ``pc`` points into the image camera. This
            is what the solvers estimate.
        depth_gt: ``(H, W) float64`` true depth of the image (evaluation only; 0 = none).
        image_ids: ``(H, W) int32`` class ids of the image pixels (synthetic only).
        point_ids: ``(N,) int32`` class ids of the points (synthetic only).
        name: a short identifier, e.g. ``"icl/00010-00040"``.
        meta: free-form facts (dataset, scene, overlap, indoor/outdoor).
    """

    image: np.ndarray
    K_image: np.ndarray
    points: np.ndarray
    K_depth: np.ndarray
    depth_size: tuple[int, int]
    T_pc_sensor: np.ndarray
    T_cam_pc: np.ndarray
    depth_gt: np.ndarray | None = None
    image_ids: np.ndarray | None = None
    point_ids: np.ndarray | None = None
    name: str = "pair"
    meta: dict = field(default_factory=dict)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.image.shape[0], self.image.shape[1]
