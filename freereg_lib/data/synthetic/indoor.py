"""The synthetic indoor world: a furnished room, its image camera and its depth camera.

Rooms of boxes, cylinders and spheres (walls, floor, ceiling, 6-10 pieces of furniture placed
without collisions, a ceiling lamp), drawn from the scene's generator; colours and textures
through ``render._Looks``. The depth camera is a second pinhole camera near the image
camera, looking near where it looks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freereg_lib.data.synthetic.render import (
    _BOX,
    _CHECKER,
    _CYLINDER,
    _NOISE,
    _SPHERE,
    _STRIPES,
    _Looks,
    _part,
    _Scene,
)
from freereg_lib.geometry.cameras import look_at, rotation_about

# Draws for one free viewpoint in a furnished room (rejections are rare).
_POSE_DRAWS = 1000


# Local parts of an object: (shape, centre relative to the object's floor origin, size,
# colour, texture, texture scale, contrast, stripe axis). All of one class.
_LocalPart = tuple[int, tuple, tuple, tuple, int, float, float, tuple]


def _legs(width: float, depth: float, height: float, colour: tuple) -> list[_LocalPart]:
    dx, dy = width / 2 - 0.04, depth / 2 - 0.04
    return [
        (_BOX, (sx * dx, sy * dy, height / 2), (0.04, 0.04, height), colour, _NOISE, 0.05, 0.2,
         (0, 0, 1))
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]


def _indoor_object(rng: np.random.Generator, looks: _Looks, kind: str) -> list[_LocalPart]:
    """The local parts of one piece of furniture, sizes drawn from ``rng``, colours and texture
    scales from ``looks``."""
    u, look = rng.uniform, looks.uniform
    wood = (0.55, 0.37, 0.22)
    if kind == "table":
        w, d, h = u(1.0, 1.8), u(0.6, 1.0), u(0.70, 0.78)
        return [(_BOX, (0, 0, h - 0.025), (w, d, 0.05), wood, _STRIPES, look(0.02, 0.05), 0.25,
                 (0, 1, 0))] + _legs(w, d, h - 0.05, wood)
    if kind == "chair":
        s = u(0.40, 0.50)
        c = tuple(look(0.2, 0.8, 3))
        return [
            (_BOX, (0, 0, 0.45), (s, s, 0.05), c, _NOISE, 0.04, 0.3, (1, 0, 0)),
            (_BOX, (0, -s / 2 + 0.025, 0.7), (s, 0.05, 0.45), c, _NOISE, 0.04, 0.3, (1, 0, 0)),
        ] + _legs(s, s, 0.425, (0.25, 0.25, 0.27))
    if kind == "cabinet":
        w, d, h = u(0.6, 1.2), u(0.4, 0.6), u(0.8, 2.0)
        c = wood if looks.random() < 0.5 else (0.85, 0.85, 0.8)
        return [(_BOX, (0, 0, h / 2), (w, d, h), c, _CHECKER, look(0.3, 0.5), 0.15, (0, 0, 1))]
    if kind == "bookshelf":
        w, h = u(0.8, 1.4), u(1.6, 2.1)
        return [(_BOX, (0, 0, h / 2), (w, 0.35, h), (0.4, 0.26, 0.16), _STRIPES, look(0.3, 0.4),
                 0.5, (0, 0, 1))]
    if kind == "sofa":
        w, d = u(1.6, 2.2), u(0.8, 0.95)
        c = tuple(look(0.15, 0.75, 3))
        fabric = (c, _NOISE, look(0.05, 0.15), 0.35, (1, 0, 0))
        return [
            (_BOX, (0, 0, 0.22), (w, d, 0.44), *fabric),
            (_BOX, (0, -d / 2 + 0.1, 0.64), (w, 0.2, 0.4), *fabric),
            (_BOX, (-w / 2 + 0.1, 0.1, 0.54), (0.2, d - 0.2, 0.2), *fabric),
            (_BOX, (w / 2 - 0.1, 0.1, 0.54), (0.2, d - 0.2, 0.2), *fabric),
        ]
    if kind == "lamp":
        metal = (0.5, 0.5, 0.52)
        return [
            (_CYLINDER, (0, 0, 0.015), (0.3, 0.3, 0.03), metal, _NOISE, 0.05, 0.1, (1, 0, 0)),
            (_CYLINDER, (0, 0, 0.78), (0.04, 0.04, 1.5), metal, _NOISE, 0.05, 0.1, (1, 0, 0)),
            (_CYLINDER, (0, 0, 1.6), (0.45, 0.45, 0.3), (0.95, 0.9, 0.75), _STRIPES, 0.05, 0.2,
             (0, 0, 1)),
        ]
    if kind == "ball":
        r = u(0.1, 0.3)
        c = tuple(look(0.1, 0.95, 3))
        return [(_SPHERE, (0, 0, r), (2 * r,) * 3, c, _CHECKER, r * 0.7, 0.5, (1, 0, 0))]
    if kind == "plant":
        r, h, rf = u(0.15, 0.25), u(0.3, 0.45), u(0.3, 0.45)
        return [
            (_CYLINDER, (0, 0, h / 2), (2 * r, 2 * r, h), (0.7, 0.35, 0.2), _STRIPES, 0.08, 0.2,
             (0, 0, 1)),
            (_SPHERE, (0, 0, h + 0.8 * rf), (2 * rf,) * 3, (0.2, 0.5, 0.15), _NOISE, 0.06, 0.6,
             (1, 0, 0)),
        ]
    s = u(0.3, 0.6)  # crate
    return [(_BOX, (0, 0, s / 2), (s, s, s), (0.7, 0.55, 0.3), _STRIPES, 0.1, 0.35, (1, 0, 0))]


_INDOOR_POOL = ("table", "chair", "chair", "cabinet", "sofa", "lamp", "ball", "plant",
                "crate", "bookshelf", "chair", "crate")
_AGAINST_WALL = {"cabinet", "bookshelf", "sofa"}


def _footprint(local: list[_LocalPart]) -> np.ndarray:
    """Half extents ``(2,)`` of the object's footprint around its origin."""
    return np.max([np.abs(c[:2]) + np.asarray(s[:2]) / 2 for _, c, s, *_ in local], axis=0)


