"""The calibrated indoor world (``make_pair(world="rooms")``): furnished rooms with the clutter of
real ones, seen as a hand-held scan sees them.

Measured against real RGB-D frames by ``python -m freereg_lib.training.world_stats`` (docs/world.md):
the "blocks" world's rooms were large planes seen from afar (88 % planar points, 2.8 m median depth),
where the real frames are cluttered (64 %) and seen from closer (1.8 m). So here: chairs with legs
and backs, open shelves full of books, tables and dressers carrying cups, bottles, bowls and books,
sofas and beds with cushions and pillows, plants of many leaves, curtains in folds, radiators,
pictures and skirting on the walls; the camera looks at the furniture from 1-3 m, and the depth
sensor is a later frame of the same hand-held scan (a small turn and step from the camera).
Every part stands upright (as in the blocks world); ellipsoids are scaled spheres.
"""
from __future__ import annotations

import numpy as np

from freereg_lib.data.synthetic.indoor import _POSE_DRAWS, _footprint, _legs, _Room
from freereg_lib.data.synthetic.render import _BOX, _CHECKER, _CYLINDER, _NOISE, _SPHERE, _STRIPES, _Looks, _part, _Scene
from freereg_lib.geometry.cameras import look_at, rotation_about

WOOD = (0.55, 0.37, 0.22)
# A camera's clearance from the furniture's footprint circles, metres: negative because a circle
# around a rectangle's corners over-covers its sides (the camera stands 1.1 m or more above the floor,
# over all but shelves and lamps).
_CLEAR = -0.25


def _p(shape, centre, size, colour, tex=_NOISE, scale=0.05, contrast=0.25, axis=(1, 0, 0), cls=None):
    """A local part (indoor.py's ``_LocalPart``) with an optional class of its own."""
    return (shape, tuple(centre), tuple(size), tuple(colour), tex, scale, contrast, tuple(axis), cls)


def _legs9(width, depth, height, colour) -> list:
    return [(*leg, None) for leg in _legs(width, depth, height, colour)]


def _colour(looks: _Looks, lo=0.1, hi=0.9) -> tuple:
    return tuple(looks.uniform(lo, hi, 3))


def _tabletop_items(rng, looks, w, d, top) -> list:
    """Cups, bottles, bowls, books, fruit and a laptop spread over a ``w x d`` top at height ``top``."""
    items = []
    for _ in range(int(rng.integers(2, 7))):
        x, y = rng.uniform(-w / 2 + 0.1, w / 2 - 0.1), rng.uniform(-d / 2 + 0.08, d / 2 - 0.08)
        kind, c = int(rng.integers(0, 6)), _colour(looks)
        if kind == 0:  # cup
            r, h = rng.uniform(0.035, 0.05), rng.uniform(0.08, 0.12)
            items.append(_p(_CYLINDER, (x, y, top + h / 2), (2 * r, 2 * r, h), c, cls="clutter"))
        elif kind == 1:  # bottle with its neck
            r, h = rng.uniform(0.03, 0.045), rng.uniform(0.16, 0.26)
            items += [_p(_CYLINDER, (x, y, top + h / 2), (2 * r, 2 * r, h), c, cls="clutter"),
                      _p(_CYLINDER, (x, y, top + h + 0.03), (0.025, 0.025, 0.06), c, cls="clutter")]
        elif kind == 2:  # bowl
            r = rng.uniform(0.08, 0.14)
            items.append(_p(_SPHERE, (x, y, top + 0.03), (2 * r, 2 * r, 0.12), c, cls="clutter"))
        elif kind == 3:  # a stack of books
            for k in range(int(rng.integers(1, 4))):
                items.append(_p(_BOX, (x, y, top + 0.015 + 0.03 * k), (rng.uniform(0.15, 0.25), rng.uniform(0.12, 0.18), 0.03),
                                _colour(looks), _STRIPES, 0.02, 0.3, cls="book"))
        elif kind == 4:  # fruit
            for _ in range(int(rng.integers(1, 4))):
                r = rng.uniform(0.03, 0.05)
                items.append(_p(_SPHERE, (x + rng.normal(0, 0.05), y + rng.normal(0, 0.05), top + r), (2 * r,) * 3, c,
                                cls="clutter"))
        else:  # laptop: base and open screen
            items += [_p(_BOX, (x, y, top + 0.01), (0.32, 0.22, 0.02), (0.2, 0.2, 0.22), cls="clutter"),
                      _p(_BOX, (x, y - 0.11, top + 0.13), (0.32, 0.01, 0.22), (0.15, 0.15, 0.18), cls="clutter")]
    return items


