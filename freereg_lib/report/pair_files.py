"""A pair written as files, the way a user brings one (notebook 05's and the tests' inputs to
``freereg register``); re-exported by :mod:`freereg_lib.pipeline.register`."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np

from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras


def write_ply(path: str | Path, points: np.ndarray) -> Path:
    """``points (N, 3)`` as a binary little-endian ``.ply``: float64 (``double``) x, y, z for a
    float64 cloud, float32 (``float``) otherwise. The input's precision is kept because a cloud
    far from its origin (UTM, thousands of km) loses decimetres in float32 and then fails."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    wide = np.asarray(points).dtype == np.float64
    pts = np.ascontiguousarray(points, dtype="<f8" if wide else "<f4")
    kind = "double" if wide else "float"
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty {kind} x\n"
              f"property {kind} y\nproperty {kind} z\nend_header\n")
    path.write_bytes(header.encode() + pts.tobytes())
    return path


def _write_image_and_depth(pair: Pair, image_path: Path, depth_path: Path | None) -> None:

    image_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(image_path), cv2.cvtColor(pair.image, cv2.COLOR_RGB2BGR))
    if depth_path is not None and pair.depth_gt is not None:
        depth_path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(depth_path), np.clip(np.round(pair.depth_gt * 1000), 0, 65534).astype(np.uint16))


def write_demo_layout(pair: Pair, root: str | Path) -> Path:
    """``pair`` in the official demo layout (:mod:`freereg_lib.data.datasets.demo`): the cloud in its
    sensor's frame (``T_pc_sensor`` applied), the image, ``intrinsics.json``, and the ground
    truth under ``just_for_eval/`` (the true depth in millimetres)."""
    root = Path(root)
    (root / "just_for_eval").mkdir(parents=True, exist_ok=True)
    _write_image_and_depth(pair, root / "source_rgb.png", root / "just_for_eval" / "source_rgb.gtd.png")
    write_ply(root / "target_pc.ply", cameras.transform(cameras.invert(pair.T_pc_sensor), pair.points))
    (H, W), (Hd, Wd) = pair.image_size, pair.depth_size
    (root / "intrinsics.json").write_text(json.dumps({
        "rgb_intrinsic": np.asarray(pair.K_image).tolist(), "dpt_intrinsic": np.asarray(pair.K_depth).tolist(),
        "rgb_size": [W, H], "dpt_size": [Wd, Hd], "dpt_scale": 1000.0}, indent=1))
    # rgb2pc: the RGB camera in the cloud's (sensor's) frame.
    np.savetxt(root / "just_for_eval" / "rgb2pc.gt.pose.txt", cameras.invert(pair.T_cam_pc @ pair.T_pc_sensor))
    return root


def write_user_files(pair: Pair, folder: str | Path, T_world_pc: np.ndarray | None = None) -> dict[str, Path]:
    """``pair`` as a user would bring it: ``image.png``, ``cloud.ply`` (in a frame of your choice,
    ``T_world_pc`` applied to the pair's cloud; **no** sensor pose), ``intrinsics.json`` (fx, fy,
    cx, cy), ``image_depth.png`` (mm) and ``gt_T_pc_cam.txt`` (the camera's pose in the cloud's
    new frame). Returns the paths by name."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    T = np.eye(4) if T_world_pc is None else np.asarray(T_world_pc, dtype=np.float64)
    paths = {"image": folder / "image.png", "cloud": folder / "cloud.ply", "intrinsics": folder / "intrinsics.json",
             "image_depth": folder / "image_depth.png", "gt_T_pc_cam": folder / "gt_T_pc_cam.txt"}
    _write_image_and_depth(pair, paths["image"], paths["image_depth"])
    write_ply(paths["cloud"], cameras.transform(T, pair.points))
    K = np.asarray(pair.K_image)
    paths["intrinsics"].write_text(json.dumps({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}))
    np.savetxt(paths["gt_T_pc_cam"], T @ cameras.invert(pair.T_cam_pc))
    if pair.depth_gt is None:
        del paths["image_depth"]
    return paths


def downscale_pair(pair: Pair, factor: float = 0.5, seed: int = 0) -> Pair:
    """A smaller copy of ``pair`` for quick runs: image, true depth and depth camera scaled by
    ``factor`` (intrinsics with them), the cloud randomly thinned to ``factor**2`` of its points."""

    H, W = pair.image_size
    h, w = max(1, round(H * factor)), max(1, round(W * factor))
    Hd, Wd = pair.depth_size
    hd, wd = max(1, round(Hd * factor)), max(1, round(Wd * factor))
    keep = np.sort(np.random.default_rng(seed).choice(len(pair.points), max(1, int(len(pair.points) * factor ** 2)),
                                                      replace=False))
    return dataclasses.replace(
        pair, image=cv2.resize(pair.image, (w, h), interpolation=cv2.INTER_AREA),
        K_image=cameras.scale_intrinsics(pair.K_image, w / W, h / H), points=pair.points[keep],
        K_depth=cameras.scale_intrinsics(pair.K_depth, wd / Wd, hd / Hd), depth_size=(hd, wd),
        depth_gt=None if pair.depth_gt is None else cv2.resize(pair.depth_gt, (w, h), interpolation=cv2.INTER_NEAREST),
        sensor_depth=None, image_ids=None, point_ids=None, meta=dict(pair.meta))
