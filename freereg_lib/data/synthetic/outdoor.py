"""The synthetic outdoor world: a street, its image camera and a 64-line rotating LiDAR.

A straight street (road, sidewalks, buildings, parked and moving cars, poles, trees) in the
sun, drawn from the scene's generator; the LiDAR follows KITTI's Velodyne HDL-64 pattern (with
fewer azimuth steps for speed) and its virtual depth camera looks along its x axis.
"""
from __future__ import annotations

import numpy as np

from freereg_lib.data.synthetic.render import _BOX, _CHECKER, _CYLINDER, _NOISE, _SPHERE, _STRIPES, _Part, _part, _Scene
from freereg_lib.geometry.cameras import look_at, make_pose, rotation_about

# LiDAR: an HDL-64-like pattern (KITTI's Velodyne), with fewer azimuth steps for speed.
LIDAR_HEIGHT = 1.73
LIDAR_ELEVATIONS_DEG = np.linspace(2.0, -24.8, 64)
LIDAR_AZIMUTH_STEPS = 1024
CAMERA_HEIGHT_OUTDOOR = 1.65



_STREET_X = (-60.0, 200.0)  # the street runs along world x
_ROAD_HALF = 5.0
_SIDEWALK_OUT = 30.0  # the sidewalk slab reaches under the buildings


def _outdoor_scene(rng: np.random.Generator) -> _Scene:
    u = rng.uniform
    x0, x1 = _STREET_X
    xm, xl = (x0 + x1) / 2, x1 - x0
    parts = [
        _part(rng, _BOX, (xm, 0.0, -0.1), (xl, 2 * _ROAD_HALF, 0.2), "road", (0.32, 0.32, 0.33),
              _NOISE, 0.4, 0.3),
    ]
    for side in (-1, 1):
        w = _SIDEWALK_OUT - _ROAD_HALF
        parts.append(_part(rng, _BOX, (xm, side * (_ROAD_HALF + w / 2), 0.06), (xl, w, 0.12),
                           "sidewalk", (0.62, 0.6, 0.57), _CHECKER, 0.6, 0.12))
    for x in np.arange(x0 + 5, x1 - 5, 10.0):  # dashed centre line
        parts.append(_part(rng, _BOX, (x, 0.0, 0.005), (3.0, 0.15, 0.01), "road",
                           (0.9, 0.9, 0.88), _NOISE, 0.2, 0.1))

    for side in (-1, 1):
        x = x0
        while x < x1:
            w, depth, h = u(8, 22), u(8, 14), u(5, 22)
            y = side * (8.0 + u(0, 1.5) + depth / 2)
            tex = int(rng.integers(0, 3))
            axis = (0, 0, 1) if tex == _STRIPES else (1, 0, 0)
            parts.append(_part(rng, _BOX, (x + w / 2, y, h / 2), (w, depth, h), "building",
                               tuple(u(0.35, 0.85, 3)), tex, u(1.2, 3.0), 0.35, tex_axis=axis))
            x += w + (u(0.5, 4.0) if rng.random() < 0.4 else 0.0)

        x = x0 + u(0, 10)
        while x < x1:  # parked cars
            if rng.random() < 0.55:
                parts += _car(rng, x, side * u(3.6, 4.2), float(rng.normal(0.0, 0.03)))
            x += u(5.5, 12.0)

        x = x0 + u(0, 20)
        while x < x1:
            parts.append(_part(rng, _CYLINDER, (x, side * 5.4, 3.5), (0.18, 0.18, 7.0),
                               "pole", (0.45, 0.45, 0.47), _NOISE, 0.3, 0.2))
            x += u(18, 30)

        x = x0 + u(0, 12)
        while x < x1:
            if rng.random() < 0.6:
                ht, rt, rc = u(2.0, 3.0), u(0.12, 0.2), u(1.2, 2.2)
                y = side * u(6.2, 7.0)
                parts.append(_part(rng, _CYLINDER, (x, y, ht / 2), (2 * rt, 2 * rt, ht), "trunk",
                                   (0.35, 0.25, 0.15), _STRIPES, 0.1, 0.3, tex_axis=(0, 0, 1)))
                parts.append(_part(rng, _SPHERE, (x, y, ht + 0.6 * rc), (2 * rc,) * 3,
                                   "foliage", (0.2, 0.45, 0.15), _NOISE, 0.25, 0.6))
            x += u(8, 16)

    # Moving cars in the lanes, far enough ahead not to sit on the camera or the LiDAR.
    for _ in range(int(rng.integers(0, 4))):
        parts += _car(rng, u(35, 150), float(rng.choice([-2.5, 2.5])), float(rng.normal(0, 0.03)))

    elev, azim = np.radians(u(30, 60)), u(0, 2 * np.pi)
    sun = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    return _Scene(parts, sun=sun, ambient=0.35, key=0.85, haze_m=250.0)