def _books(rng, looks, x0, x1, z, depth, max_h) -> list:
    """A row of upright books between ``x0`` and ``x1`` on a board at height ``z``."""
    out, x = [], x0 + rng.uniform(0.0, 0.1)
    while x < x1 - 0.03:
        t = rng.uniform(0.02, 0.06)
        if rng.random() < 0.15:  # a gap
            x += rng.uniform(0.05, 0.2)
            continue
        h = rng.uniform(0.5, 1.0) * max_h
        d = depth * rng.uniform(0.7, 0.95)
        out.append(_p(_BOX, (x + t / 2, -0.5 * (depth - d), z + h / 2), (t, d, h), _colour(looks), _STRIPES, 0.03,
                      0.35, (0, 0, 1), cls="book"))
        x += t + 0.002
    return out


def _object(rng, looks, kind: str) -> list:
    """Local parts of one piece of furniture with what it carries (origin: floor, back towards -y)."""
    u = rng.uniform
    if kind == "table":
        w, d, h = u(0.8, 1.6), u(0.6, 0.9), u(0.45, 0.78)
        return ([_p(_BOX, (0, 0, h - 0.02), (w, d, 0.04), WOOD, _STRIPES, looks.uniform(0.02, 0.05), 0.25, (0, 1, 0))]
                + _legs9(w, d, h - 0.04, WOOD) + _tabletop_items(rng, looks, w, d, h))
    if kind == "chair":
        s, c, metal = u(0.40, 0.48), _colour(looks, 0.2, 0.8), (0.25, 0.25, 0.27)
        back = [_p(_BOX, (sx * (s / 2 - 0.02), -s / 2 + 0.02, 0.7), (0.035, 0.035, 0.5), c) for sx in (-1, 1)]
        back += [_p(_BOX, (0, -s / 2 + 0.02, z), (s - 0.04, 0.02, 0.06), c) for z in (0.62, 0.76, 0.9)]
        return [_p(_BOX, (0, 0, 0.45), (s, s, 0.04), c)] + _legs9(s, s, 0.43, metal) + back
    if kind == "armchair":
        w, c = u(0.75, 0.95), _colour(looks, 0.15, 0.75)
        return [_p(_BOX, (0, 0, 0.22), (w, 0.8, 0.34), c), _p(_BOX, (0, -0.32, 0.6), (w, 0.16, 0.5), c),
                _p(_BOX, (-w / 2 + 0.08, 0.05, 0.5), (0.16, 0.7, 0.22), c), _p(_BOX, (w / 2 - 0.08, 0.05, 0.5), (0.16, 0.7, 0.22), c),
                _p(_SPHERE, (0, -0.18, 0.58), (w - 0.3, 0.16, 0.38), _colour(looks))] + _legs9(w, 0.8, 0.06, (0.2, 0.2, 0.2))
    if kind == "sofa":
        w, d, c = u(1.6, 2.2), u(0.85, 0.95), _colour(looks, 0.15, 0.75)
        n = int(rng.integers(2, 4))
        seats = [_p(_BOX, (-w / 2 + 0.2 + (k + 0.5) * (w - 0.4) / n, 0.05, 0.46), ((w - 0.4) / n - 0.02, d - 0.3, 0.12), c)
                 for k in range(n)]
        pillows = [_p(_SPHERE, (u(-w / 2 + 0.4, w / 2 - 0.4), -d / 2 + 0.3, 0.68), (u(0.35, 0.5), 0.15, u(0.3, 0.42)),
                      _colour(looks), _CHECKER, 0.08, 0.3) for _ in range(int(rng.integers(1, 4)))]
        return [_p(_BOX, (0, 0, 0.2), (w, d, 0.32), c), _p(_BOX, (0, -d / 2 + 0.1, 0.62), (w, 0.2, 0.5), c),
                _p(_BOX, (-w / 2 + 0.1, 0.05, 0.52), (0.2, d - 0.1, 0.24), c),
                _p(_BOX, (w / 2 - 0.1, 0.05, 0.52), (0.2, d - 0.1, 0.24), c)] + seats + pillows
    if kind == "bed":
        w, c = u(1.0, 1.8), _colour(looks, 0.5, 0.95)
        return [_p(_BOX, (0, 0.05, 0.15), (w + 0.06, 2.0, 0.3), WOOD, cls="bed"),
                _p(_BOX, (0, 0.05, 0.4), (w, 1.95, 0.2), (0.9, 0.9, 0.88), cls="bed"),
                _p(_BOX, (0, -0.97, 0.65), (w + 0.06, 0.06, 0.9), WOOD, _STRIPES, 0.05, 0.3, cls="bed"),
                _p(_BOX, (0, 0.45, 0.53), (w + 0.04, 1.1, 0.06), c, _CHECKER, 0.15, 0.35, cls="bed")] + [
            _p(_SPHERE, (x, -0.7, 0.58), (min(0.6, w / 2 - 0.05), 0.35, 0.16), (0.95, 0.95, 0.92), cls="bed")
            for x in ((-w / 4, w / 4) if w > 1.2 else (0.0,))]
    if kind == "bookshelf":
        w, h, d, c = u(0.7, 1.3), u(1.2, 2.0), 0.32, (WOOD if rng.random() < 0.6 else (0.9, 0.9, 0.88))
        n = int(round(h / 0.38))
        parts = [_p(_BOX, (sx * (w / 2 - 0.01), 0, h / 2), (0.02, d, h), c) for sx in (-1, 1)]
        parts.append(_p(_BOX, (0, -d / 2 + 0.005, h / 2), (w, 0.01, h), c))
        for k in range(n + 1):
            z = 0.05 + k * (h - 0.07) / n
            parts.append(_p(_BOX, (0, 0, z), (w - 0.04, d, 0.02), c))
            if k < n:
                parts += _books(rng, looks, -w / 2 + 0.02, w / 2 - 0.02, z + 0.01, d - 0.02, (h - 0.07) / n - 0.04)
        return parts
    if kind in ("dresser", "desk", "tv_stand"):
        w, d = u(0.8, 1.4), u(0.45, 0.6)
        h = {"dresser": u(0.75, 1.1), "desk": 0.74, "tv_stand": u(0.4, 0.55)}[kind]
        c = WOOD if rng.random() < 0.5 else _colour(looks, 0.5, 0.95)
        if kind == "desk":
            parts = [_p(_BOX, (0, 0, h - 0.02), (w, d, 0.04), c), _p(_BOX, (-w / 2 + 0.02, 0, h / 2), (0.04, d, h - 0.04), c),
                     _p(_BOX, (w / 2 - 0.2, 0, h / 2), (0.4, d, h - 0.04), c)]
        else:
            parts = [_p(_BOX, (0, 0, h / 2), (w, d, h), c, _CHECKER, 0.3, 0.1)]
            rows = max(2, int(h / 0.25))
            for r in range(rows):  # drawer handles
                for sx in (-0.25, 0.25):
                    parts.append(_p(_BOX, (sx * w, d / 2 + 0.015, (r + 0.5) * h / rows), (0.12, 0.03, 0.025), (0.6, 0.6, 0.6)))
        if kind in ("desk", "tv_stand"):  # a screen on a foot
            sw = u(0.5, min(1.2, w))
            parts += [_p(_CYLINDER, (0, -0.05, h + 0.05), (0.2, 0.15, 0.1), (0.1, 0.1, 0.1)),
                      _p(_BOX, (0, -0.05, h + 0.1 + 0.3 * sw), (sw, 0.04, 0.6 * sw), (0.05, 0.05, 0.06))]
            if kind == "desk":
                parts.append(_p(_BOX, (0, 0.12, h + 0.015), (0.42, 0.14, 0.03), (0.2, 0.2, 0.2)))
        return parts + _tabletop_items(rng, looks, w * 0.9, d * 0.6, h)[: 3]
    if kind == "lamp":
        metal = (0.5, 0.5, 0.52)
        return [_p(_CYLINDER, (0, 0, 0.015), (0.3, 0.3, 0.03), metal), _p(_CYLINDER, (0, 0, 0.78), (0.035, 0.035, 1.5), metal),
                _p(_CYLINDER, (0, 0, 1.6), (u(0.3, 0.5),) * 2 + (0.3,), (0.95, 0.9, 0.75), _STRIPES, 0.05, 0.2, (0, 0, 1))]
    if kind == "plant":
        r, h = u(0.12, 0.22), u(0.25, 0.45)
        leaves = []
        for _ in range(int(rng.integers(6, 14))):
            a, e, s = u(0, 2 * np.pi), u(0.0, 1.0), u(0.12, 0.3)
            leaves.append(_p(_SPHERE, (0.6 * r * e * np.cos(a) * 2, 0.6 * r * e * np.sin(a) * 2, h + u(0.05, 0.7)),
                             (s, s * u(0.4, 1.0), s * u(0.3, 0.8)), (0.15, u(0.35, 0.6), 0.12), _NOISE, 0.04, 0.5))
        return [_p(_CYLINDER, (0, 0, h / 2), (2 * r, 2 * r, h), (0.7, 0.35, 0.2), _STRIPES, 0.08, 0.2, (0, 0, 1))] + leaves
    # floor clutter: stacked boxes, a bag, a ball
    parts, z = [], 0.0
    for _ in range(int(rng.integers(1, 4))):
        s = u(0.2, 0.5) * (0.8 if z else 1.0)
        parts.append(_p(_BOX, (rng.normal(0, 0.03), rng.normal(0, 0.03), z + s / 2), (s, s * u(0.7, 1.0), s * u(0.5, 1.0)),
                        (0.7, 0.55, 0.3), _STRIPES, 0.1, 0.35, cls="crate"))
        z += s * 0.8
    r = u(0.1, 0.25)
    return parts + [_p(_SPHERE, (0.45, 0.1, r * 0.8), (2 * r, 1.6 * r, 1.6 * r), _colour(looks), cls="clutter")]


