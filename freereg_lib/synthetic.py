"""Seeded synthetic scenes: an indoor room and an outdoor street, raycast with Open3D.

This module owns the synthetic data source of the library:

* building the scenes out of boxes, cylinders and spheres, baked once per scene into an
  Open3D ``RaycastingScene`` (CPU);
* rendering the image camera: RGB (procedural textures in object coordinates, Lambertian
  shading with cast shadows, ambient light, sky and haze outdoors), true depth and class ids;
* the depth side: a second depth camera indoors, a 64-line rotating LiDAR outdoors, whose
  pose is resampled until the pair's overlap lies in a requested range;
* :func:`overlap_ratio`, the overlap measure that range refers to, and :data:`CLASS_NAMES`.

Conventions are those of :mod:`freereg_lib.cameras`: world z up, the point cloud frame
``pc`` is the world frame, ``T_a_b`` maps frame ``b`` into frame ``a``, depth is the camera
z coordinate with 0 where a ray hits nothing. Every random choice is drawn from one
``numpy.random.Generator`` seeded by ``seed``, so the same arguments give bit-identical
pairs.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from tqdm import tqdm

from freereg_lib.cameras import (
    backproject,
    intrinsics,
    invert,
    lift,
    look_at,
    make_pose,
    pixel_grid,
    project,
    rotation_about,
    transform,
)
from freereg_lib.pair import Pair

CLASS_NAMES: dict[int, str] = {
    0: "none",  # sky outdoors; no hit
    1: "floor",
    2: "wall",
    3: "ceiling",
    4: "table",
    5: "chair",
    6: "cabinet",
    7: "sofa",
    8: "lamp",
    9: "ball",
    10: "plant",
    11: "crate",
    12: "bookshelf",
    13: "road",
    14: "sidewalk",
    15: "building",
    16: "car",
    17: "pole",
    18: "trunk",
    19: "foliage",
}
_ID = {name: i for i, name in CLASS_NAMES.items()}

KINDS = ("indoor", "outdoor")
DEFAULT_IMAGE_SIZE = {"indoor": (480, 640), "outdoor": (256, 832)}
MAX_POINTS = 60_000

# LiDAR: an HDL-64-like pattern (KITTI's Velodyne), with fewer azimuth steps for speed.
LIDAR_HEIGHT = 1.73
LIDAR_ELEVATIONS_DEG = np.linspace(2.0, -24.8, 64)
LIDAR_AZIMUTH_STEPS = 1024
CAMERA_HEIGHT_OUTDOOR = 1.65

_HORIZON = np.array([0.82, 0.87, 0.93])
_ZENITH = np.array([0.32, 0.52, 0.85])

# Per-pixel shading runs over slices of this many pixels: full-image temporaries page-fault
# on every allocation, cache-sized ones are reused (5-8x faster on the 2-core dev VM).
_CHUNK = 16384

# Display gamma 2.2 as a lookup on linear intensity quantised to 12 bits (a power is slow).
_GAMMA_LUT = np.round((np.arange(4096) / 4095) ** (1 / 2.2) * 255).astype(np.uint8)

_BOX, _CYLINDER, _SPHERE = 0, 1, 2
_CHECKER, _STRIPES, _NOISE = 0, 1, 2

# Resampling budget of the depth-side pose; one camera pose may simply see too little.
_CAMERA_TRIES = 6
_SENSOR_TRIES = 60
# Draws for one free viewpoint in a furnished room (rejections are rare).
_POSE_DRAWS = 1000
# Image pixels probed (every _PROBE_STRIDE-th row and column) by the cheap overlap estimate.
_PROBE_STRIDE = 4
# overlap_ratio's depth consistency tolerance, metres: absolute + relative to depth.
_TOL_ABS = 0.05
_TOL_REL = 0.03


@dataclass
class _Part:
    """One primitive: its placement, class and appearance.

    ``size`` is the full extent along the local axes: a box's sides, ``(2r, 2r, h)`` for a
    z-axis cylinder, ``(2r, 2r, 2r)`` for a sphere. The local axes are the world's turned by
    ``yaw`` about z: every part stands upright, which keeps per-pixel frames cheap.
    """

    shape: int
    centre: np.ndarray
    yaw: float
    size: np.ndarray
    class_id: int
    colour: np.ndarray
    texture: int
    tex_scale: float  # metres per texture period
    tex_contrast: float
    tex_axis: np.ndarray  # local stripe direction
    tex_offset: np.ndarray  # decorrelates the patterns of parts with the same texture


@dataclass
class _Hits:
    """A batch of raycast results; ``N`` rays from one origin.

    ``dirs (N, 3)`` are the (unnormalised) world directions, ``t (N,)`` the hit parameter in
    units of ``dirs`` (``inf`` on a miss), ``part (N,)`` the part index (-1 on a miss),
    ``normal (N, 3)`` the hit triangle's normal.
    """

    origin: np.ndarray
    dirs: np.ndarray
    t: np.ndarray
    part: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.part >= 0

    def points(self) -> np.ndarray:
        """World hit points of the hit rays, ``(M, 3)``."""
        h = self.hit
        return self.origin + self.t[h, None] * self.dirs[h]


@functools.lru_cache(maxsize=None)
def _unit_mesh(shape: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3) float64`` and triangles ``(F, 3) uint32`` of a unit-extent primitive
    centred on the origin."""
    if shape == _BOX:
        mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
        mesh.translate((-0.5, -0.5, -0.5))
    elif shape == _CYLINDER:
        mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=0.5, height=1.0, resolution=32)
    else:
        mesh = o3d.geometry.TriangleMesh.create_sphere(radius=0.5, resolution=20)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.triangles).astype(np.uint32)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear intensities (any shape, clipped to [0, 1]) to display-gamma ``uint8``."""
    return _GAMMA_LUT[np.rint(np.clip(linear, 0.0, 1.0) * 4095).astype(np.int64)]


def _chunks(n: int) -> list[slice]:
    """Slices of ``range(n)`` of ``_CHUNK`` items (the last shorter)."""
    return [slice(i, min(i + _CHUNK, n)) for i in range(0, n, _CHUNK)]


@functools.lru_cache(maxsize=8)
def _camera_rays(K_flat: tuple[float, ...], H: int, W: int) -> np.ndarray:
    """Camera-frame ray directions ``(H * W, 3)`` of every pixel, row-major, with z = 1 so
    that a ray's hit parameter t is the depth z itself."""
    d = lift(pixel_grid(H, W).reshape(-1, 2), np.ones(H * W), np.reshape(K_flat, (3, 3)))
    d.flags.writeable = False
    return d


