"""The ``stub`` backend: no weights, CPU, instant, deterministic; synthetic scenes only.

It stands in for the learned models with what a synthetic scene knows (class ids, true
depth), reproducing the properties the paper describes, not its numbers. Every figure or
table made with it must say so (``StubBackend.label``).

Diffusion features (:meth:`StubBackend.diffusion_rgb` / ``diffusion_depth``)
    The per-pixel class-id map is area-pooled to each layer's grid, the grid of an input
    resized to ``resize_hw`` (8 x 11, 16 x 22, 32 x 44 at 512 x 704): a cell's value is the
    fraction of each class among its pixels with a non-zero id. "Context" copies of these
    fractions, Gaussian-blurred by ``context`` cells (default 0, 1, 3: like a decoder
    feature's growing receptive field, larger in cells' units on the coarse layers), make a
    cell depend on what surrounds it, so a uniform region is not one single feature. Each
    (layer, context scale) maps class ``k`` to a fixed random unit vector ``E[k]`` (seeded by
    ``cfg.seed``, the layer, the scale and ``k``; id 0 = nothing -> zero vector), and a
    cell's feature is ``sum_scales sum_k frac_k E[k] / sqrt(n_scales)``: coarse, semantic and
    the same for the RGB and depth sides. Gaussian noise of relative level ``noise`` (its
    per-pixel norm) is added, drawn differently for the RGB and the depth call (seeded by
    ``cfg.seed``, the side, the layer and the id map). Layers 7 and 8 ("texture" layers in
    the paper, which lose cross-modal consistency) carry ``texture_noise`` times more noise
    and half the shared signal.
    Channels: by default 256 for layers 0-6 and 128 for 7-8, the paper's 1280 / 640
    (Table 2) divided by 5 to keep the stub and its PCA cheap (still >= 128, so PCA to 128
    dims works as with the real model); pass ``channels=PAPER_CHANNELS`` for the paper's
    counts or any ``(c0_2, c3_5, c6, c7_8)``.
    What it cannot mimic: the ids are class ids (all walls share one), so inside a large
    region only the context tells cells apart; real diffusion features see texture and
    geometry as well.

Monocular depth (:meth:`StubBackend.mono_depth`)
    ``Z = D (1 + k (s + r(u, v)))`` on valid pixels of the true depth ``D`` (zeros stay
    zeros): ``s`` a global scale error of random sign and weight ``scale_share`` (default
    0.8: most of ZoeDepth's indoor error is a per-image scale, which is why the paper's
    Kabsch estimates a similarity), ``r`` a smooth field (a ``distortion_cells`` grid of
    Gaussian values, bicubically upsampled, unit mean absolute value, weight
    ``1 - scale_share``), and ``k`` chosen so the mean absolute error equals ``mono_mae``
    (default 0.27 m indoors, the error the paper reports for ZoeDepth; outdoors 8 % of the
    mean depth). The factor is floored at 0.2. Seeded by ``cfg.seed`` and the depth map.
"""
from __future__ import annotations

import cv2
import numpy as np

from freereg_lib.models.base import LAYER_STRIDES, Backend, _hints, check_layers, seed_from

PAPER_CHANNELS = (1280, 1280, 1280, 640)  # layers 0-2, 3-5, 6, 7-8 (Table 2)
STUB_CHANNELS = (256, 256, 256, 128)  # the stub's default: 5x fewer, still >= 128 for PCA


def _group_channels(channels) -> list[int]:
    c0, c1, c2, c3 = channels
    return [c0, c0, c0, c1, c1, c1, c2, c3, c3]


