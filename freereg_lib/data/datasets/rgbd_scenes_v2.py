"""RGBD-Scenes-v2 as 2D3D-MATR prepares it (Table 5 of the appendix: scenes 11-14).

Layout (2D3D-MATR's release of the data; paths inside the metadata are relative to ``data/``)::

    <root>/metadata/test.pkl                    a pickled list, one dict per pair: scene_name,
                                                image_file, depth_file, cloud_file, overlap,
                                                cloud_to_image (4 x 4, cloud frame -> camera)
    <root>/data/<scene_name>/camera-intrinsics.txt   3 x 3 intrinsics
    <root>/data/<image_file>, <depth_file>      colour PNG; its 16-bit depth PNG in millimetres
    <root>/data/<cloud_file>                    the point cloud, (N, 3) float .npy, metres

The cloud is taken in its own depth camera's frame, seen by a camera with the image's
intrinsics and size (the depth view projects it there); ``cloud_to_image`` is ``T_cam_pc``.
"""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from freereg_lib.data.datasets.common import INDOOR_DEPTH_RANGE, read_depth, read_rgb
from freereg_lib.data.datasets.pairlists import PairEntry, PairSource, require
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras

LAYOUT = __doc__.split("::\n\n", 1)[1].split("\n\n", 1)[0]
KEYS = ("scene_name", "image_file", "depth_file", "cloud_file", "overlap", "cloud_to_image")


class RGBDScenesV2(PairSource):
    """The pairs of ``metadata/<subset>.pkl`` (``test``: scenes 11-14), in the file's order."""

    dataset = "rgbd_scenes_v2"

    def __init__(self, root, subset: str = "test"):
        self.root = require(root, "RGBD-Scenes-v2 root folder", LAYOUT)
        path = require(self.root / "metadata" / f"{subset}.pkl", "metadata file", LAYOUT)
        try:  # 2D3D-MATR's own format, the file the user downloaded
            with open(path, "rb") as fh:
                self.records = pickle.load(fh)
        except Exception as exc:
            raise ValueError(f"{path}: cannot read it as a pickled list ({type(exc).__name__}: {exc})") from None
        recs = self.records if isinstance(self.records, list) else [None]
        bad = [n for n, r in enumerate(recs) if not isinstance(r, dict) or set(KEYS) - set(r)]
        if bad:
            raise ValueError(f"{path}: entry {bad[0]} is not a dict with the keys {list(KEYS)}")
        self.entries = {PairEntry(r["scene_name"], Path(r["image_file"]).stem, Path(r["cloud_file"]).stem,
                                  float(r["overlap"])).key: r for r in self.records}

    def pair_list(self) -> list[PairEntry]:
        return [PairEntry(r["scene_name"], Path(r["image_file"]).stem, Path(r["cloud_file"]).stem, float(r["overlap"]))
                for r in self.records]

    def pair(self, entry: PairEntry) -> Pair:
        r, data = self.entries[entry.key], self.root / "data"
        image = read_rgb(data / r["image_file"])
        size = image.shape[:2]
        K = cameras.check_intrinsics(np.loadtxt(require(data / r["scene_name"] / "camera-intrinsics.txt",
                                                        "intrinsics file", LAYOUT)), size, entry.scene)
        points = np.load(require(data / r["cloud_file"], "point cloud", LAYOUT)).astype(np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise ValueError(f"{data / r['cloud_file']}: expected an (N, 3) array of points, got shape {points.shape}")
        return Pair(image=image, K_image=K, points=points, K_depth=K.copy(), depth_size=size, T_pc_sensor=np.eye(4),
                    T_cam_pc=np.asarray(r["cloud_to_image"], np.float64),
                    depth_gt=read_depth(data / r["depth_file"], 1000.0, expected=INDOOR_DEPTH_RANGE),
                    name=f"{self.dataset}/{entry.key}",
                    meta={"dataset": self.dataset, "scene": entry.scene, "overlap": entry.score, "outdoor": False})