_AGAINST_WALL = ("sofa", "bed", "bookshelf", "bookshelf", "dresser", "desk", "tv_stand", "armchair", "plant", "lamp")
_FREE = ("table", "chair", "chair", "plant", "lamp", "crate", "armchair")


def _wall_decor(rng, looks, Lx, Ly, Hr) -> list:
    """World-frame parts on the walls: skirting, pictures, a radiator, curtains in folds, a wall shelf."""
    parts = []
    walls = [((Lx / 2, 0.0), 0.0, Lx), ((Lx, Ly / 2), np.pi / 2, Ly), ((Lx / 2, Ly), np.pi, Lx), ((0.0, Ly / 2), -np.pi / 2, Ly)]
    for (cx, cy), yaw, length in walls:
        R = rotation_about([0.0, 0.0, 1.0], yaw)

        def put(local, size, colour, tex=_NOISE, scale=0.05, contrast=0.2, cls="decor", shape=_BOX):
            parts.append(_part(looks, shape, np.array([cx, cy, 0.0]) + R @ np.asarray(local, float), size, cls, colour,
                               tex, scale, contrast, yaw=yaw))

        put((0, 0.008, 0.04), (length, 0.016, 0.08), (0.95, 0.95, 0.93))
        for _ in range(int(rng.integers(0, 3))):
            w, h = rng.uniform(0.3, 0.9), rng.uniform(0.25, 0.7)
            put((rng.uniform(-length / 2 + w, length / 2 - w), 0.015, rng.uniform(1.3, 1.8)), (w, 0.03, h),
                _colour(looks), _NOISE, looks.uniform(0.02, 0.1), 0.6)
        kind = rng.integers(0, 4)
        x = rng.uniform(-length / 2 + 1.0, length / 2 - 1.0)
        if kind == 0:  # radiator: fins
            for k in range(int(rng.integers(8, 16))):
                put((x + 0.06 * k, 0.06, 0.45), (0.03, 0.08, 0.6), (0.92, 0.92, 0.92))
        elif kind == 1:  # curtains in folds
            c = _colour(looks, 0.3, 0.9)
            for k in range(int(rng.integers(10, 20))):
                put((x + 0.07 * k, 0.1 + 0.02 * np.sin(k), Hr / 2 - 0.1), (0.09, 0.09, Hr - 0.3), c, _STRIPES, 0.1, 0.2,
                    shape=_CYLINDER)
        elif kind == 2:  # wall shelf with books
            put((x, 0.12, 1.5), (0.9, 0.24, 0.025), WOOD)
            for part in _books(rng, looks, -0.42, 0.42, 1.51, 0.2, 0.25):
                shape, centre, size, colour, tex, scale, contrast, axis, _ = part
                put((x + centre[0], 0.12 + centre[1], centre[2]), size, colour, tex, scale, contrast, cls="book")
    return parts


