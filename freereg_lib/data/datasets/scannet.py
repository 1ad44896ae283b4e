"""ScanNet test scenes, from ScanNet's own export or from the official FreeReg data.

Layout read by :class:`ScanNet`, what ScanNet's ``SensReader`` writes when it exports a
``.sens`` file (``python reader.py --export_color_images --export_depth_images
--export_poses --export_intrinsics``), one folder per scene::

    <root>/<scene>/color/<frame>.jpg                RGB, 1296 x 968
    <root>/<scene>/depth/<frame>.png                16-bit depth, 640 x 480, millimetres, 0 or 65535 = none
    <root>/<scene>/pose/<frame>.txt                 4 x 4 camera -> world (a pose with -inf: frame skipped)
    <root>/<scene>/intrinsic/intrinsic_color.txt    4 x 4, K of the colour camera top-left
    <root>/<scene>/intrinsic/intrinsic_depth.txt    4 x 4, K of the depth camera top-left

A pair is the RGB of frame ``i`` (1296 x 968, colour intrinsics) against the cloud of
depth frame ``j`` (640 x 480, depth intrinsics) in camera ``j``'s frame: the back-projection
of that depth map, which is also the pair's ``sensor_depth`` (the official code's depth-side
cloud is the back-projection of the depth map, not a 3 cm voxel cloud; the paper's "3 cm"
is available as ``voxel=0.03``); ``T_cam_pc = inv(T_i) @ T_j``. The exported colour and depth cameras share centre
and orientation, so the image's true depth is depth ``i`` resampled through the two
intrinsics. ScanNet ships no overlap list; ours: every ``frame_step``-th frame with a valid
pose, pairs ``i < j`` at most ``max_gap`` frames apart, overlap = the fraction of depth
``j``'s pixels (every 4th row and column) whose 3D point, moved into camera ``i``, lands on
a pixel of depth ``i`` within ``overlap_tol`` metres of its own depth; kept at overlap > 0.3.
The paper's own 4660 pairs come with the official FreeReg data: read those with
:func:`scannet_official` (the 3DMatch layout with ScanNet's cameras).

Checks as files are read (each error names the file): depth value 65535 is a hole, a depth
frame with a median outside 0.1..20 m is refused (units), pose files are made rigid within
1e-2 and refused beyond (a pose with -inf, lost tracking, skips the frame), translations over
100 m are refused (millimetres), intrinsics must fit the image and depth sizes, truncated
JPEG / PNG files are refused.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from freereg_lib.data.datasets.common import (
    INDOOR_DEPTH_RANGE, INDOOR_MAX_TRANSLATION, INVALID_DEPTH, checked_pose, read_depth, read_rgb,
)
from freereg_lib.data.datasets.pairlists import (
    PairEntry, PairSource, depth_in_image, load_or_build, require, voxel_downsample,
)
from freereg_lib.data.datasets.threedmatch import FreeRegScenes
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras

LAYOUT = __doc__.split("::\n\n", 1)[1].split("\n\n", 1)[0]
# The cameras of the official FreeReg ScanNet data (its config/scannet.yaml).
K_COLOR_OFFICIAL = np.array([[1163.45, 0, 635.626], [0, 1164.79, 481.600], [0, 0, 1]])
K_DEPTH_OFFICIAL = np.array([[574.541, 0, 322.522], [0, 577.584, 238.559], [0, 0, 1]])


def scannet_official(root, min_overlap: float = 0.3, pair_list=None) -> FreeRegScenes:
    """The official FreeReg ScanNet test data (3DMatch layout, RGB 1296 x 968 and depth
    640 x 480 with their own intrinsics). The cloud is the back-projection of depth frame
    ``j`` and that depth map is ``sensor_depth``, as the official code uses them (no 3 cm
    voxel grid)."""
    return FreeRegScenes(root, "scannet", K_COLOR_OFFICIAL, K_DEPTH_OFFICIAL, (968, 1296), (480, 640),
                         1000.0, None, min_overlap, pair_list)


def frame_overlap(depth_i: np.ndarray, depth_j: np.ndarray, K: np.ndarray, T_i_j: np.ndarray,
                  tol: float = 0.1, stride: int = 4) -> float:
    """Fraction of depth ``j``'s pixels seen by camera ``i`` at a consistent depth.

    ``depth_i``, ``depth_j``: ``(H, W)`` metres from cameras with intrinsics ``K``;
    ``T_i_j`` maps camera ``j`` points into camera ``i``. Every ``stride``-th row and column
    of ``depth_j`` is tested. Returns a float in [0, 1] (0 when depth ``j`` is empty).
    """
    sub = np.zeros_like(depth_j)
    sub[::stride, ::stride] = depth_j[::stride, ::stride]
    pts, _ = cameras.backproject(sub, K)
    if len(pts) == 0:
        return 0.0
    uv, z = cameras.project(cameras.transform(T_i_j, pts), K)
    H, W = depth_i.shape
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    d = np.zeros(len(pts))
    d[inside] = depth_i[v[inside].astype(int), u[inside].astype(int)]
    seen = inside & (d > 0) & (np.abs(d - z) < tol)
    return float(seen.sum() / len(pts))


class ScanNet(PairSource):
    """ScanNet scenes in the ``SensReader`` export layout (module docstring).

    Args:
        root: folder with one sub-folder per scene (e.g. ``scene0707_00``).
        min_overlap, frame_step, max_gap, overlap_tol: the pair rule (module docstring).
        voxel: when set, the cloud is voxel-downsampled to this size in metres (the paper's
            text: 3 cm); default None, the back-projection of the depth map as the official
            code uses it (module docstring).
        pair_list: where the pair list is kept; default
            ``<root>/freereg_pairs_overlap<o>_step<s>_gap<g>.txt``.
    """

    dataset = "scannet"

    def __init__(self, root, min_overlap: float = 0.3, frame_step: int = 20, max_gap: int = 100,
                 overlap_tol: float = 0.1, voxel: float | None = None, pair_list=None):
        self.root = require(root, "ScanNet root folder", LAYOUT)
        self.min_overlap, self.frame_step, self.max_gap = min_overlap, frame_step, max_gap
        self.overlap_tol, self.voxel = overlap_tol, voxel
        self.rule = (f"overlap > {min_overlap:g} (tolerance {overlap_tol:g} m; every {frame_step}th "
                     f"frame; at most {max_gap} frames apart)")
        self.pair_list_path = Path(pair_list) if pair_list else (
            self.root / f"freereg_pairs_overlap{min_overlap:g}_step{frame_step}_gap{max_gap}.txt")
        self._intrinsics: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def scenes(self) -> list[str]:
        """Scene folder names (those with a ``color/`` folder), sorted."""
        found = sorted(p.parent.name for p in self.root.glob("*/color") if p.is_dir())
        if not found:
            raise FileNotFoundError(f"no <scene>/color/ folder under {self.root}\nexpected layout:\n{LAYOUT}")
        return found

    def _path(self, scene: str, sub: str, name: str, what: str) -> Path:
        return require(self.root / scene / sub / name, what, LAYOUT)

    def intrinsics(self, scene: str) -> tuple[np.ndarray, np.ndarray]:
        """``(K_color, K_depth)``, each ``(3, 3)`` (read once per scene)."""
        if scene in self._intrinsics:
            return self._intrinsics[scene]
        out = []
        for cam in ("color", "depth"):
            path = self._path(scene, "intrinsic", f"intrinsic_{cam}.txt", f"{cam} intrinsics")
            try:
                M = np.loadtxt(path, ndmin=2)
            except ValueError as exc:
                raise ValueError(f"cannot read {path} as a matrix of numbers: {exc}") from None
            if M.shape not in ((4, 4), (3, 3)):
                raise ValueError(f"{path}: expected a 4 x 4 (or 3 x 3) matrix, got shape {M.shape}")
            out.append(cameras.check_intrinsics(M[:3, :3], None, str(path)))
        self._intrinsics[scene] = (out[0], out[1])
        return self._intrinsics[scene]

    def pose(self, scene: str, frame: str) -> np.ndarray:
        """``T_world_cam (4, 4)``; NaN / inf entries where ScanNet lost tracking."""
        path = self._path(scene, "pose", f"{frame}.txt", "pose file")
        try:
            T = np.loadtxt(path, ndmin=2)
        except ValueError as exc:
            raise ValueError(f"cannot read {path} as a 4 x 4 pose of numbers: {exc}") from None
        if T.shape != (4, 4):
            raise ValueError(f"{path}: expected a 4 x 4 pose, got shape {T.shape}")
        return checked_pose(T, path, INDOOR_MAX_TRANSLATION) if np.all(np.isfinite(T)) else T

    def depth(self, scene: str, frame: str) -> np.ndarray:
        """Depth of ``frame`` in metres (0 = hole, 65535 included)."""
        return read_depth(self._path(scene, "depth", f"{frame}.png", "depth image"), 1000.0, INVALID_DEPTH,
                          INDOOR_DEPTH_RANGE)

    def frames(self, scene: str) -> list[str]:
        """Frames with a colour image, a depth image and a finite pose, in numeric order."""
        names = sorted((p.stem for p in (self.root / scene / "color").glob("*.jpg")), key=int)
        return [f for f in names if (self.root / scene / "depth" / f"{f}.png").is_file()
                and np.all(np.isfinite(self.pose(scene, f)))]

    def pair_list(self) -> list[PairEntry]:
        """The fixed pair list; built on first use (reads every sampled depth frame once)."""
        return load_or_build(self.pair_list_path, self.dataset, self.rule, str(self.root), self._build)

    def _build(self) -> list[PairEntry]:

        entries = []
        for scene in tqdm(self.scenes(), desc="ScanNet overlaps"):
            _, K_depth = self.intrinsics(scene)
            frames = self.frames(scene)[:: self.frame_step]
            depths = {f: self.depth(scene, f) for f in frames}
            poses = {f: self.pose(scene, f) for f in frames}
            for a, i in enumerate(frames):
                for j in frames[a + 1:]:
                    if int(j) - int(i) > self.max_gap:
                        break
                    T_i_j = cameras.invert(poses[i]) @ poses[j]
                    o = frame_overlap(depths[i], depths[j], K_depth, T_i_j, self.overlap_tol)
                    if o > self.min_overlap:
                        entries.append(PairEntry(scene, i, j, o))
        return entries

    def pair(self, entry: PairEntry) -> Pair:
        """RGB of ``entry.image_frame`` against the cloud of depth frame ``entry.cloud_frame``."""
        s, i, j = entry.scene, entry.image_frame, entry.cloud_frame
        K_color, K_depth = self.intrinsics(s)
        image = read_rgb(self._path(s, "color", f"{i}.jpg", "colour image"))
        intr = self.root / s / "intrinsic"
        cameras.check_intrinsics(K_color, image.shape[:2], str(intr / "intrinsic_color.txt"))
        depth_j = self.depth(s, j)
        cameras.check_intrinsics(K_depth, depth_j.shape, str(intr / "intrinsic_depth.txt"))
        points = cameras.backproject(depth_j, K_depth)[0]
        if self.voxel:
            points = voxel_downsample(points, self.voxel)
        T_i, T_j = self.pose(s, i), self.pose(s, j)
        if not (np.all(np.isfinite(T_i)) and np.all(np.isfinite(T_j))):
            raise ValueError(f"{s}: frame {i} or {j} has no valid pose (ScanNet lost tracking there)")
        return Pair(
            image=image, K_image=K_color.copy(), points=points, K_depth=K_depth.copy(),
            depth_size=depth_j.shape, T_pc_sensor=np.eye(4), T_cam_pc=cameras.invert(T_i) @ T_j,
            depth_gt=depth_in_image(self.depth(s, i), K_depth, K_color, image.shape[:2]),
            sensor_depth=depth_j, name=f"scannet/{entry.key}",
            meta={"dataset": "scannet", "scene": s, "frame_image": i, "frame_cloud": j,
                  "overlap": entry.score, "outdoor": False},
        )
