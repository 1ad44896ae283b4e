"""The official FreeReg demo: one RGB image against one point cloud.

Layout (the official repository's ``data/demo/``; also the way to bring one's own pair)::

    <root>/source_rgb.png                      the RGB image
    <root>/target_pc.ply                       the point cloud, in the frame of its depth sensor
    <root>/intrinsics.json                     optional, the cameras (default: the demo's own)
    <root>/just_for_eval/rgb2pc.gt.pose.txt    4 x 4 ground truth, RGB camera -> cloud frame
    <root>/just_for_eval/source_rgb.gtd.png    optional: true depth of the RGB, millimetres
    <root>/just_for_eval/target_dpt.gtd.png    optional: true dense depth of the depth camera, millimetres

``intrinsics.json`` uses the names of the official ``config/demo.yaml``:
``{"rgb_intrinsic": 3 x 3, "dpt_intrinsic": 3 x 3, "rgb_size": [W, H], "dpt_size": [W, H],
"dpt_scale": 1000.0}``; without it the demo's ScanNet cameras are used (RGB 1296 x 968,
depth 640 x 480). A key it leaves out keeps the demo's value; an unknown or misspelt key is
refused (naming the file, the key and the expected keys) rather than ignored, and the
intrinsics must fit their sizes (in pixels, not normalised). The cloud is projected on a depth camera at the cloud frame's origin
(the official demo projects with an identity extrinsic). The pose file maps RGB-camera
points into the cloud frame, so :class:`~freereg_lib.data.pair.Pair`'s ``T_cam_pc`` is its
inverse. Without ``source_rgb.gtd.png`` the pair has no ``depth_gt`` (it can be
registered, not scored); its value 65535 is a hole, and a median outside 0.1..20 m is
refused (units). ``target_dpt.gtd.png`` (dpt_size) is the depth side's truth, the pair's
``depth_frame_gt``, as the official demo scores it (not the sparse projection of the cloud,
which covers ~6 % of the pixels); without it the densified projection is the truth. ``config_for("demo")`` is the official ``config/demo.yaml``'s setting (the
ScanNet one: indoor, depth up to 15 m).
"""
from __future__ import annotations

import difflib
import json
from pathlib import Path

import numpy as np

from freereg_lib.data.datasets.common import (
    INDOOR_DEPTH_RANGE,
    INDOOR_MAX_TRANSLATION,
    INVALID_DEPTH,
    read_depth,
    read_pose_txt,
    read_rgb,
)
from freereg_lib.data.datasets.common import read_ply_points as read_ply_vertices
from freereg_lib.data.datasets.pairlists import PairEntry, PairSource, require
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras

LAYOUT = __doc__.split("::\n\n", 1)[1].split("\n\n", 1)[0]
# config/demo.yaml of the official code (ScanNet's cameras); sizes are [W, H] there.
DEMO_CAMERAS = {
    "rgb_intrinsic": [[1163.45, 0, 635.626], [0, 1164.79, 481.600], [0, 0, 1]],
    "dpt_intrinsic": [[574.541, 0, 322.522], [0, 577.584, 238.559], [0, 0, 1]],
    "rgb_size": [1296, 968],
    "dpt_size": [640, 480],
    "dpt_scale": 1000.0,
}


def read_ply_points(path: str | Path) -> np.ndarray:
    """The ``x y z`` of the vertices of a ``.ply`` file, ``(N, 3) float64``
    (:func:`freereg_lib.data.datasets.common.read_ply_points`); a missing file names the demo's layout."""
    return read_ply_vertices(require(path, "point cloud", LAYOUT))


def read_cameras(path: str | Path) -> dict:
    """The cameras of an ``intrinsics.json`` (module docstring) over the demo's own.

    Refused with a ``ValueError`` naming the file: not JSON, not an object, an unknown key
    (with the nearest known key and the expected keys), a matrix that is not 3 x 3 numbers, a
    size that is not ``[W, H]`` positive integers, a ``dpt_scale`` that is not a positive number.
    """

    path = Path(path)
    try:
        given = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(given, dict):
        raise ValueError(f"{path} must hold a JSON object with the keys {sorted(DEMO_CAMERAS)}")
    unknown = sorted(set(given) - set(DEMO_CAMERAS))
    if unknown:
        near = {k: difflib.get_close_matches(k, list(DEMO_CAMERAS), n=1) for k in unknown}
        hints = "; ".join(f"{k!r}: did you mean {v[0]!r}?" for k, v in near.items() if v)
        raise ValueError(f"{path}: unknown key(s) {unknown}" + (f" ({hints})" if hints else "")
                         + f"; expected keys: {sorted(DEMO_CAMERAS)} (a key left out keeps the demo's value)")
    cams = {**DEMO_CAMERAS, **given}
    for key in ("rgb_intrinsic", "dpt_intrinsic"):
        try:
            K = np.asarray(cams[key], dtype=np.float64)
        except (TypeError, ValueError):
            K = np.zeros(0)
        if K.shape != (3, 3):
            raise ValueError(f"{path}: {key} must be a 3 x 3 matrix of numbers [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "
                             f"got {cams[key]!r}")
        cams[key] = K
    for key in ("rgb_size", "dpt_size"):
        v = cams[key]
        if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, int) and x > 0 for x in v)):
            raise ValueError(f"{path}: {key} must be [W, H], two positive integers (width first, as the "
                             f"official config/demo.yaml), got {v!r}")
    if not (isinstance(cams["dpt_scale"], (int, float)) and cams["dpt_scale"] > 0):
        raise ValueError(f"{path}: dpt_scale must be a positive number (depth PNG value per metre), "
                         f"got {cams['dpt_scale']!r}")
    return cams


