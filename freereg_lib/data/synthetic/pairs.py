"""Synthetic image-to-point-cloud pairs: :func:`make_pair`, :func:`make_pairs` and
:func:`overlap_ratio`.

The image camera is drawn in an indoor or outdoor scene (:mod:`.indoor`, :mod:`.outdoor`),
then the depth side's pose is resampled until the pair's overlap lies in the requested range;
the cloud is the depth camera's back-projected frame indoors, the LiDAR's returns outdoors,
subsampled to at most ``MAX_POINTS``.
"""
from __future__ import annotations

import functools

import cv2
import numpy as np
from tqdm import tqdm

from freereg_lib.data.pair import Pair
from freereg_lib.data.synthetic.indoor import _indoor_camera, _indoor_scene, _indoor_sensor, _same_pose
from freereg_lib.data.synthetic.outdoor import (
    LIDAR_ELEVATIONS_DEG,
    _depth_view_of_lidar,
    _lidar_dirs,
    _outdoor_camera,
    _outdoor_lidar,
    _outdoor_scene,
)
from freereg_lib.data.synthetic import rooms
from freereg_lib.data.synthetic.render import _Looks
from freereg_lib.data.synthetic.seeds import check_eval_seed
from freereg_lib.geometry.cameras import backproject, intrinsics, invert, project, transform

KINDS = ("indoor", "outdoor")
# The indoor worlds: "blocks", the rooms of 2026-12 that the committed micro models were trained and
# measured in; "rooms", calibrated against real rooms (:mod:`.rooms`).
WORLDS = ("blocks", "rooms")
DEFAULT_IMAGE_SIZE = {"indoor": (480, 640), "outdoor": (256, 832)}
MAX_POINTS = 60_000

# Resampling budget of the depth-side pose; one camera pose may simply see too little.
_CAMERA_TRIES = 6
_SENSOR_TRIES = 60
# Image pixels probed (every _PROBE_STRIDE-th row and column) by the cheap overlap estimate.
_PROBE_STRIDE = 4
# overlap_ratio's depth consistency tolerance, metres: absolute + relative to depth.
_TOL_ABS = 0.05
_TOL_REL = 0.03