def _blur(frac: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (in cells, reflected borders) of each class-fraction map."""

    return np.stack([cv2.GaussianBlur(f, (0, 0), sigmaX=sigma, sigmaY=sigma,
                                      borderType=cv2.BORDER_REFLECT) for f in frac])


class StubBackend(Backend):
    """Stand-in features and depth for synthetic scenes (see the module docstring).

    Args:
        cfg: the config (``resize_hw``, ``seed``, ``outdoor``).
        noise: relative noise level of the diffusion features (0 = noise-free).
        texture_noise: noise multiplier of layers 7 and 8.
        channels: channels of layers (0-2, 3-5, 6, 7-8).
        context: Gaussian sigmas (in cells of each layer) of the context copies; ``(0,)``
            = the plain pooled class fractions.
        position_share: share of the signal's energy that comes from the scene position
            ``xyz`` when it is given (the rest is the semantic part).
        lengthscales: metres over which the positional part of layers (0-2, 3-5, 6, 7-8)
            stays similar: coarse layers are smooth, fine layers sharper.
        mono_mae: mean absolute error of the stub monocular depth in metres (None = the
            default: 0.27 m indoors, 8 % of the mean true depth outdoors).
        scale_share: share of the depth error that is a global scale error (the rest is the
            smooth distortion).
        distortion_cells: ``(rows, cols)`` of the distortion field's control grid (its size:
            fewer cells = smoother, lower frequency).
        resize_hw: override of ``cfg.resize_hw``.
    """

    name = "stub"
    label = "stub backend (synthetic stand-in features, no learned model)"
    # The pipeline passes class ids and scene coordinates only to backends that ask.
    uses_scene_hints = True

    def __init__(self, cfg, noise: float = 1.5, texture_noise: float = 3.0,
                 channels: tuple[int, int, int, int] = STUB_CHANNELS,
                 mono_mae: float | None = None, scale_share: float = 0.8,
                 distortion_cells: tuple[int, int] = (3, 4),
                 context: tuple[float, ...] = (0.0, 1.0, 3.0),
                 position_share: float = 0.3,
                 lengthscales: tuple[float, float, float, float] = (2.4, 1.2, 0.6, 0.3),
                 resize_hw: tuple[int, int] | None = None, device: str | None = None):
        super().__init__(cfg, resize_hw)
        if noise < 0 or texture_noise < 0:
            raise ValueError("noise levels must be >= 0")
        if not 0.0 <= scale_share <= 1.0:
            raise ValueError(f"scale_share must be in [0, 1], got {scale_share}")
        self.noise = float(noise)
        self.texture_noise = float(texture_noise)
        self.channels = _group_channels(channels)
        self.mono_mae = mono_mae
        self.scale_share = float(scale_share)
        self.distortion_cells = tuple(int(c) for c in distortion_cells)
        self.context = tuple(float(c) for c in context)
        if not 0.0 <= position_share <= 1.0:
            raise ValueError(f"position_share must be in [0, 1], got {position_share}")
        self.position_share = float(position_share)
        self.lengthscales = _group_channels(lengthscales)
        self._emb_cache: dict[tuple[int, int, int], np.ndarray] = {}

    # ---- diffusion stand-in -------------------------------------------------------------
    def _embedding(self, layer: int, class_id: int, scale: int = 0) -> np.ndarray:
        key = (layer, int(class_id), scale)
        if key not in self._emb_cache:
            c = self.channels[layer]
            if class_id == 0:
                v = np.zeros(c, dtype=np.float32)
            else:
                rng = np.random.default_rng(seed_from(self.cfg.seed, "stub-emb", layer, class_id,
                                                      scale))
                v = rng.standard_normal(c).astype(np.float32)
                v /= np.linalg.norm(v)
            self._emb_cache[key] = v
        return self._emb_cache[key]

    def _cells(self, size: tuple[int, int], stride: int) -> tuple[np.ndarray, int, int]:
        """Cell index ``(H, W)`` of every pixel on the layer grid of ``stride``, and the grid ``h, w``.

        A pixel goes to the cell holding its centre in the resized image (area pooling).
        """
        H, W = size
        h, w = self.resize_hw[0] // stride, self.resize_hw[1] // stride
        rows = np.minimum(((np.arange(H) + 0.5) * h / H).astype(np.int64), h - 1)
        cols = np.minimum(((np.arange(W) + 0.5) * w / W).astype(np.int64), w - 1)
        return rows[:, None] * w + cols[None, :], h, w

    def _pooled_fractions(self, ids: np.ndarray, stride: int):
        """Class fractions ``(K, h, w)`` of the grid of stride ``stride`` and the class list."""
        cell, h, w = self._cells(ids.shape, stride)
        classes, inv = np.unique(ids, return_inverse=True)
        inv = inv.reshape(ids.shape)
        counts = np.bincount((inv * (h * w) + cell).ravel(),
                             minlength=len(classes) * h * w).reshape(len(classes), h, w)
        counts = counts.astype(np.float32)
        nz = classes != 0
        total = counts[nz].sum(axis=0)
        frac = counts / np.maximum(total, 1.0)[None]
        frac[~nz] = 0.0
        return frac, classes

    def _positional(self, layer: int, xyz_cells: np.ndarray) -> np.ndarray:
        """Random Fourier features ``(C, h, w)`` of pooled scene points ``(3, h, w)``.

        Their dot product approximates a Gaussian kernel of the layer's lengthscale in
        metres, so two cells look alike exactly when they see nearby scene points, from
        either modality. Cells without a point get zeros.
        """
        C = self.channels[layer]
        rng = np.random.default_rng(seed_from(self.cfg.seed, "stub-pos", layer))
        B = rng.standard_normal((C, 3)) / self.lengthscales[layer]
        phase = rng.uniform(0, 2 * np.pi, C)
        _, h, w = xyz_cells.shape
        flat = xyz_cells.reshape(3, -1)
        valid = np.all(np.isfinite(flat), axis=0)
        out = np.zeros((C, h * w), dtype=np.float32)
        out[:, valid] = np.sqrt(2.0 / C) * np.cos(B @ flat[:, valid] + phase[:, None])
        return out.reshape(C, h, w)

    def _pooled_xyz(self, xyz: np.ndarray, stride: int) -> np.ndarray:
        """Mean scene point ``(3, h, w)`` of each cell of the layer grid (NaN where none)."""
        cell, h, w = self._cells(xyz.shape[:2], stride)
        cell = cell.ravel()
        pts = xyz.reshape(-1, 3)
        ok = np.all(np.isfinite(pts), axis=1)
        count = np.bincount(cell[ok], minlength=h * w).astype(np.float64)
        out = np.stack([np.bincount(cell[ok], pts[ok, k], minlength=h * w) for k in range(3)])
        with np.errstate(invalid="ignore", divide="ignore"):
            out = out / count
        out[:, count == 0] = np.nan
        return out.reshape(3, h, w)

    def _features(self, ids: np.ndarray | None, side: str, xyz: np.ndarray | None = None,
                  layers=None) -> dict[int, np.ndarray]:
        """``{layer: map}`` for ``layers`` (all nine when None); each layer is computed alone
        (its own seeded noise), so a subset equals the same layers of the full set."""
        if ids is None:
            raise ValueError(
                "the stub diffusion features need a synthetic scene: pass the per-pixel class-id "
                "map `ids` (Pair.image_ids for the image; the projected Pair.point_ids for the "
                'depth map). For real images use backend="tiny" (random weights) or "real".'
            )
        ids = np.asarray(ids)
        if ids.ndim != 2:
            raise ValueError(f"ids must be an (H, W) integer map, got shape {ids.shape}")
        ids = ids.astype(np.int64)
        id_key = np.ascontiguousarray(ids.astype(np.int32)).tobytes()
        out = {}
        frac_cache: dict[int, tuple] = {}
        xyz_cache: dict[int, np.ndarray] = {}
        if xyz is not None:
            xyz = np.asarray(xyz, dtype=np.float64)
            if xyz.shape != ids.shape + (3,):
                raise ValueError(f"xyz must be (H, W, 3) like ids {ids.shape}, got {xyz.shape}")
        for layer in check_layers(layers):
            stride = LAYER_STRIDES[layer]
            if stride not in frac_cache:
                frac_cache[stride] = self._pooled_fractions(ids, stride)
            frac, classes = frac_cache[stride]
            K, h, w = frac.shape
            C = self.channels[layer]
            signal = np.zeros((C, h, w), dtype=np.float32)
            for si, sigma in enumerate(self.context):
                f = frac if sigma <= 0 else _blur(frac, sigma)
                E = np.stack([self._embedding(layer, k, si) for k in classes])  # (K, C)
                signal += (E.T @ f.reshape(K, -1)).reshape(C, h, w)
            signal /= np.sqrt(len(self.context))
            if xyz is not None and self.position_share > 0:
                if stride not in xyz_cache:
                    xyz_cache[stride] = self._pooled_xyz(xyz, stride)
                signal = (np.sqrt(1.0 - self.position_share) * signal
                          + np.sqrt(self.position_share) * self._positional(layer, xyz_cache[stride]))
            noise = self.noise
            if layer >= 7:
                signal = 0.5 * signal
                noise = noise * self.texture_noise
            if noise > 0:
                rng = np.random.default_rng(seed_from(self.cfg.seed, "stub-noise", side, layer,
                                                      id_key))
                signal = signal + (noise / np.sqrt(C)) * rng.standard_normal(
                    (C, h, w), dtype=np.float32)
            out[layer] = signal.astype(np.float32, copy=False)
        return out

    def diffusion_rgb(self, image: np.ndarray, ids: np.ndarray | None = None,
                      xyz: np.ndarray | None = None) -> list[np.ndarray]:
        return list(self._checked(image, {"ids": ids, "xyz": xyz}, "rgb", None).values())

    def diffusion_depth(self, depth: np.ndarray, ids: np.ndarray | None = None,
                        xyz: np.ndarray | None = None) -> list[np.ndarray]:
        return list(self._checked(depth, {"ids": ids, "xyz": xyz}, "depth", None).values())

    def diffusion_rgb_batch(self, images, hints=None, layers=None) -> list[dict[int, np.ndarray]]:
        """Only the chosen ``layers`` are computed (see :meth:`Backend.diffusion_rgb_batch`)."""
        return [self._checked(im, h, "rgb", layers) for im, h in zip(images, _hints(hints, len(images)))]

    def diffusion_depth_batch(self, depths, hints=None, layers=None) -> list[dict[int, np.ndarray]]:
        """Only the chosen ``layers`` are computed (see :meth:`Backend.diffusion_depth_batch`)."""
        return [self._checked(d, h, "depth", layers) for d, h in zip(depths, _hints(hints, len(depths)))]

    def _checked(self, x: np.ndarray, hint: dict, side: str, layers) -> dict[int, np.ndarray]:
        ids = hint.get("ids")
        size = np.shape(x)[:2] if side == "rgb" else np.shape(x)
        if ids is not None and x is not None and np.shape(ids) != size:
            raise ValueError(f"ids {np.shape(ids)} and {'image' if side == 'rgb' else 'depth'} {size} differ in size")
        return self._features(ids, side, hint.get("xyz"), layers)

    # ---- monocular depth stand-in -------------------------------------------------------
    def mono_depth(self, image: np.ndarray, depth_gt: np.ndarray | None = None) -> np.ndarray:
        if depth_gt is None:
            raise ValueError(
                "the stub monocular depth needs the true depth `depth_gt` (a synthetic scene's "
                'Pair.depth_gt); for real images use backend="tiny" or "real".'
            )

        D = np.asarray(depth_gt, dtype=np.float64)
        if image is not None and np.shape(image)[:2] != D.shape:
            raise ValueError(f"depth_gt {D.shape} and image {np.shape(image)[:2]} differ in size")
        valid = np.isfinite(D) & (D > 0)
        out = np.zeros_like(D)
        if not valid.any():
            return out
        rng = np.random.default_rng(
            seed_from(self.cfg.seed, "stub-mono", np.round(D * 1000).astype(np.int64).tobytes()))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        gh, gw = self.distortion_cells
        grid = rng.standard_normal((gh, gw))
        H, W = D.shape
        field = cv2.resize(grid, (W, H), interpolation=cv2.INTER_CUBIC)
        field /= max(np.abs(field[valid]).mean(), 1e-9)
        rel = sign * self.scale_share + (1.0 - self.scale_share) * field
        target = self.mono_mae
        if target is None:
            target = 0.08 * float(D[valid].mean()) if self.cfg.outdoor else 0.27
        mae_unit = float(np.abs(D[valid] * rel[valid]).mean())
        k = target / max(mae_unit, 1e-12)
        factor = np.maximum(1.0 + k * rel, 0.2)
        out[valid] = D[valid] * factor[valid]
        return out
