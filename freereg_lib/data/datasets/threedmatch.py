"""3DMatch test scenes in the official FreeReg data layout (and any data in that layout).

Layout (the official FreeReg test data; ``<id>`` is an integer frame number)::

    <root>/<scene>/query/<id>.color.png       RGB image
    <root>/<scene>/query/<id>.depth.png       16-bit depth PNG, value / depth_scale = metres, 0 or 65535 = none
    <root>/<scene>/query/<id>_pose.txt        4 x 4 pose of the camera in the scene (camera -> world)
    <root>/<scene>/query/overlap.txt          one candidate pair per row: "i j overlap"
    <root>/<scene>/query/<id>.color.gtd.png   optional: true depth of the RGB at its own size
    <root>/<scene>/query/<id>.depth.gtd.png   optional: true depth of the depth frame (ScanNet's data)

A pair is the RGB of frame ``i`` against the point cloud back-projected from the depth of
frame ``j``, in camera ``j``'s frame (the depth view is camera ``j`` itself), kept when
``overlap > 0.3``; that depth map, exactly as read, is the pair's ``sensor_depth`` (the
official code's depth-side input on 3DMatch, holes kept). The official code's ground truth ``inv(T_j) @ T_i`` maps the image camera
into the cloud frame; :class:`~freereg_lib.data.pair.Pair` stores the inverse,
``T_cam_pc = inv(T_i) @ T_j``. 3DMatch: 640 x 480, fx = fy = 585, (cx, cy) = (320, 240),
depth in millimetres.

What is checked as the files are read (each error names the file): depth value 65535 is
"no measurement" (7-Scenes, part of 3DMatch's test set, writes it) and becomes a hole (0),
not 65.5 m; a depth frame whose median lies outside 0.1..20 m is refused with a units hint
(a wrong ``depth_scale``); pose files are made rigid when their rotation is off orthonormal
by up to 1e-2 (7-Scenes poses are orthonormal only to ~3e-4; a warning above 1e-4, once
per folder) and refused beyond, or when transposed, or when a translation exceeds 100 m
(millimetres); overlaps above 1 (percentages) are refused; the intrinsics must fit the
image sizes; a truncated PNG is refused.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from freereg_lib.data.datasets.common import (
    INDOOR_DEPTH_RANGE, INDOOR_MAX_TRANSLATION, INVALID_DEPTH, read_depth, read_pose_txt, read_rgb,
)
from freereg_lib.data.datasets.pairlists import (
    PairEntry, PairSource, depth_in_image, load_or_build, require, voxel_downsample,
)
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras

LAYOUT = __doc__.split("::\n\n", 1)[1].split("\n\n", 1)[0]
K_3DMATCH = cameras.intrinsics(585.0, 585.0, 320.0, 240.0)


class FreeRegScenes(PairSource):
    """Reader of the official FreeReg layout (above) for any camera set-up.

    Args:
        root: the folder holding one sub-folder per scene.
        dataset: the name written into pair names and the pair list (``"3dmatch"``, ...).
        K_image, K_depth: ``(3, 3)`` intrinsics of the colour and depth cameras, which share
            their centre and orientation.
        image_size, depth_size: ``(H, W)`` of the colour and depth images.
        depth_scale: depth PNG value per metre.
        voxel: when set, the cloud is voxel-downsampled to this size in metres (then the
            cloud is no longer the back-projection of ``sensor_depth``; default None).
        min_overlap: pairs with ``overlap > min_overlap`` in ``overlap.txt`` are kept (a
            fraction in [0, 1)).
        pair_list: where the pair list is kept; default
            ``<root>/freereg_pairs_overlap<min_overlap>.txt``.
        invalid_depth: raw depth value meaning "no measurement" besides 0 (65535).
        depth_range: ``(lo, hi)`` metres the median depth of a frame must lie in.
        max_translation: longest camera translation (m) a pose file may hold.
    """

    def __init__(self, root, dataset: str, K_image: np.ndarray, K_depth: np.ndarray,
                 image_size: tuple[int, int], depth_size: tuple[int, int], depth_scale: float = 1000.0,
                 voxel: float | None = None, min_overlap: float = 0.3, pair_list=None,
                 invalid_depth: int | None = INVALID_DEPTH, depth_range: tuple[float, float] = INDOOR_DEPTH_RANGE,
                 max_translation: float = INDOOR_MAX_TRANSLATION):
        self.root = require(root, f"{dataset} root folder", LAYOUT)
        self.dataset = dataset
        if not 0 <= min_overlap < 1:
            raise ValueError(f"min_overlap = {min_overlap:g}: it is a fraction in [0, 1) (0.3 for 30 %), not a percentage")
        self.image_size, self.depth_size = tuple(image_size), tuple(depth_size)
        self.K_image = cameras.check_intrinsics(K_image, self.image_size, f"{dataset} K_image")
        self.K_depth = cameras.check_intrinsics(K_depth, self.depth_size, f"{dataset} K_depth")
        self.depth_scale = depth_scale
        self.invalid_depth, self.depth_range, self.max_translation = invalid_depth, depth_range, max_translation
        self.voxel = voxel
        self.min_overlap = min_overlap
        self.rule = f"overlap > {min_overlap:g}"
        self.pair_list_path = Path(pair_list) if pair_list else self.root / f"freereg_pairs_overlap{min_overlap:g}.txt"

    def scenes(self) -> list[str]:
        """Scene folder names (those with a ``query/`` folder), sorted."""
        found = sorted(p.parent.name for p in self.root.glob("*/query") if p.is_dir())
        if not found:
            raise FileNotFoundError(f"no <scene>/query/ folder under {self.root}\nexpected layout:\n{LAYOUT}")
        return found

    def pair_list(self) -> list[PairEntry]:
        """The fixed pair list, built from every scene's ``overlap.txt`` on first use."""
        return load_or_build(self.pair_list_path, self.dataset, self.rule, str(self.root), self._build)

    def _build(self) -> list[PairEntry]:
        entries = []
        for scene in self.scenes():
            path = require(self.root / scene / "query" / "overlap.txt", "overlap file", LAYOUT)
            try:
                rows = np.loadtxt(path, ndmin=2)
            except ValueError as exc:
                raise ValueError(f"cannot read {path} as rows 'i j overlap' of numbers: {exc}") from None
            if rows.size and rows.shape[1] != 3:
                raise ValueError(f"{path}: expected rows 'i j overlap', got {rows.shape[1]} columns")
            if rows.size and (rows[:, 2].max() > 1 or rows[:, 2].min() < 0):
                hint = ("; they look like percentages: write fractions (divide by 100)" if rows[:, 2].max() > 1 else "")
                raise ValueError(f"{path}: overlaps range over {rows[:, 2].min():g}..{rows[:, 2].max():g}, "
                                 f"expected fractions in [0, 1]{hint}")
            entries += [PairEntry(scene, str(int(i)), str(int(j)), float(o))
                        for i, j, o in rows if o > self.min_overlap]
        return entries

    def _file(self, entry_scene: str, name: str, what: str) -> Path:
        return require(self.root / entry_scene / "query" / name, what, LAYOUT)

    def _checked(self, arr: np.ndarray, size: tuple[int, int], path: Path) -> np.ndarray:
        if arr.shape[:2] != size:
            raise ValueError(f"{path} is {arr.shape[1]} x {arr.shape[0]}, expected "
                             f"{size[1]} x {size[0]} for {self.dataset}")
        return arr

    def pose(self, scene: str, frame: str) -> np.ndarray:
        """``T_world_cam (4, 4)`` of ``frame``."""
        return read_pose_txt(self._file(scene, f"{frame}_pose.txt", "pose file"), self.max_translation)

    def depth(self, scene: str, frame: str) -> np.ndarray:
        """Depth of ``frame`` in metres, ``depth_size`` (0 = hole, ``invalid_depth`` included)."""
        path = self._file(scene, f"{frame}.depth.png", "depth image")
        return self._checked(read_depth(path, self.depth_scale, self.invalid_depth, self.depth_range),
                             self.depth_size, path)

    def pair(self, entry: PairEntry) -> Pair:
        """RGB of ``entry.image_frame`` against the cloud of ``entry.cloud_frame``."""
        s, i, j = entry.scene, entry.image_frame, entry.cloud_frame
        rgb_path = self._file(s, f"{i}.color.png", "colour image")
        image = self._checked(read_rgb(rgb_path), self.image_size, rgb_path)
        sensor_depth = self.depth(s, j)
        points, _ = cameras.backproject(sensor_depth, self.K_depth)
        if self.voxel:
            points = voxel_downsample(points, self.voxel)
        gtd = self.root / s / "query" / f"{i}.color.gtd.png"
        if gtd.is_file():
            depth_gt = self._checked(read_depth(gtd, self.depth_scale, self.invalid_depth, self.depth_range),
                                     self.image_size, gtd)
        else:
            depth_gt = depth_in_image(self.depth(s, i), self.K_depth, self.K_image, self.image_size)
        # The depth side's truth: <j>.depth.gtd.png when the data has one (the official dpt_gtd),
        # else the pipeline's rule (the densified map when the dataset densifies, else the raw one).
        dpt_gtd = self.root / s / "query" / f"{j}.depth.gtd.png"
        depth_frame_gt = None
        if dpt_gtd.is_file():
            depth_frame_gt = self._checked(read_depth(dpt_gtd, self.depth_scale, self.invalid_depth, self.depth_range),
                                           self.depth_size, dpt_gtd)
        return Pair(
            image=image, K_image=self.K_image.copy(), points=points, K_depth=self.K_depth.copy(),
            depth_size=self.depth_size, T_pc_sensor=np.eye(4),
            T_cam_pc=cameras.invert(self.pose(s, i)) @ self.pose(s, j),
            depth_gt=depth_gt, sensor_depth=sensor_depth, depth_frame_gt=depth_frame_gt, name=f"{self.dataset}/{entry.key}",
            meta={"dataset": self.dataset, "scene": s, "frame_image": i, "frame_cloud": j,
                  "overlap": entry.score, "outdoor": False},
        )


class ThreeDMatch(FreeRegScenes):
    """The 3DMatch test scenes of the official FreeReg data (1210 pairs at overlap > 0.3)."""

    def __init__(self, root, min_overlap: float = 0.3, pair_list=None):
        super().__init__(root, "3dmatch", K_3DMATCH, K_3DMATCH, (480, 640), (480, 640), 1000.0,
                         None, min_overlap, pair_list)