def _pixels(points_view: np.ndarray, K: np.ndarray, size: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixels of camera-frame points ``(N, 3)`` in a ``size`` image.

    Returns ``inside (N,) bool`` (in front of the camera and in the image), then the rows,
    columns ``(M,) int64`` and depths ``(M,) float64`` of the ``M`` inside points.
    """
    uv, z = project(points_view, K)
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        inside = (z > 0) & (u >= 0) & (u < size[1]) & (v >= 0) & (v < size[0])
    return inside, v[inside].astype(np.int64), u[inside].astype(np.int64), z[inside]


def _subsample(rng: np.random.Generator, n: int) -> np.ndarray:
    """Sorted indices of at most ``MAX_POINTS`` of ``n`` items (sorted keeps scan order)."""
    if n <= MAX_POINTS:
        return np.arange(n)
    return np.sort(rng.choice(n, MAX_POINTS, replace=False))


def _check_overlap(overlap: tuple[float, float]) -> tuple[float, float]:
    lo, hi = (float(x) for x in overlap)
    if not 0.0 <= lo < hi <= 1.0:
        raise ValueError(f"overlap must be (lo, hi) with 0 <= lo < hi <= 1, got {overlap!r}")
    return lo, hi


def _seed_label(seed) -> str:
    if isinstance(seed, (int, np.integer)):
        return f"seed{int(seed):04d}"
    return "seed" + "-".join(str(int(s)) for s in seed)


def make_pair(
    kind: str = "indoor",
    seed: int | tuple[int, ...] = 0,
    overlap: tuple[float, float] | None = None,
    image_size: tuple[int, int] | None = None,
    depth_camera_image: bool = False,
    appearance_seed: int | tuple[int, ...] | None = None,
    world: str = "blocks",
) -> Pair:
    """One synthetic image-to-point-cloud pair.

    ``kind`` is ``"indoor"`` (a furnished room, a second depth camera gives the cloud) or
    ``"outdoor"`` (a street, a 64-line LiDAR gives a sparse cloud). ``image_size`` is
    ``(H, W)``; ``None`` picks ``DEFAULT_IMAGE_SIZE[kind]``: ``(480, 640)`` indoor,
    ``(256, 832)`` outdoor. The depth-side pose is resampled until
    :func:`overlap_ratio` lies in ``overlap = (lo, hi)``; a ``RuntimeError`` names the range
    when that fails.

    The pair: ``image (H, W, 3) uint8``, ``points (N, 3) float64`` in the world frame
    (N <= ``MAX_POINTS``), ``point_ids (N,) int32``, ``depth_gt (H, W) float64``,
    ``image_ids (H, W) int32``, ``K_image`` and ``K_depth (3, 3)``, ``depth_size = (H, W)``,
    ``T_pc_sensor`` the depth camera in the world, ``T_cam_pc`` the world in the camera.

    ``world`` (indoor only) is ``"blocks"``, the rooms of boxes the committed micro models were
    trained and measured in, or ``"rooms"``, the world calibrated against real rooms (:mod:`.rooms`:
    clutter, hand-held scan pairs). ``overlap=None`` is ``(0.3, 0.8)`` in ``blocks`` and outdoors
    and 3DMatch's protocol, above 0.3, in ``rooms``.

    ``seed`` may also be a tuple of integers (a NumPy seed sequence), as the micro models'
    training pairs are drawn. An integer seed that NumPy would turn into a training stream's
    sequence (its low 32 bits a training tag, :mod:`.seeds`) raises ``TrainingSeedError``.

    ``depth_camera_image=True`` also shades the RGB image the depth camera would have seen,
    ``(H_d, W_d, 3) uint8`` in ``pair.meta["depth_camera_image"]`` (a diagnostic no real
    cloud has: :mod:`freereg_lib.training.diagnose`); the pair is otherwise the same.

    ``appearance_seed`` (indoor only; an integer or, like ``seed``, a tuple of them) draws every
    colour, texture and texture scale from a generator of its own: the same room, poses and cloud, shaded in another colouring from the
    world's prior (a diagnostic of how much of an image its depth map cannot tell).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown synthetic kind {kind!r}; expected one of {KINDS}")
    if world not in WORLDS or (world != "blocks" and kind != "indoor"):
        raise ValueError(f"unknown synthetic world {world!r} for {kind!r}; expected one of {WORLDS} (indoor)")
    lo, hi = _check_overlap(overlap or ((0.3, 1.0) if world == "rooms" else (0.3, 0.8)))
    if isinstance(seed, (int, np.integer)):
        check_eval_seed(seed)  # an integer never draws a training room (tuples are training's own form)
    H, W = image_size if image_size is not None else DEFAULT_IMAGE_SIZE[kind]
    size = (int(H), int(W))
    # Focal lengths of the reference sensors (Kinect-like 525 px at 640 wide; KITTI's
    # 721.5 px at 1242 wide), scaled with the width so the field of view is kept.
    f = 525.0 * W / 640 if kind == "indoor" else 721.5377 * W / 1242
    K = intrinsics(f, f, (W - 1) / 2, (H - 1) / 2)
    rng = np.random.default_rng(seed)
    if appearance_seed is not None and kind != "indoor":
        raise ValueError(f"appearance_seed: only an indoor scene's appearance can be drawn apart from its "
                         f"geometry, not {kind!r}")

    if kind == "indoor":
        redraw = None if appearance_seed is None else np.random.default_rng(appearance_seed)
        scene_of, camera_of, sensor_of = (_indoor_scene, _indoor_camera, _indoor_sensor) if world == "blocks" else (
            rooms._room_scene, rooms._scan_camera, rooms._scan_sensor)
        scene, room = scene_of(rng, _Looks(rng, redraw))
        sample_camera = functools.partial(camera_of, room=room)
        sample_sensor = functools.partial(sensor_of, room=room)
        depth_view = _same_pose  # the sensor is itself the depth camera
    else:
        scene = _outdoor_scene(rng)
        sample_camera = _outdoor_camera
        sample_sensor = _outdoor_lidar
        depth_view = _depth_view_of_lidar

    for _ in range(_CAMERA_TRIES):
        T_world_cam = sample_camera(rng)
        hits, depth_gt, image_ids = scene.camera_view(T_world_cam, K, size)
        image = None  # shaded once a depth-side pose is found
        probe = np.zeros(size, dtype=bool)
        probe[::_PROBE_STRIDE, ::_PROBE_STRIDE] = True
        probe = (probe & (depth_gt > 0)).reshape(-1)
        probe_points = hits.origin + hits.t[probe, None] * hits.dirs[probe]
        if len(probe_points) == 0:
            continue
        for _ in range(_SENSOR_TRIES):
            T_world_sensor = sample_sensor(rng, T_world_cam)
            T_world_depth = depth_view(T_world_sensor)
            # Cheap exact estimate on the probes first; overlap_ratio confirms on the pair.
            seen = _pixels(transform(invert(T_world_depth), probe_points), K, size)[0]
            if kind == "outdoor":  # the LiDAR only sees its elevation fan
                d = transform(invert(T_world_sensor), probe_points[seen])
                el = np.degrees(np.arctan2(d[:, 2], np.linalg.norm(d[:, :2], axis=1)))
                seen[seen] = (el <= LIDAR_ELEVATIONS_DEG[0] + 0.2) & (
                    el >= LIDAR_ELEVATIONS_DEG[-1] - 0.2)
            seen[seen] = scene.visible(T_world_sensor[:3, 3], probe_points[seen])
            if not lo <= seen.mean() <= hi:
                continue
            if kind == "indoor":
                _, sensor_depth, sensor_ids = scene.camera_view(T_world_sensor, K, size)
                points_s, _ = backproject(sensor_depth, K)
                points = transform(T_world_sensor, points_s)
                point_ids = sensor_ids[sensor_depth > 0]
            else:
                lidar_hits = scene.cast(T_world_sensor[:3, 3], _lidar_dirs(T_world_sensor))
                points = lidar_hits.points()
                point_ids = scene.class_id[lidar_hits.part[lidar_hits.hit]]
            keep = _subsample(rng, len(points))
            if image is None:
                image = scene.shade(hits, size)
            pair = Pair(
                image=image,
                K_image=K,
                points=points[keep],
                K_depth=K.copy(),
                depth_size=size,
                T_pc_sensor=T_world_depth,
                T_cam_pc=invert(T_world_cam),
                depth_gt=depth_gt,
                # The cloud samples this depth frame; the official evaluation lifts with the whole frame.
                depth_frame_gt=sensor_depth if kind == "indoor" else None,
                image_ids=image_ids,
                point_ids=point_ids[keep].astype(np.int32),
                name=f"synthetic-{'rooms' if world == 'rooms' else kind}/{_seed_label(seed)}",
                meta={"dataset": "synthetic", "kind": kind, "world": world, "outdoor": kind == "outdoor",
                      "seed": seed, "overlap_range": (lo, hi)},
            )
            ratio = overlap_ratio(pair)
            if lo <= ratio <= hi:
                pair.meta["overlap"] = ratio
                if kind == "outdoor":
                    pair.meta["T_pc_lidar"] = T_world_sensor
                if depth_camera_image:
                    hits_depth, _, _ = scene.camera_view(T_world_depth, pair.K_depth, size)
                    pair.meta["depth_camera_image"] = scene.shade(hits_depth, size)
                return pair
    raise RuntimeError(
        f"synthetic {kind} seed {seed}: no depth-side pose with overlap in [{lo}, {hi}] after "
        f"{_CAMERA_TRIES * _SENSOR_TRIES} tries; widen the overlap range"
    )


def make_pairs(
    n: int, kind: str = "indoor", seed: int = 0, progress: bool = False, **kw
) -> list[Pair]:
    """``n`` pairs; pair ``k`` is ``make_pair(kind, seed=seed * 1_000_003 + k, **kw)``, so
    ``seed=0`` gives seeds ``0 .. n-1`` and distinct ``seed`` values never collide for
    ``n < 1_000_003``."""
    seeds = [seed * 1_000_003 + k for k in range(n)]
    it = tqdm(seeds, desc=f"synthetic {kind}") if progress else seeds
    return [make_pair(kind, seed=s, **kw) for s in it]


def _cloud_depth_envelope(pair: Pair) -> tuple[np.ndarray, np.ndarray]:
    """Per depth-map pixel, the min and max depth ``(H_d, W_d) float32`` of the cloud's points
    projected within a window around it (``inf`` / 0 where none).

    The window half-width is the points' mean pixel spacing, so sparse LiDAR rings and a
    randomly subsampled cloud both cover their surfaces without holes.
    """
    Hd, Wd = pair.depth_size
    _, v, u, z = _pixels(transform(invert(pair.T_pc_sensor), pair.points), pair.K_depth,
                         pair.depth_size)
    zbuf = np.full(Hd * Wd, np.inf)
    np.minimum.at(zbuf, v * Wd + u, z)
    zbuf = zbuf.reshape(Hd, Wd).astype(np.float32)
    occupied = np.isfinite(zbuf)
    n_occ = int(occupied.sum())
    if n_occ == 0:
        return zbuf, np.zeros_like(zbuf)
    span = occupied.any(axis=1).sum() * occupied.any(axis=0).sum()
    r = int(np.clip(np.ceil(np.sqrt(span / n_occ)), 1, 12))
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    zmin = cv2.erode(zbuf, kernel)
    zmax = cv2.dilate(np.where(occupied, zbuf, 0.0).astype(np.float32), kernel)
    return zmin, zmax


def overlap_ratio(pair: Pair) -> float:
    """Fraction of the image's pixels with true depth whose 3D point the depth view sees.

    A pixel's point is seen when it projects inside the depth map and its depth there is
    consistent (within 5 cm + 3 %) with the point cloud's depths projected nearby, i.e. it
    is neither outside the cloud nor hidden behind it. Needs ``pair.depth_gt``.
    """
    if pair.depth_gt is None:
        raise ValueError(f"overlap_ratio needs pair.depth_gt; {pair.name} has none")
    points_cam, _ = backproject(pair.depth_gt, pair.K_image)
    if len(points_cam) == 0:
        return 0.0
    T_sensor_cam = invert(pair.T_pc_sensor) @ invert(pair.T_cam_pc)
    _, v, u, z = _pixels(transform(T_sensor_cam, points_cam), pair.K_depth, pair.depth_size)
    zmin, zmax = _cloud_depth_envelope(pair)
    tol = _TOL_ABS + _TOL_REL * z
    seen = (z >= zmin[v, u] - tol) & (z <= zmax[v, u] + tol)
    return float(seen.sum() / len(points_cam))