def _room_scene(rng: np.random.Generator, looks: _Looks | None = None) -> tuple[_Scene, _Room]:
    """A furnished, cluttered room drawn from ``rng`` (colours and textures from ``looks``)."""
    looks = _Looks(rng) if looks is None else looks
    Lx, Ly, Hr = rng.uniform(3.5, 5.5), rng.uniform(3.0, 4.5), rng.uniform(2.4, 2.8)
    th = 0.1
    wall = (_colour(looks, 0.55, 0.95), _STRIPES if looks.random() < 0.4 else _NOISE, looks.uniform(0.05, 0.3))
    parts = [_part(looks, _BOX, (Lx / 2, Ly / 2, -th / 2), (Lx + 2 * th, Ly + 2 * th, th), "floor", (0.6, 0.45, 0.3),
                   _STRIPES if looks.random() < 0.5 else _CHECKER, looks.uniform(0.1, 0.5), 0.3),
             _part(looks, _BOX, (Lx / 2, Ly / 2, Hr + th / 2), (Lx + 2 * th, Ly + 2 * th, th), "ceiling", (0.92, 0.92, 0.9),
                   _NOISE, 0.5, 0.1)]
    for centre, size in (((Lx / 2, -th / 2, Hr / 2), (Lx, th, Hr)), ((Lx / 2, Ly + th / 2, Hr / 2), (Lx, th, Hr)),
                         ((-th / 2, Ly / 2, Hr / 2), (th, Ly + 2 * th, Hr)), ((Lx + th / 2, Ly / 2, Hr / 2), (th, Ly + 2 * th, Hr))):
        parts.append(_part(looks, _BOX, centre, size, "wall", *wall, 0.2, tex_axis=(1, 1, 0)))
    if rng.random() < 0.6:  # a rug
        parts.append(_part(looks, _BOX, (Lx / 2, Ly / 2, 0.005), (rng.uniform(1.2, 2.4), rng.uniform(1.0, 1.8), 0.01),
                           "decor", _colour(looks), _CHECKER, looks.uniform(0.1, 0.3), 0.5))
    parts += _wall_decor(rng, looks, Lx, Ly, Hr)

    kinds = list(rng.choice(_AGAINST_WALL, int(rng.integers(4, 7)))) + list(rng.choice(_FREE, int(rng.integers(3, 7))))
    objects = sorted(((k, _object(rng, looks, k)) for k in kinds), key=lambda o: -float(np.prod(_footprint(o[1]))))
    circles: list[tuple[float, float, float]] = []
    for kind, local in objects:
        half = _footprint(local)
        radius = float(np.linalg.norm(half))
        n = 32
        if kind in _AGAINST_WALL:
            side = rng.integers(0, 4, n)
            yaw = side * (np.pi / 2)
            along = rng.uniform(half[0] + 0.05, np.maximum(np.where(side % 2 == 0, Lx, Ly) - half[0] - 0.05, half[0] + 0.06))
            off = half[1] + 0.03
            xy = np.select([side[:, None] == 0, side[:, None] == 1, side[:, None] == 2],
                           [np.stack([along, np.full(n, off)], 1), np.stack([np.full(n, Lx - off), along], 1),
                            np.stack([Lx - along, np.full(n, Ly - off)], 1)], np.stack([np.full(n, off), Ly - along], 1))
        else:
            yaw = rng.uniform(0, 2 * np.pi, n)
            m = min(radius, 1.0)
            xy = np.stack([rng.uniform(m, Lx - m, n), rng.uniform(m, Ly - m, n)], 1)
        c = np.asarray(circles) if circles else np.zeros((0, 3))
        gap = np.min(np.linalg.norm(xy[:, None] - c[None, :, :2], axis=2) - c[None, :, 2] - radius, axis=1, initial=np.inf)
        ok = np.flatnonzero(gap > 0.02)
        if not len(ok):
            continue  # a full room drops the piece
        k = int(ok[0])
        circles.append((xy[k, 0], xy[k, 1], radius))
        Rz = rotation_about([0.0, 0.0, 1.0], float(yaw[k]))
        origin = np.array([xy[k, 0], xy[k, 1], 0.0])
        for shape, centre, size, colour, tex, scale, contrast, axis, cls in local:
            parts.append(_part(looks, shape, origin + Rz @ np.asarray(centre, float), size, cls or _kind_class(kind), colour,
                               tex, scale, contrast, yaw=float(yaw[k]), tex_axis=axis))
    lamp = np.array([rng.uniform(0.3, 0.7) * Lx, rng.uniform(0.3, 0.7) * Ly, Hr - 0.05])
    return _Scene(parts, lamp=lamp, lamp_range=3.5, ambient=0.25, key=1.1), _Room(np.array([Lx, Ly, Hr]), np.asarray(circles))


