"""A disk cache of backend outputs, so that ablations after the backend cost no model time.

The diffusion features and the monocular depth of a frame depend only on the input arrays,
the backend and a few hyper-parameters (``t_hat``, DDIM steps, guidance, prompts, resize,
seed, indoor/outdoor model, the UNet variant, the ControlNet checkpoint, the dtype). Everything an ablation over the fusion weight ``w``, the layer
choice, PCA, matching or the solver changes happens *after* the backend, so wrapping the
backend in :class:`CachedBackend` makes a second run of such an ablation read the features
from disk instead of running Stable Diffusion, ControlNet and ZoeDepth again::

    backend = CachedBackend(get_backend("real", cfg), "cache/features", feature_params(cfg))
    rows = pipeline.run_pairs(pairs, backend, cfg)   # second time: no model call

Files: ``<cache_dir>/<backend name>/<method>/<key[:2]>/<key>.npz``; the key is a SHA-256
of the backend name, the method, ``params`` and every input array (dtype, shape, bytes).
Size: the nine decoder layers of one 512 x 704 input are about 20 MB in float32 (layer 6
alone 7 MB); ``half=True`` stores diffusion layers as float16 (half that, returned as
float32, relative error ~1e-3). Writes are atomic, so an interrupted run leaves no broken
entry; delete the folder to clear the cache.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .backends.base import Backend, _hints, check_layers

# The config fields that change a backend's outputs (see FreeRegConfig).
FEATURE_FIELDS = ("outdoor", "resize_hw", "t_hat", "ddim_steps", "ddim_eta", "guidance_w",
                  "prompt", "negative_prompt", "seed", "sd_unet_variant", "controlnet", "dtype")


def feature_params(cfg, resize_hw: tuple[int, int] | None = None) -> dict:
    """The cache-relevant fields of ``cfg`` (:data:`FEATURE_FIELDS`) as a plain dict.

    Pass ``resize_hw`` when the backend was built with a size other than ``cfg.resize_hw``.
    """
    params = {name: getattr(cfg, name) for name in FEATURE_FIELDS}
    if resize_hw is not None:
        params["resize_hw"] = tuple(resize_hw)
    return params


class CachedBackend:
    """``backend`` with its three outputs memoised on disk.

    Args:
        backend: any object with ``name``, ``diffusion_rgb(image, ids=None[, xyz])``,
            ``diffusion_depth(depth, ids=None[, xyz])`` (lists of ``(C, h, w)`` arrays) and
            ``mono_depth(image, depth_gt=None)`` (an ``(H, W)`` array).
        cache_dir: the cache's root folder (created when missing).
        params: everything besides the inputs that changes the outputs; usually
            :func:`feature_params`. Two runs share entries only when their params are equal.
        half: store diffusion layers as float16 (returned as float32).

    Other attributes (``cfg``, ``resize_hw``, ``label``, ...) are the wrapped backend's.
    ``hits`` and ``misses`` count the calls served from disk and computed.
    """

    def __init__(self, backend, cache_dir: str | os.PathLike, params: dict, half: bool = False):
        self.backend = backend
        self.name = backend.name
        self.cache_dir = Path(cache_dir)
        self.params = dict(params)
        self.half = half
        self.hits = 0
        self.misses = 0
        # default=str: tuples, paths and numbers all serialise the same way every run.
        self._params_blob = json.dumps(self.params, sort_keys=True, default=str).encode()

    def __getattr__(self, attr):
        if attr == "backend":  # not set yet (e.g. while unpickling): no recursion
            raise AttributeError(attr)
        return getattr(self.backend, attr)

    def diffusion_rgb(self, image: np.ndarray, ids: np.ndarray | None = None,
                      xyz: np.ndarray | None = None) -> list[np.ndarray]:
        """Decoder layers of an RGB image ``(H, W, 3) uint8`` (see the backend)."""
        hints = {"ids": ids} if xyz is None else {"ids": ids, "xyz": xyz}
        return self._cached("diffusion_rgb", (image, ids, xyz),
                            lambda: self.backend.diffusion_rgb(image, **hints), self.half)

    def diffusion_depth(self, depth: np.ndarray, ids: np.ndarray | None = None,
                        xyz: np.ndarray | None = None) -> list[np.ndarray]:
        """Decoder layers of a depth map ``(H, W)`` in metres (see the backend)."""
        hints = {"ids": ids} if xyz is None else {"ids": ids, "xyz": xyz}
        return self._cached("diffusion_depth", (depth, ids, xyz),
                            lambda: self.backend.diffusion_depth(depth, **hints), self.half)

    def mono_depth(self, image: np.ndarray, depth_gt: np.ndarray | None = None) -> np.ndarray:
        """Metric depth ``(H, W)`` of an RGB image (see the backend); never stored as float16."""
        return self._cached("mono_depth", (image, depth_gt),
                            lambda: [self.backend.mono_depth(image, depth_gt=depth_gt)], False)[0]

    # The backends' default: :meth:`mono_depth` per image, so each is its own cache entry.
    mono_depth_batch = Backend.mono_depth_batch

    def key(self, method: str, inputs: tuple) -> str:
        """The cache key of ``method`` on ``inputs`` (arrays or None), a hex SHA-256."""
        h = hashlib.sha256()
        h.update(f"{self.name}\0{method}\0".encode())
        h.update(self._params_blob)
        for arr in inputs:
            if arr is None:
                h.update(b"\0none")
                continue
            a = np.ascontiguousarray(arr)
            h.update(f"\0{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        return h.hexdigest()

    def path(self, method: str, inputs: tuple) -> Path:
        """Where the output of ``method`` on ``inputs`` is (or would be) stored."""
        k = self.key(method, inputs)
        return self.cache_dir / self.name / method / k[:2] / f"{k}.npz"

    def diffusion_rgb_batch(self, images, hints=None, layers=None) -> list[dict[int, np.ndarray]]:
        """As the backend's, with the entries of :meth:`diffusion_rgb`: the misses are computed
        in one batch (all nine layers, so an entry serves any later layer choice)."""
        return self._cached_batch("diffusion_rgb", images, hints, layers)

    def diffusion_depth_batch(self, depths, hints=None, layers=None) -> list[dict[int, np.ndarray]]:
        """As :meth:`diffusion_rgb_batch`, with the entries of :meth:`diffusion_depth`."""
        return self._cached_batch("diffusion_depth", depths, hints, layers)

    def _cached_batch(self, method: str, xs, hints, layers) -> list[dict[int, np.ndarray]]:
        keep = check_layers(layers)
        hints = _hints(hints, len(xs))
        paths = [self.path(method, (x, h.get("ids"), h.get("xyz"))) for x, h in zip(xs, hints)]
        out: list = [None] * len(xs)
        todo = []
        for i, path in enumerate(paths):
            if path.is_file():
                self.hits += 1
                out[i] = self._load(path, self.half)
            else:
                todo.append(i)
        if todo:
            self.misses += len(todo)
            batch = getattr(self.backend, f"{method}_batch", None)
            if batch is not None:
                computed = batch([xs[i] for i in todo], [hints[i] for i in todo], None)
            else:  # a backend without batches: one call per input
                computed = [dict(enumerate(getattr(self.backend, method)(xs[i], **hints[i]))) for i in todo]
            for i, maps in zip(todo, computed):
                out[i] = self._store(paths[i], [maps[k] for k in sorted(maps)], self.half)
        return [{k: maps[k] for k in keep} for maps in out]

    def _cached(self, method: str, inputs: tuple, compute, half: bool) -> list[np.ndarray]:
        path = self.path(method, inputs)
        if path.is_file():
            self.hits += 1
            return self._load(path, half)
        self.misses += 1
        return self._store(path, compute(), half)

    @staticmethod
    def _load(path: Path, half: bool) -> list[np.ndarray]:
        with np.load(path) as f:
            arrays = [f[f"arr_{i}"] for i in range(len(f.files))]
        return [a.astype(np.float32) if half else a for a in arrays]

    @staticmethod
    def _store(path: Path, arrays, half: bool) -> list[np.ndarray]:
        arrays = [np.asarray(a) for a in arrays]
        stored = [a.astype(np.float16) if half else a for a in arrays]
        if half:  # the first run sees what every later run will read back
            arrays = [a.astype(np.float32) for a in stored]
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, *stored)
        os.replace(tmp, path)  # atomic: readers never see a half-written file
        return arrays
