"""The synthetic world's renderer: primitives, their raycasting scene and their shading.

* ``_Part``, a box, cylinder or sphere with its class and appearance, and ``_part``,
  which jitters its colour and draws its texture offset;
* ``_Scene``, the parts baked once into an Open3D ``RaycastingScene`` (CPU), cast by a
  pinhole camera or any rays, and shaded: procedural textures in object coordinates, Lambertian
  shading with cast shadows, ambient light, sky and haze outdoors;
* ``_Looks``, the appearance draws of an indoor scene (the same room in another colouring);
* ``CLASS_NAMES``, the classes of both worlds.

The scenes themselves are :mod:`.indoor` and :mod:`.outdoor`; the pairs, :mod:`.pairs`.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from freereg_lib.geometry.cameras import lift, pixel_grid, rotation_about

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
    20: "bed",  # the "rooms" world's own classes (rooms.py)
    21: "book",
    22: "clutter",
    23: "decor",
}
_ID = {name: i for i, name in CLASS_NAMES.items()}

_HORIZON = np.array([0.82, 0.87, 0.93])
_ZENITH = np.array([0.32, 0.52, 0.85])

# Per-pixel shading runs over slices of this many pixels: full-image temporaries page-fault
# on every allocation, cache-sized ones are reused (5-8x faster on the 2-core dev VM).
_CHUNK = 16384

# Display gamma 2.2 as a lookup on linear intensity quantised to 12 bits (a power is slow).
_GAMMA_LUT = np.round((np.arange(4096) / 4095) ** (1 / 2.2) * 255).astype(np.uint8)

_BOX, _CYLINDER, _SPHERE = 0, 1, 2
_CHECKER, _STRIPES, _NOISE = 0, 1, 2


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
    ``_Looks`` indoors)."""
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