# A fixed lattice of random values for the procedural textures: a constant, not drawn from
# the scene's rng, so a texture is a function of object coordinates alone.
_LATTICE_BITS = 6
_LATTICE = np.random.default_rng(20240101).random(1 << (3 * _LATTICE_BITS))


def _lattice(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray) -> np.ndarray:
    """Lattice values in ``[0, 1)`` at integer points (periodic, period 64 per axis)."""
    m = (1 << _LATTICE_BITS) - 1
    return _LATTICE[(((ix & m) << _LATTICE_BITS | (iy & m)) << _LATTICE_BITS) | (iz & m)]


def _value_noise(s: np.ndarray) -> np.ndarray:
    """Smooth 3D value noise of ``s (N, 3)``, values ``(N,)`` in ``[0, 1]``."""
    i0 = np.floor(s)
    f = s - i0
    w = f * f * (3.0 - 2.0 * f)
    i0 = i0.astype(np.int64)
    out = np.zeros(len(s))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wxy = wx * (w[:, 1] if dy else 1.0 - w[:, 1])
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wxy * wz * _lattice(i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz)
    return out


class _Scene:
    """The parts of one scene, raycast-ready, with its lighting.

    Exactly one of ``sun`` (a unit direction towards the sun) and ``lamp`` (a point light
    position) is set.
    """

    def __init__(
        self,
        parts: list[_Part],
        *,
        sun: np.ndarray | None = None,
        lamp: np.ndarray | None = None,
        lamp_range: float = 3.5,
        ambient: float = 0.25,
        key: float = 1.0,
        haze_m: float = np.inf,
    ) -> None:
        self.raycaster = o3d.t.geometry.RaycastingScene()
        geometry_ids = []
        for p in parts:
            v, f = _unit_mesh(p.shape)
            v = (v * p.size) @ rotation_about([0.0, 0.0, 1.0], p.yaw).T + p.centre
            geometry_ids.append(
                self.raycaster.add_triangles(
                    o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f)
                )
            )
        self.part_of_geometry = np.full(max(geometry_ids) + 1, -1, dtype=np.int64)
        self.part_of_geometry[geometry_ids] = np.arange(len(parts))
        self.shape = np.array([p.shape for p in parts])
        self.centre = np.stack([p.centre for p in parts])
        self.cos_yaw = np.cos([p.yaw for p in parts])
        self.sin_yaw = np.sin([p.yaw for p in parts])
        self.half = np.stack([p.size for p in parts]) / 2.0
        self.class_id = np.array([p.class_id for p in parts], dtype=np.int32)
        self.colour = np.stack([p.colour for p in parts])
        self.texture = np.array([p.texture for p in parts])
        self.tex_scale = np.array([p.tex_scale for p in parts])
        self.tex_contrast = np.array([p.tex_contrast for p in parts])
        self.tex_axis = np.stack([p.tex_axis for p in parts])
        self.tex_offset = np.stack([p.tex_offset for p in parts])
        self.sun, self.lamp, self.lamp_range = sun, lamp, lamp_range
        self.ambient, self.key, self.haze_m = ambient, key, haze_m

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> _Hits:
        """Cast rays ``origin (3,) + t * dirs (N, 3)`` in one call."""
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        ans = self.raycaster.cast_rays(o3d.core.Tensor(rays))
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        miss = gid >= len(self.part_of_geometry)
        part = np.where(miss, -1, self.part_of_geometry[np.where(miss, 0, gid)])
        t = ans["t_hit"].numpy().astype(np.float64)
        t[miss] = np.inf
        normal = ans["primitive_normals"].numpy().astype(np.float64)
        return _Hits(np.asarray(origin, dtype=np.float64), dirs, t, part, normal)

    def visible(self, origin: np.ndarray, points: np.ndarray, tol_m: float = 0.02) -> np.ndarray:
        """``(N,) bool``: nothing lies between ``origin (3,)`` and ``points (N, 3)``."""
        d = points - origin
        hits = self.cast(origin, d)
        return hits.t >= 1.0 - tol_m / np.maximum(np.linalg.norm(d, axis=1), 1e-9)

    def camera_view(
        self, T_world_cam: np.ndarray, K: np.ndarray, size: tuple[int, int]
    ) -> tuple[_Hits, np.ndarray, np.ndarray]:
        """Raycast a pinhole camera. Returns the hits, depth ``(H, W) float64`` (z, 0 on a
        miss) and class ids ``(H, W) int32`` (0 on a miss)."""
        H, W = size
        d_cam = _camera_rays(tuple(np.asarray(K, dtype=np.float64).ravel()), H, W)
        hits = self.cast(T_world_cam[:3, 3], d_cam @ T_world_cam[:3, :3].T)
        depth = np.where(hits.hit, hits.t, 0.0).reshape(H, W)
        ids = np.where(hits.hit, self.class_id[np.maximum(hits.part, 0)], 0).astype(np.int32)
        return hits, depth, ids.reshape(H, W)

    def _to_local(self, p: np.ndarray, part: np.ndarray) -> np.ndarray:
        """World points ``p (M, 3)`` on parts ``part (M,)`` in their parts' frames."""
        d = p - self.centre[part]
        c, s = self.cos_yaw[part], self.sin_yaw[part]
        return np.stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], d[:, 2]], axis=1)

    def _normals(self, p: np.ndarray, part: np.ndarray, flat: np.ndarray) -> np.ndarray:
        """Shading normals ``(M, 3)``: analytic on curved surfaces so that coarse meshes still
        shade smoothly, the triangle's otherwise."""
        n = flat.copy()
        curved = self.shape[part] != _BOX
        if curved.any():
            pc = part[curved]
            n_local = self._to_local(p[curved], pc) / self.half[pc] ** 2
            side = (self.shape[pc] == _CYLINDER) & (np.abs(flat[curved, 2]) < 0.9)
            cap = (self.shape[pc] == _CYLINDER) & ~side
            n_local[side, 2] = 0.0
            c, s = self.cos_yaw[pc], self.sin_yaw[pc]
            n_curved = np.stack([c * n_local[:, 0] - s * n_local[:, 1],
                                 s * n_local[:, 0] + c * n_local[:, 1], n_local[:, 2]], axis=1)
            n_curved[cap] = flat[curved][cap]
            n[curved] = n_curved
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def _albedo(self, p: np.ndarray, part: np.ndarray) -> np.ndarray:
        """Textured base colour ``(M, 3)`` in object coordinates, hence the same in every view."""
        q = self._to_local(p, part)
        s = q / self.tex_scale[part, None] + self.tex_offset[part]
        raw = np.empty(len(p))
        tex = self.texture[part]
        m = tex == _CHECKER
        raw[m] = np.floor(s[m]).sum(axis=1) % 2
        m = tex == _STRIPES
        phase = np.einsum("ni,ni->n", s[m], self.tex_axis[part[m]])
        raw[m] = 0.5 + 0.5 * np.sin(2 * np.pi * phase)
        m = tex == _NOISE
        raw[m] = 0.65 * _value_noise(s[m]) + 0.35 * _value_noise(2.7 * s[m])
        c = self.tex_contrast[part]
        pattern = 1.0 - c + c * raw
        # Fine grain everywhere (4 mm cells, one lattice value each: cheap), so flat faces
        # are not uniform patches.
        cell = np.floor(q * 250.0).astype(np.int64)
        pattern *= 0.92 + 0.08 * _lattice(cell[:, 0] + 7 * part, cell[:, 1], cell[:, 2])
        return self.colour[part] * pattern[:, None]

    def _sky(self, dirs: np.ndarray) -> np.ndarray:
        """Sky colour ``(M, 3)`` along ``dirs (M, 3)``: pale at the horizon, blue above."""
        up = dirs[:, 2] / np.linalg.norm(dirs, axis=1)
        a = np.clip(up * 2.5, 0.0, 1.0)[:, None]
        return (1 - a) * _HORIZON + a * _ZENITH

    def _light(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit directions to the light ``(M, 3)``, its falloff ``(M,)`` and the shadow-ray
        directions ``(M, 3)`` (reaching the light at t = 1 for a lamp) from points ``p``."""
        if self.sun is not None:
            to_light = np.broadcast_to(self.sun, p.shape)
            return to_light, np.ones(len(p)), to_light
        shadow_dirs = self.lamp - p
        dist = np.linalg.norm(shadow_dirs, axis=1)
        falloff = 1.0 / (1.0 + (dist / self.lamp_range) ** 2)
        return shadow_dirs / dist[:, None], falloff, shadow_dirs

    def shade(self, hits: _Hits, size: tuple[int, int]) -> np.ndarray:
        """RGB ``(H, W, 3) uint8`` of a camera view's hits."""
        h = hits.hit
        part, p, d, flat = hits.part[h], hits.points(), hits.dirs[h], hits.normal[h]
        M = len(p)
        direct = np.empty(M)
        shadow_rays = np.empty((M, 6), dtype=np.float32)
        for s in _chunks(M):
            n = self._normals(p[s], part[s], flat[s])
            # Triangle winding is arbitrary (walls are seen from inside): face the viewer.
            n *= -np.sign(np.einsum("ni,ni->n", n, d[s]))[:, None]
            to_light, falloff, shadow_dirs = self._light(p[s])
            direct[s] = falloff * np.clip(np.einsum("ni,ni->n", n, to_light), 0.0, None)
            # Shadow rays start a millimetre off the surface to not hit it again.
            shadow_rays[s, :3] = p[s] + 1e-3 * n
            shadow_rays[s, 3:] = shadow_dirs
        occluded = self.raycaster.test_occlusions(
            o3d.core.Tensor(shadow_rays), tnear=0.0, tfar=1.0 if self.sun is None else np.inf
        ).numpy()
        direct[occluded] = 0.0
        rgb = np.zeros((len(h), 3), dtype=np.uint8)
        if self.sun is not None:
            rgb[~h] = _to_srgb8(self._sky(hits.dirs[~h]))
        t_hit = hits.t[h]
        pixels = np.flatnonzero(h)
        for s in _chunks(M):
            colour = self._albedo(p[s], part[s]) * (self.ambient + self.key * direct[s])[:, None]
            if np.isfinite(self.haze_m):
                fog = np.exp(-t_hit[s] * np.linalg.norm(d[s], axis=1) / self.haze_m)[:, None]
                colour = fog * colour + (1 - fog) * _HORIZON
            rgb[pixels[s]] = _to_srgb8(colour)
        return rgb.reshape(*size, 3)


class _Looks:
    """The appearance draws of an indoor scene: colours, textures and their scales.

    Every draw is also made from the scene's generator ``rng``, so the geometry, poses and
    cloud drawn after it are the same whether or not ``redraw`` is set; with ``redraw`` (a
    generator of its own) the value used is drawn from it instead: the same room in another
    colouring from the world's prior.
    """

    def __init__(self, rng: np.random.Generator, redraw: np.random.Generator | None = None) -> None:
        self.rng, self.redraw = rng, redraw

    def uniform(self, low=0.0, high=1.0, size=None):
        value = self.rng.uniform(low, high, size)
        return value if self.redraw is None else self.redraw.uniform(low, high, size)

    def random(self) -> float:
        value = self.rng.random()
        return value if self.redraw is None else self.redraw.random()


def _part(
    rng: np.random.Generator | _Looks,
    shape: int,
    centre,
    size,
    class_name: str,
    colour,
    texture: int,
    tex_scale: float,
    tex_contrast: float,
    *,
    yaw: float = 0.0,
    tex_axis=(1.0, 0.0, 0.0),
) -> _Part:
    """A part with its colour jittered and its texture offset drawn from ``rng`` (a scene's
    :class:`_Looks` indoors)."""
    jitter = rng.uniform(0.85, 1.15, 3)
    return _Part(
        shape=shape,
        centre=np.asarray(centre, dtype=np.float64),
        yaw=yaw,
        size=np.asarray(size, dtype=np.float64),
        class_id=_ID[class_name],
        colour=np.clip(np.asarray(colour) * jitter, 0.02, 0.98),
        texture=texture,
        tex_scale=tex_scale,
        tex_contrast=tex_contrast,
        tex_axis=np.asarray(tex_axis, dtype=np.float64),
        tex_offset=rng.uniform(0.0, 100.0, 3),
    )


# ----------------------------------------------------------------------------- indoor

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


# ---------------------------------------------------------------------------- outdoor

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


# ------------------------------------------------------------------------------ pairs


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
    overlap: tuple[float, float] = (0.3, 0.8),
    image_size: tuple[int, int] | None = None,
    depth_camera_image: bool = False,
    appearance_seed: int | tuple[int, ...] | None = None,
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

    ``seed`` may also be a tuple of integers (a NumPy seed sequence), as the micro models'
    training pairs are drawn, so that no integer evaluation seed reproduces them.

    ``depth_camera_image=True`` also shades the RGB image the depth camera would have seen,
    ``(H_d, W_d, 3) uint8`` in ``pair.meta["depth_camera_image"]`` (a diagnostic no real
    cloud has: :mod:`freereg_lib.micro.diagnose`); the pair is otherwise the same.

    ``appearance_seed`` (indoor only; an integer or, like ``seed``, a tuple of them) draws every
    colour, texture and texture scale from a generator of its own: the same room, poses and cloud, shaded in another colouring from the
    world's prior (a diagnostic of how much of an image its depth map cannot tell).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown synthetic kind {kind!r}; expected one of {KINDS}")
    lo, hi = _check_overlap(overlap)
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
        scene, room = _indoor_scene(rng, _Looks(rng, redraw))
        sample_camera = functools.partial(_indoor_camera, room=room)
        sample_sensor = functools.partial(_indoor_sensor, room=room)
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
                name=f"synthetic-{kind}/{_seed_label(seed)}",
                meta={"dataset": "synthetic", "kind": kind, "outdoor": kind == "outdoor",
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


if __name__ == "__main__":
    import time

    for kind in KINDS:
        make_pair(kind, seed=0)  # warm-up: imports, cached meshes
        t0 = time.perf_counter()
        pairs = [make_pair(kind, seed=s) for s in range(5)]
        dt = (time.perf_counter() - t0) / len(pairs)
        ov = ", ".join(f"{p.meta['overlap']:.2f}" for p in pairs)
        npts = ", ".join(str(len(p.points)) for p in pairs)
        print(f"{kind}: {dt * 1000:.0f} ms/pair; overlaps {ov}; points {npts}")