def _kind_class(kind: str) -> str:
    """The class of a piece of furniture (``CLASS_NAMES``)."""
    return {"armchair": "sofa", "dresser": "cabinet", "desk": "table", "tv_stand": "cabinet"}.get(kind, kind)


def _scan_camera(rng: np.random.Generator, room: _Room) -> np.ndarray:
    """``T_world_cam`` of a hand-held scan: 1.1-1.7 m high, in free space, looking at a piece of
    furniture 1-3 m away."""
    Lx, Ly, _ = room.size
    for _ in range(_POSE_DRAWS):
        eye = np.array([rng.uniform(0.3, Lx - 0.3), rng.uniform(0.3, Ly - 0.3), rng.uniform(1.1, 1.7)])
        x, y, r = room.circles[rng.integers(len(room.circles))]
        target = np.array([x, y, rng.uniform(0.3, 1.0)]) + rng.normal(0.0, 0.3, 3)
        if room.free(eye[:2], _CLEAR) and 1.0 < np.linalg.norm(target[:2] - eye[:2]) < 3.0:
            return look_at(eye, target)
    raise RuntimeError("synthetic rooms: the room is too crowded for a camera")


def _scan_sensor(rng: np.random.Generator, T_world_cam: np.ndarray, room: _Room) -> np.ndarray:
    """The depth sensor as a later frame of the same scan: the camera turned (yaw 12 deg, pitch
    4 deg, standard deviations) and stepped (0.2 m per axis)."""
    Lx, Ly, Hr = room.size
    for _ in range(_POSE_DRAWS):
        R = rotation_about([0.0, 0.0, 1.0], np.radians(rng.normal(0.0, 12.0)))
        tilt = rotation_about(T_world_cam[:3, 0], np.radians(rng.normal(0.0, 4.0)))
        T = T_world_cam.copy()
        T[:3, :3] = R @ tilt @ T_world_cam[:3, :3]
        T[:3, 3] = T_world_cam[:3, 3] + rng.normal(0.0, 0.2, 3)
        e = T[:3, 3]
        if 0.25 < e[0] < Lx - 0.25 and 0.25 < e[1] < Ly - 0.25 and 0.8 < e[2] < Hr - 0.3 and room.free(e[:2], _CLEAR):
            return T
    raise RuntimeError("synthetic rooms: no free pose for the depth sensor")