@dataclass
class _Room:
    size: np.ndarray  # (Lx, Ly, height); the room spans [0, Lx] x [0, Ly] x [0, height]
    circles: np.ndarray  # (M, 3) object footprints as (x, y, radius)

    def free(self, xy: np.ndarray, clearance: float) -> bool:
        gap = np.linalg.norm(self.circles[:, :2] - xy, axis=1) - self.circles[:, 2]
        return bool(np.all(gap > clearance))


def _indoor_scene(rng: np.random.Generator, looks: _Looks | None = None) -> tuple[_Scene, _Room]:
    """A furnished room drawn from ``rng``; its colours and textures from ``looks`` (by default
    from ``rng`` too, as every pair and training view draws them)."""
    looks = _Looks(rng) if looks is None else looks
    Lx, Ly, Hr = rng.uniform(4.6, 5.4), rng.uniform(3.6, 4.4), rng.uniform(2.5, 2.8)
    wall_colour = tuple(looks.uniform(0.6, 0.95, 3))
    th = 0.1  # walls are slabs outside the interior, whose faces lie exactly on its bounds
    parts = [
        _part(looks, _BOX, (Lx / 2, Ly / 2, -th / 2), (Lx + 2 * th, Ly + 2 * th, th), "floor",
              (0.6, 0.45, 0.3), _STRIPES if looks.random() < 0.5 else _CHECKER,
              looks.uniform(0.15, 0.5), 0.3, tex_axis=(1, 0, 0)),
        _part(looks, _BOX, (Lx / 2, Ly / 2, Hr + th / 2), (Lx + 2 * th, Ly + 2 * th, th),
              "ceiling", (0.92, 0.92, 0.9), _NOISE, 0.5, 0.1),
    ]
    wall_tex = _STRIPES if looks.random() < 0.5 else _NOISE
    wall_scale = looks.uniform(0.08, 0.3)
    for centre, size in (
        ((Lx / 2, -th / 2, Hr / 2), (Lx, th, Hr)),
        ((Lx / 2, Ly + th / 2, Hr / 2), (Lx, th, Hr)),
        ((-th / 2, Ly / 2, Hr / 2), (th, Ly + 2 * th, Hr)),
        ((Lx + th / 2, Ly / 2, Hr / 2), (th, Ly + 2 * th, Hr)),
    ):
        parts.append(_part(looks, _BOX, centre, size, "wall", wall_colour, wall_tex, wall_scale,
                           0.2, tex_axis=(1, 1, 0)))

    kinds = rng.choice(_INDOOR_POOL, size=int(rng.integers(6, 11)), replace=False)
    objects = [(str(k), _indoor_object(rng, looks, str(k))) for k in kinds]
    # Big objects first so they still find room.
    objects.sort(key=lambda o: -float(np.prod(_footprint(o[1]))))
    circles: list[tuple[float, float, float]] = []
    for kind, local in objects:
        half = _footprint(local)
        radius = float(np.linalg.norm(half))
        n_cand = 32
        if kind in _AGAINST_WALL:
            wall = rng.integers(0, 4, n_cand)
            yaw = wall * (np.pi / 2)
            # Along the wall with the object's back (local -y) against it.
            along = rng.uniform(half[0] + 0.05, np.where(wall % 2 == 0, Lx, Ly) - half[0] - 0.05)
            off = half[1] + 0.02
            xy = np.select(
                [wall[:, None] == 0, wall[:, None] == 1, wall[:, None] == 2],
                [np.stack([along, np.full(n_cand, off)], 1),
                 np.stack([np.full(n_cand, Lx - off), along], 1),
                 np.stack([along, np.full(n_cand, Ly - off)], 1)],
                np.stack([np.full(n_cand, off), along], 1),
            )
        else:
            yaw = rng.integers(0, 4, n_cand) * (np.pi / 2) + rng.normal(0.0, 0.3, n_cand)
            margin = min(radius, 1.0)
            xy = np.stack([rng.uniform(margin, Lx - margin, n_cand),
                           rng.uniform(margin, Ly - margin, n_cand)], 1)
        if circles:
            c = np.asarray(circles)
            gap = np.min(np.linalg.norm(xy[:, None] - c[None, :, :2], axis=2)
                         - c[None, :, 2] - radius, axis=1)
        else:
            gap = np.full(n_cand, np.inf)
        # First candidate with some clearance; failing that the least crowded one, so the
        # object count stays as drawn.
        ok = np.flatnonzero(gap > 0.05)
        k = int(ok[0]) if len(ok) else int(np.argmax(gap))
        circles.append((xy[k, 0], xy[k, 1], radius))
        Rz = rotation_about([0.0, 0.0, 1.0], float(yaw[k]))
        origin = np.array([xy[k, 0], xy[k, 1], 0.0])
        for shape, centre, size, colour, tex, scale, contrast, axis in local:
            parts.append(_part(looks, shape, origin + Rz @ np.asarray(centre, float), size, kind,
                               colour, tex, scale, contrast, yaw=float(yaw[k]), tex_axis=axis))

    lamp = np.array([rng.uniform(0.3, 0.7) * Lx, rng.uniform(0.3, 0.7) * Ly, Hr - 0.05])
    scene = _Scene(parts, lamp=lamp, lamp_range=3.5, ambient=0.22, key=1.1)
    return scene, _Room(np.array([Lx, Ly, Hr]), np.asarray(circles))


