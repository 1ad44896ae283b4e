"""KITTI-DC: the left colour camera against the 64-line Velodyne, from KITTI raw drives.

KITTI depth completion is built on KITTI raw drives; this loader reads the raw
"synced + rectified" drives and their calibration (what the KITTI raw download script
unpacks), one folder per recording day::

    <root>/<date>/calib_cam_to_cam.txt                      P_rect_02 (3 x 4), R_rect_00 (3 x 3)
    <root>/<date>/calib_velo_to_cam.txt                     R (3 x 3), T (3): Velodyne -> camera 0
    <root>/<date>/calib_imu_to_velo.txt                     R (3 x 3), T (3): IMU -> Velodyne
    <root>/<date>/<drive>/image_02/data/<frame>.png         left colour camera, rectified
    <root>/<date>/<drive>/velodyne_points/data/<frame>.bin  float32 rows x y z reflectance
    <root>/<date>/<drive>/oxts/data/<frame>.txt             GPS/IMU: lat lon alt roll pitch yaw ...

``<date>`` is e.g. ``2011_09_26``, ``<drive>`` ``2011_09_26_drive_0002_sync``, ``<frame>``
ten digits. What is read:

* camera 2 from the Velodyne: ``T_cam2_velo = [I | t2] @ R_rect_00 @ [R | T]`` with
  ``K2 = P_rect_02[:, :3]`` and ``t2 = inv(K2) @ P_rect_02[:, 3]`` (the rectified camera 2
  sits ``t2`` from rectified camera 0);
* poses from OXTS as in the KITTI raw devkit (``convertOxtsToPose``): Mercator
  ``x = s * er * lon``, ``y = s * er * log(tan(pi/4 + lat/2))``, ``z = alt`` with
  ``er = 6378137`` m and ``s = cos(lat of the drive's first frame)``, rotation
  ``Rz(yaw) Ry(pitch) Rx(roll)``; that is ``T_world_imu``, and
  ``T_world_velo = T_world_imu @ inv(T_velo_imu)``;
* the image loses its top 150 rows (sky, no LiDAR), as in the official code, and ``cy``
  shifts by 150.

A pair is image ``i`` against the Velodyne scan ``j`` (in Velodyne frame ``j``), seen by a
depth camera placed at camera 2 of frame ``j`` with the image's intrinsics;
``T_cam_pc = T_cam2_velo @ inv(T_world_velo_i) @ T_world_velo_j``. Pairs: every
``frame_step``-th frame of each drive, ``i < j``, LiDAR centres less than 10 m apart. The
image's true depth is scan ``i`` projected into camera 2 and densified with IP-Basic's
multi-scale fill, as the official evaluation does. The pair's ``sensor_depth`` (the depth
frame's own sensor depth) is scan ``j`` projected onto the depth camera (camera 2 of frame
``j``) with :func:`~freereg_lib.geometry.projection.project_to_depth`, sparse (0 = no LiDAR return;
the pipeline densifies it per ``cfg.densify``): KITTI raw has no per-frame LiDAR depth map
of its own (KITTI-DC's ``velodyne_raw`` maps are this projection), so the loader builds it
from the 360-degree scan, keeping the points in front of the camera (0.1 m and beyond). The
paper's 342 pairs (4 scenes) come with the official FreeReg data, which this loader does
not read.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from freereg_lib.data.datasets.common import read_rgb
from freereg_lib.data.datasets.pairlists import PairEntry, PairSource, load_or_build, require
from freereg_lib.data.pair import Pair
from freereg_lib.geometry import cameras, densify, projection

LAYOUT = __doc__.split("::\n\n", 1)[1].split("\n\n", 1)[0]
EARTH_RADIUS = 6378137.0


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """A KITTI calibration file: ``key: numbers`` lines (non-numeric lines are skipped)."""
    out = {}
    for line in require(path, "calibration file", LAYOUT).read_text().splitlines():
        key, _, value = line.partition(":")
        try:
            out[key.strip()] = np.array(value.split(), dtype=np.float64)
        except ValueError:  # e.g. "calib_time: 09-Jan-2012 13:57:47"
            continue
    return out


def _entry(calib: dict, key: str, size: int, path: Path) -> np.ndarray:
    if key not in calib or calib[key].size != size:
        raise ValueError(f"{path}: expected an entry '{key}:' with {size} numbers")
    return calib[key]


def _oxts_row(path: Path) -> np.ndarray:
    """The first 6 numbers (lat, lon, alt, roll, pitch, yaw) of an OXTS file; errors name the file."""
    try:
        row = np.loadtxt(path, ndmin=1)
    except ValueError as exc:
        raise ValueError(f"cannot read {path} as an OXTS row of numbers: {exc}") from None
    if row.ndim != 1 or row.size < 6 or not np.all(np.isfinite(row[:6])):
        raise ValueError(f"{path}: expected one row of at least 6 finite numbers (lat lon alt roll pitch yaw ...)")
    return row[:6]


def oxts_poses(rows: np.ndarray) -> np.ndarray:
    """``T_world_imu (F, 4, 4)`` of OXTS rows ``(F, >= 6)`` (lat, lon in degrees, alt, roll,
    pitch, yaw in radians), with the Mercator scale of the first row (module docstring)."""
    lat, lon, alt = np.radians(rows[:, 0]), np.radians(rows[:, 1]), rows[:, 2]
    scale = np.cos(lat[0])
    t = np.stack([scale * EARTH_RADIUS * lon, scale * EARTH_RADIUS * np.log(np.tan(np.pi / 4 + lat / 2)), alt], axis=1)
    poses = np.empty((len(rows), 4, 4))
    for k, (roll, pitch, yaw) in enumerate(rows[:, 3:6]):
        R = (cameras.rotation_about([0, 0, 1], yaw) @ cameras.rotation_about([0, 1, 0], pitch)
             @ cameras.rotation_about([1, 0, 0], roll))
        poses[k] = cameras.make_pose(R, t[k])
    return poses


class KittiDC(PairSource):
    """KITTI raw drives in the layout of the module docstring.

    Args:
        root: folder of the ``<date>`` folders.
        max_distance: pairs are kept when their LiDAR centres are closer than this (m).
        frame_step: use every ``frame_step``-th frame of a drive (10 Hz recording).
        top_crop: image rows removed at the top (the official code: 150).
        pair_list: where the pair list is kept; default
            ``<root>/freereg_pairs_dist<max_distance>_step<frame_step>.txt``.
    """

    dataset = "kitti"

    def __init__(self, root, max_distance: float = 10.0, frame_step: int = 5, top_crop: int = 150, pair_list=None):
        self.root = require(root, "KITTI root folder", LAYOUT)
        self.max_distance, self.frame_step, self.top_crop = max_distance, frame_step, top_crop
        self.rule = f"distance < {max_distance:g} m (every {frame_step}th frame)"
        self.pair_list_path = Path(pair_list) if pair_list else (
            self.root / f"freereg_pairs_dist{max_distance:g}_step{frame_step}.txt")
        self._poses: dict[str, dict[str, np.ndarray]] = {}
        self._calib: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def drives(self) -> list[str]:
        """``<date>/<drive>`` of every drive with an ``image_02/data`` folder, sorted."""
        found = sorted(f"{p.parents[2].name}/{p.parents[1].name}" for p in self.root.glob("*/*/image_02/data"))
        if not found:
            raise FileNotFoundError(f"no <date>/<drive>/image_02/data/ under {self.root}\nexpected layout:\n{LAYOUT}")
        return found

    def calibration(self, date: str) -> tuple[np.ndarray, np.ndarray]:
        """``(T_cam2_velo (4, 4), K2 (3, 3))`` of a recording day (before cropping)."""
        if date not in self._calib:
            cam_path = self.root / date / "calib_cam_to_cam.txt"
            velo_path = self.root / date / "calib_velo_to_cam.txt"
            cam, velo = read_calib(cam_path), read_calib(velo_path)
            P2 = _entry(cam, "P_rect_02", 12, cam_path).reshape(3, 4)
            R_rect = cameras.make_pose(_entry(cam, "R_rect_00", 9, cam_path).reshape(3, 3), np.zeros(3))
            T_cam0_velo = cameras.make_pose(_entry(velo, "R", 9, velo_path).reshape(3, 3),
                                            _entry(velo, "T", 3, velo_path))
            K2 = P2[:, :3].copy()
            T_cam2_rect0 = cameras.make_pose(np.eye(3), np.linalg.solve(K2, P2[:, 3]))
            self._calib[date] = (T_cam2_rect0 @ R_rect @ T_cam0_velo, K2)
        return self._calib[date]

    def poses(self, drive: str) -> dict[str, np.ndarray]:
        """``{frame: T_world_velo (4, 4)}`` of every frame of ``drive`` with an OXTS file."""
        if drive not in self._poses:
            date = drive.split("/")[0]
            files = sorted((self.root / drive / "oxts" / "data").glob("*.txt"))
            if not files:
                raise FileNotFoundError(f"no OXTS files in {self.root / drive / 'oxts' / 'data'}\n"
                                        f"expected layout:\n{LAYOUT}")
            rows = np.stack([_oxts_row(f) for f in files])
            imu_path = self.root / date / "calib_imu_to_velo.txt"
            imu = read_calib(imu_path)
            R, T = _entry(imu, "R", 9, imu_path).reshape(3, 3), _entry(imu, "T", 3, imu_path)
            T_velo_imu = cameras.make_pose(R, T)
            T_imu_velo = cameras.invert(T_velo_imu)
            self._poses[drive] = {f.stem: T @ T_imu_velo for f, T in zip(files, oxts_poses(rows))}
        return self._poses[drive]

    def scan(self, drive: str, frame: str) -> np.ndarray:
        """Velodyne points ``(N, 3) float64`` of ``frame`` in its own Velodyne frame."""
        path = require(self.root / drive / "velodyne_points" / "data" / f"{frame}.bin", "Velodyne scan", LAYOUT)
        raw = np.fromfile(path, dtype=np.float32)
        if raw.size % 4:
            raise ValueError(f"{path}: {raw.size} floats, expected rows of 4 (x y z reflectance)")
        return raw.reshape(-1, 4)[:, :3].astype(np.float64)

    def pair_list(self) -> list[PairEntry]:
        """The fixed pair list, built from the OXTS poses on first use."""
        return load_or_build(self.pair_list_path, self.dataset, self.rule, str(self.root), self._build)

    def _build(self) -> list[PairEntry]:
        entries = []
        for drive in self.drives():
            poses = self.poses(drive)
            have = {p.stem for p in (self.root / drive / "velodyne_points" / "data").glob("*.bin")}
            frames = sorted(p.stem for p in (self.root / drive / "image_02" / "data").glob("*.png")
                            if p.stem in have and p.stem in poses)[:: self.frame_step]
            for a, i in enumerate(frames):
                for j in frames[a + 1:]:
                    dist = float(np.linalg.norm(poses[i][:3, 3] - poses[j][:3, 3]))
                    if dist < self.max_distance:
                        entries.append(PairEntry(drive, i, j, dist))
        return entries

    def pair(self, entry: PairEntry) -> Pair:
        """Image ``entry.image_frame`` (cropped) against scan ``entry.cloud_frame``."""

        drive, i, j = entry.scene, entry.image_frame, entry.cloud_frame
        T_cam2_velo, K2 = self.calibration(drive.split("/")[0])
        image = read_rgb(require(self.root / drive / "image_02" / "data" / f"{i}.png", "colour image", LAYOUT))
        image = np.ascontiguousarray(image[self.top_crop:])
        K = K2.copy()
        K[1, 2] -= self.top_crop
        size = image.shape[:2]
        poses = self.poses(drive)
        raw_gt, _ = projection.project_to_depth(self.scan(drive, i), K, T_cam2_velo, size, depth_min=0.1)
        scan_j = self.scan(drive, j)
        sensor_depth, _ = projection.project_to_depth(scan_j, K, T_cam2_velo, size, depth_min=0.1)
        return Pair(
            image=image, K_image=K, points=scan_j, K_depth=K.copy(), depth_size=size,
            T_pc_sensor=cameras.invert(T_cam2_velo),
            T_cam_pc=T_cam2_velo @ cameras.invert(poses[i]) @ poses[j],
            depth_gt=densify.densify(raw_gt, "multiscale"), sensor_depth=sensor_depth,
            name=f"kitti/{entry.key}",
            meta={"dataset": "kitti", "scene": drive, "frame_image": i, "frame_cloud": j,
                  "distance": entry.score, "outdoor": True},
        )


# --------------------------------------------------------------------------------------
# The official FreeReg KITTI-DC data (its dataops/metas.py), for data in that layout.

# config/kitti.yaml of the official code (images pre-cropped to 1242 x 225).
K_OFFICIAL = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 22.8540], [0.0, 0.0, 1.0]])


def official_seq_pairs(n_frames: int, seq_n_pair: int = 4) -> list[tuple[int, int]]:
    """The official sequence pairs of a KITTI drive of ``n_frames``: frame ``i`` against
    ``i + 1 .. i + seq_n_pair - 1`` for ``i < n_frames - seq_n_pair`` (``gen_meta``'s 'seq'
    rule with ``seq_n_pair = 4``: three pairs per frame, the last four frames start none)."""
    return [(i, j) for i in range(n_frames - seq_n_pair) for j in range(i + 1, i + seq_n_pair)]


def trans_gt_for_kitti(gt: np.ndarray) -> np.ndarray:
    """The official ``trans_gt_for_kitti`` on a pair's ``gt = inv(T_j) @ T_i``: rows and columns
    of R permuted ``[0, 2, 1]``, ``t -> [t2, -t1, t0]`` (a copy; the official one works in place)."""
    out = np.array(gt, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3][[0, 2, 1]][:, [0, 2, 1]]
    t = out[:3, 3].copy()
    out[:3, 3] = [t[2], -t[1], t[0]]
    return out