def _car(rng: np.random.Generator, x: float, y: float, yaw: float) -> list[_Part]:
    L, W = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9)
    colour = tuple(rng.uniform(0.1, 0.9, 3)) if rng.random() < 0.6 else (0.7,) * 3
    Rz = rotation_about([0.0, 0.0, 1.0], yaw)
    origin = np.array([x, y, 0.0])
    return [
        _part(rng, _BOX, origin + Rz @ np.array([0.0, 0.0, 0.7]), (L, W, 0.9), "car", colour,
              _NOISE, 0.3, 0.1, yaw=yaw),
        _part(rng, _BOX, origin + Rz @ np.array([-0.1 * L, 0.0, 1.45]), (0.55 * L, 0.9 * W, 0.6),
              "car", (0.15, 0.17, 0.2), _NOISE, 0.3, 0.1, yaw=yaw),
    ]


def _outdoor_camera(rng: np.random.Generator) -> np.ndarray:
    """On the road, looking down the street (+x) with a little yaw and pitch."""
    eye = np.array([rng.uniform(0.0, 10.0), rng.uniform(-1.5, 1.5), CAMERA_HEIGHT_OUTDOOR])
    yaw, pitch = np.radians(rng.uniform(-5, 5)), np.radians(rng.uniform(-2, 1))
    return look_at(eye, eye + np.array([np.cos(yaw), np.sin(yaw), np.tan(pitch)]))


def _outdoor_lidar(rng: np.random.Generator, T_world_cam: np.ndarray) -> np.ndarray:
    """``T_world_lidar`` (z up, x forward): a few metres along the street from the camera,
    a little sideways and yawed."""
    cam = T_world_cam[:3, 3]
    dx = rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 6.0)
    pos = np.array([cam[0] + dx, np.clip(cam[1] + rng.uniform(-0.8, 0.8), -2.2, 2.2),
                    LIDAR_HEIGHT])
    fwd = T_world_cam[:3, 2]
    yaw = np.arctan2(fwd[1], fwd[0]) + np.radians(rng.uniform(-8, 8))
    return make_pose(rotation_about([0.0, 0.0, 1.0], yaw), pos)


def _lidar_dirs(T_world_lidar: np.ndarray) -> np.ndarray:
    """Unit ray directions ``(64 * LIDAR_AZIMUTH_STEPS, 3)`` in the world, ring by ring."""
    el = np.radians(LIDAR_ELEVATIONS_DEG)[:, None]
    az = np.linspace(0.0, 2 * np.pi, LIDAR_AZIMUTH_STEPS, endpoint=False)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                     np.sin(el)), axis=-1).reshape(-1, 3)
    return d @ T_world_lidar[:3, :3].T


def _depth_view_of_lidar(T_world_lidar: np.ndarray) -> np.ndarray:
    """The virtual depth camera at the LiDAR, looking along its x axis, level."""
    pos = T_world_lidar[:3, 3]
    return look_at(pos, pos + T_world_lidar[:3, 0])