def load_demo_pair(root: str | Path) -> Pair:
    """The demo pair of ``root`` (layout in the module docstring)."""
    root = require(root, "demo folder", LAYOUT)
    intr_path = root / "intrinsics.json"
    cams = read_cameras(intr_path) if intr_path.is_file() else dict(DEMO_CAMERAS)
    where = intr_path if intr_path.is_file() else "the demo's default cameras"
    (w_rgb, h_rgb), (w_dpt, h_dpt) = cams["rgb_size"], cams["dpt_size"]
    for key, K, (w, h) in (("rgb_size", cams["rgb_intrinsic"], (w_rgb, h_rgb)), ("dpt_size", cams["dpt_intrinsic"], (w_dpt, h_dpt))):
        try:
            cameras.check_size_order(K, (h, w), key, key.replace("size", "intrinsic"))
        except ValueError:
            raise ValueError(f"{where}: {key} is [W, H] (width first, as the official config/demo.yaml), you gave "
                             f"[H, W]? {key} = {[w, h]} puts the image centre at ({(w - 1) / 2:g}, {(h - 1) / 2:g}), "
                             f"far from the principal point of its intrinsics; {[h, w]} fits it") from None
    K_rgb = cameras.check_intrinsics(cams["rgb_intrinsic"], (h_rgb, w_rgb), f"rgb_intrinsic of {where}")
    K_dpt = cameras.check_intrinsics(cams["dpt_intrinsic"], (h_dpt, w_dpt), f"dpt_intrinsic of {where}")
    image_path = require(root / "source_rgb.png", "RGB image", LAYOUT)
    image = read_rgb(image_path)
    if image.shape[:2] != (h_rgb, w_rgb):
        raise ValueError(f"{image_path} is {image.shape[1]} x {image.shape[0]}, but rgb_size is "
                         f"{w_rgb} x {h_rgb}; give the image's cameras in {root / 'intrinsics.json'}")
    T_pc_cam = read_pose_txt(require(root / "just_for_eval" / "rgb2pc.gt.pose.txt", "ground-truth pose", LAYOUT),
                             INDOOR_MAX_TRANSLATION)
    gtd = root / "just_for_eval" / "source_rgb.gtd.png"
    depth_gt = None
    if gtd.is_file():
        depth_gt = read_depth(gtd, float(cams["dpt_scale"]), INVALID_DEPTH, INDOOR_DEPTH_RANGE)
        if depth_gt.shape != image.shape[:2]:
            raise ValueError(f"{gtd} is {depth_gt.shape[1]} x {depth_gt.shape[0]}, expected the RGB's "
                             f"{image.shape[1]} x {image.shape[0]}")
    dpt_gtd = root / "just_for_eval" / "target_dpt.gtd.png"
    depth_frame_gt = None
    if dpt_gtd.is_file():
        depth_frame_gt = read_depth(dpt_gtd, float(cams["dpt_scale"]), INVALID_DEPTH, INDOOR_DEPTH_RANGE)
        if depth_frame_gt.shape != (int(h_dpt), int(w_dpt)):
            raise ValueError(f"{dpt_gtd} is {depth_frame_gt.shape[1]} x {depth_frame_gt.shape[0]}, expected the "
                             f"depth camera's {w_dpt} x {h_dpt} (dpt_size)")
    return Pair(
        image=image, K_image=K_rgb, points=read_ply_points(root / "target_pc.ply"), K_depth=K_dpt,
        depth_size=(int(h_dpt), int(w_dpt)), T_pc_sensor=np.eye(4),
        T_cam_pc=cameras.invert(T_pc_cam),
        depth_gt=depth_gt, depth_frame_gt=depth_frame_gt,
        name="demo/source_rgb-target_pc",
        meta={"dataset": "demo", "outdoor": False},
    )


class FreeRegDemo(PairSource):
    """The demo as a one-pair dataset, so it runs wherever a dataset name is accepted."""

    dataset = "demo"

    def __init__(self, root: str | Path):
        self.root = require(root, "demo folder", LAYOUT)

    def pair_list(self) -> list[PairEntry]:
        return [PairEntry("demo", "source_rgb", "target_pc", float("nan"))]

    def pair(self, entry: PairEntry) -> Pair:
        return load_demo_pair(self.root)
