"""The registry of datasets: each name and the loader that reads it.

It sits above the loaders it lists (:mod:`.threedmatch`, :mod:`.scannet`, :mod:`.kitti`, :mod:`.demo`),
which share :mod:`.pairlists` and :mod:`.common` and never import this module.
"""
from __future__ import annotations

from pathlib import Path

from freereg_lib.data.datasets.demo import FreeRegDemo
from freereg_lib.data.datasets.kitti import KittiDC
from freereg_lib.data.datasets.pairlists import PairSource
from freereg_lib.data.datasets.rgbd_scenes_v2 import RGBDScenesV2
from freereg_lib.data.datasets.scannet import ScanNet, scannet_official
from freereg_lib.data.datasets.threedmatch import ThreeDMatch


def open_dataset(name: str, root: str | Path, **kw) -> PairSource:
    """The loader of dataset ``name`` reading ``root``; ``kw`` go to its constructor
    (e.g. ``pair_list=``).

    ``3dmatch``: :class:`~.threedmatch.ThreeDMatch`; ``kitti``: :class:`~.kitti.KittiDC`;
    ``scannet``: the official FreeReg data (:func:`~.scannet.scannet_official`) when
    ``root`` holds ``<scene>/query/`` folders, else ScanNet's own export
    (:class:`~.scannet.ScanNet`); ``demo``: :class:`~.demo.FreeRegDemo` (one pair); ``rgbd-scenes-v2``:
    :class:`~.rgbd_scenes_v2.RGBDScenesV2` (2D3D-MATR's preparation).
    """
    key = name.lower().replace("-", "_")
    if key == "scannet":
        official = any(p.is_dir() for p in Path(root).glob("*/query"))
        return (scannet_official if official else ScanNet)(root, **kw)
    loaders = {"3dmatch": ThreeDMatch, "kitti": KittiDC, "kitti_dc": KittiDC, "demo": FreeRegDemo,
               "rgbd_scenes_v2": RGBDScenesV2}
    if key not in loaders:
        raise ValueError(f"unknown dataset {name!r}; loaders exist for {sorted([*loaders, 'scannet'])}")
    return loaders[key](root, **kw)