def _indoor_camera(rng: np.random.Generator, room: _Room) -> np.ndarray:
    """``T_world_cam`` at head height, outside every object, looking at a point of the room."""
    Lx, Ly, _ = room.size
    for _ in range(_POSE_DRAWS):
        eye = np.array([rng.uniform(0.4, Lx - 0.4), rng.uniform(0.4, Ly - 0.4),
                        rng.uniform(1.2, 1.8)])
        target = np.array([rng.uniform(0.3, Lx - 0.3), rng.uniform(0.3, Ly - 0.3),
                           rng.uniform(0.3, 1.5)])
        # A target too close would fill the view with one surface.
        if room.free(eye[:2], 0.15) and np.linalg.norm(target[:2] - eye[:2]) > 1.5:
            return look_at(eye, target)
    raise RuntimeError("synthetic indoor: the room is too crowded for a camera")


def _indoor_sensor(rng: np.random.Generator, T_world_cam: np.ndarray, room: _Room) -> np.ndarray:
    """A depth-sensor pose near the camera looking near where it looks, so that the overlap
    spreads over the whole ``[0, 1]`` range."""
    Lx, Ly, Hr = room.size
    for _ in range(_POSE_DRAWS):
        ang, rad = rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 2.0)
        eye = T_world_cam[:3, 3] + np.array([rad * np.cos(ang), rad * np.sin(ang), 0.0])
        eye[2] = rng.uniform(1.0, 2.0)
        if not (0.3 < eye[0] < Lx - 0.3 and 0.3 < eye[1] < Ly - 0.3 and room.free(eye[:2], 0.15)):
            continue
        target = T_world_cam[:3, 3] + 2.5 * T_world_cam[:3, 2] + rng.normal(0.0, 1.0, 3)
        target = np.clip(target, [0.1, 0.1, 0.1], [Lx - 0.1, Ly - 0.1, Hr - 0.1])
        if np.linalg.norm(target - eye) > 1.0:
            return look_at(eye, target)
    raise RuntimeError("synthetic indoor: the room is too crowded for a depth sensor")


def _same_pose(T: np.ndarray) -> np.ndarray:
    return T
