"""The embedded real sample: ICL-NUIM living room 1 (CC BY 3.0, see its README).

22 rendered RGB-D frames (0, 10, ..., 210) with ground-truth poses. A pair is the colour
image of frame ``i`` and the depth of frame ``j`` back-projected to a point cloud in
camera ``j``'s frame, so ``T_cam_pc = inv(T_world_i) @ T_world_j``. Frame ``j``'s depth is
the pair's ``sensor_depth``: sensor RGB-D frames are used as they are, as the official code
uses 3DMatch's (``config_for("icl")`` densifies nothing).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from freereg_lib.data.datasets.common import INDOOR_DEPTH_RANGE, read_depth, read_redwood_log, read_rgb
from freereg_lib.data.pair import Pair, load_or_record
from freereg_lib.geometry import cameras

ICL_ROOT = Path(__file__).resolve().parent.parent / "icl_livingroom"
# Real Kinect v1 frames of an office desk in the same layout (TUM RGB-D fr1_rpy, undistorted; its README).
TUM_ROOT = Path(__file__).resolve().parent.parent / "tum_fr1_rpy"


class ICLSample:
    """Reader of the ICL folder (colour/, depth/, trajectory.log, intrinsics.json), or of any folder in
    its layout (``TUM_ROOT``); a ``trajectory_depth.log`` beside it gives the depth frames' own
    poses (a sensor that takes depth and colour at different instants)."""

    def __init__(self, root: str | Path = ICL_ROOT):
        self.root = Path(root)
        self.prefix = "icl" if self.root.resolve() == ICL_ROOT else self.root.name  # of the pairs' names
        intr_path = self.root / "intrinsics.json"
        if not intr_path.is_file():
            raise FileNotFoundError(f"missing {intr_path}: is {self.root} an ICL sample folder?")
        intr = json.loads(intr_path.read_text())
        keys = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
        missing = [k for k in keys if k not in intr]
        if missing:
            raise ValueError(f"{intr_path}: missing key(s) {missing}; expected {list(keys)}")
        self.size = (int(intr["height"]), int(intr["width"]))
        self.K = cameras.check_intrinsics(cameras.intrinsics(intr["fx"], intr["fy"], intr["cx"], intr["cy"]),
                                          self.size, str(intr_path))
        self.depth_scale = float(intr["depth_scale"])
        self.poses = read_redwood_log(self.root / "trajectory.log")
        depth_log = self.root / "trajectory_depth.log"
        self.depth_poses = read_redwood_log(depth_log) if depth_log.is_file() else self.poses
        self.frames = sorted(int(p.stem) for p in (self.root / "color").glob("*.jpg"))
        missing = sorted(set(self.frames) - set(self.poses))
        if missing:
            raise ValueError(f"{self.root}: frames {missing} have images but no pose in trajectory.log")

    def pose(self, frame: int, depth: bool = False) -> np.ndarray:
        """``T_world_cam (4, 4)`` of ``frame`` (of its depth image with ``depth``), its rotation
        re-orthonormalised.

        The .log stores 8 decimals, so the raw rotation is off orthonormal by ~1e-7, enough
        to read an identical pose as a 0.006 deg error.
        """
        T = (self.depth_poses if depth else self.poses)[frame].copy()
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        return T

    def rgb(self, frame: int) -> np.ndarray:
        return read_rgb(self.root / "color" / f"{frame:05d}.jpg")

    def depth(self, frame: int) -> np.ndarray:
        return read_depth(self.root / "depth" / f"{frame:05d}.png", self.depth_scale, expected=INDOOR_DEPTH_RANGE)

    def pair(self, i: int, j: int) -> Pair:
        """RGB of frame ``i`` against the point cloud of frame ``j``."""
        depth_j = self.depth(j)
        points, _ = cameras.backproject(depth_j, self.K)
        if len(points) == 0:
            raise ValueError(f"{self.root / 'depth' / f'{j:05d}.png'} has no valid pixel (all zero): "
                             f"the point cloud of frame {j} would be empty")
        return Pair(
            image=self.rgb(i),
            K_image=self.K.copy(),
            points=points,
            K_depth=self.K.copy(),
            depth_size=self.size,
            T_pc_sensor=np.eye(4),
            T_cam_pc=cameras.invert(self.pose(i)) @ self.pose(j, depth=True),
            depth_gt=self.depth(i),
            sensor_depth=depth_j,
            name=f"{self.prefix}/{i:05d}-{j:05d}",
            meta={"dataset": "icl", "frame_image": i, "frame_cloud": j},
        )

    def pair_list(self, max_gap: int = 40, min_gap: int = 10) -> list[tuple[int, int]]:
        """Frame pairs ``(i, j)`` with ``min_gap <= j - i <= max_gap`` (frame numbers)."""
        return [(i, j) for i in self.frames for j in self.frames if min_gap <= j - i <= max_gap]

    def pairs(self, n: int | None = None, max_gap: int = 40):
        """Yield up to ``n`` pairs in a fixed order.

        A pair whose files cannot be read comes as an
        :class:`~freereg_lib.data.pair.UnreadablePair` holding the error, so a benchmark records
        it and goes on (``self.pair(i, j)`` raises it directly).
        """
        for k, (i, j) in enumerate(self.pair_list(max_gap=max_gap)):
            if n is not None and k >= n:
                return
            yield load_or_record(f"icl/{i:05d}-{j:05d}", self.pair, i, j)
