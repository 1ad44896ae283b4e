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
of the backend's full identity (:func:`backend_identity`: its class, every plain setting such
as the stub's noise or the tiny model's seed, its dtype and device, its weights folder (a
relative path resolved against the working directory) and the size and SHA-256 of every weight
file, the library version and a hash of the backends' code), the method, ``params``, the
storage precision (``half``) and every input array (dtype, shape, bytes). The content hashes
are computed once per file version (:func:`freereg_lib.models.weightcheck.file_sha256`, remembered by
path, size, inode and change time in ``<cache_dir>/weight_hashes.json``), so weights rewritten
with the same size and modification time (``cp -p``, ``rsync -a``, ``tar``) are still seen.
Each entry stores its key and is checked on read; an entry that cannot be read or holds another
key is reported (a warning naming its path), removed and computed again.
Size: the nine decoder layers of one 512 x 704 input are about 20 MB in float32 (layer 6
alone 7 MB); ``half=True`` stores diffusion layers as float16 (half that, returned as
float32, relative error ~1e-3; entries of their own). Writes are atomic, so an interrupted run
leaves no broken entry; delete the folder to clear the cache.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
import zipfile
from pathlib import Path

import numpy as np

from freereg_lib.models.base import Backend, _hints, check_layers
from freereg_lib.models.weightcheck import MODEL_FILES, WEIGHT_SUFFIXES, file_sha256

# The config fields that change a backend's outputs (see FreeRegConfig). batched_guidance and
# pair_batch only batch the same computation (float rounding apart) and share entries.
FEATURE_FIELDS = ("outdoor", "resize_hw", "t_hat", "ddim_steps", "ddim_eta", "guidance_w", "controlnet_scale",
                  "prompt", "negative_prompt", "seed", "sd_unet_variant", "controlnet", "dtype")


def feature_params(cfg, resize_hw: tuple[int, int] | None = None) -> dict:
    """The cache-relevant fields of ``cfg`` (:data:`FEATURE_FIELDS`) as a plain dict.

    Pass ``resize_hw`` when the backend was built with a size other than ``cfg.resize_hw``.
    """
    params = {name: getattr(cfg, name) for name in FEATURE_FIELDS}
    if resize_hw is not None:
        params["resize_hw"] = tuple(resize_hw)
    return params


_SKIP = object()


def _plain(value):
    """``value`` as plain JSON data, or ``_SKIP`` for objects that are not settings (models)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if type(value) in (tuple, list):
        items = [_plain(v) for v in value]
        return _SKIP if any(v is _SKIP for v in items) else items
    if type(value) is dict:  # not a Counter or other state kept by the backend
        items = {str(k): _plain(v) for k, v in value.items()}
        return _SKIP if any(v is _SKIP for v in items.values()) else items
    if isinstance(value, np.ndarray):
        return f"array {value.dtype.str}{value.shape} sha256 {hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()}"
    if type(value).__module__.split(".")[0] == "torch" and type(value).__name__ in ("device", "dtype"):
        return str(value)
    return _SKIP


_PATH_WORDS = ("dir", "path", "file", "weight", "checkpoint", "ckpt", "controlnet", "folder")


def _as_path(value, key: str = "") -> Path | None:
    """The existing file or folder ``value`` names, resolved (a relative path against the working
    directory), or None. A relative string counts only when it looks like a path (a ``/``, a
    leading ``.`` or ``~``) or its setting's name does (``weights_dir``, ``checkpoint``, ...)."""
    if not isinstance(value, (str, os.PathLike)):
        return None
    text = os.fspath(value)
    if not text:
        return None
    path = Path(text).expanduser()
    pathlike = (isinstance(value, os.PathLike) or path.is_absolute() or "/" in text or text.startswith((".", "~"))
                or any(w in key.lower() for w in _PATH_WORDS))
    if not pathlike:
        return None
    try:
        return path.resolve() if path.exists() else None
    except OSError:
        return None


def _weight_files(value, found: dict, key: str = "", memo_file=None) -> None:
    """``found[path] = [size, sha256]`` for every weight file ``value`` names (paths, in dicts /
    lists too): a file itself, or the weight and model-config files under a folder
    (:data:`~freereg_lib.models.weightcheck.WEIGHT_SUFFIXES`, ``config.json``, ...)."""
    if isinstance(value, dict):
        for k, v in value.items():
            _weight_files(v, found, f"{key}.{k}", memo_file)
    elif isinstance(value, (tuple, list)):
        for v in value:
            _weight_files(v, found, key, memo_file)
    else:
        path = _as_path(value, key)
        if path is None:
            return
        files = [path] if path.is_file() else sorted(
            f for f in path.rglob("*") if f.is_file() and (f.name.endswith(WEIGHT_SUFFIXES) or f.name in MODEL_FILES))
        for f in files:
            found[str(f)] = [f.stat().st_size, file_sha256(f, memo_file)]


def _resolved(value, key: str = ""):
    """A plain setting with every relative path that exists replaced by its absolute path."""
    if isinstance(value, dict):
        return {k: _resolved(v, f"{key}.{k}") for k, v in value.items()}
    if isinstance(value, list):
        return [_resolved(v, key) for v in value]
    path = _as_path(value, key)
    return str(path) if path is not None else value


_CODE_HASH: list[str] = []


def _backend_code_hash() -> str:
    if not _CODE_HASH:
        root = Path(__file__).resolve().parents[1] / "models"
        h = hashlib.sha256()
        for f in sorted(root.glob("*.py")):
            h.update(f.name.encode() + b"\0" + f.read_bytes())
        _CODE_HASH.append(h.hexdigest()[:16])
    return _CODE_HASH[0]


def backend_identity(backend, memo_file=None) -> dict:
    """What makes ``backend``'s outputs what they are, besides the inputs and ``params``.

    Its class; every attribute that is a plain setting (numbers, strings, tuples, paths, torch
    dtype and device: the stub's noise, the tiny model's seed, the real backend's weights
    folder, ...; models, ``_private`` caches, counters and the config object are left out, the config's relevant
    fields are ``params``), relative paths resolved; the size and SHA-256 of every weight file
    its paths name (:func:`_weight_files`; ``memo_file`` remembers the hashes across runs); the
    library version and a hash of the backends' code.
    """
    from freereg_lib import __version__

    settings, weights = {}, {}
    for k, v in sorted(vars(backend).items()):
        plain = _plain(v)
        if plain is not _SKIP and not k.startswith("_"):  # _private: caches, lazy models
            settings[k] = _resolved(plain, k)
            _weight_files(v, weights, k, memo_file)
    kind = type(backend)
    return {"class": f"{kind.__module__}.{kind.__qualname__}", "name": getattr(backend, "name", None),
            "settings": settings, "weights": weights, "library": __version__, "code": _backend_code_hash()}


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
        self.repaired = 0
        self.identity = backend_identity(backend, self.cache_dir / "weight_hashes.json")
        # Files the params name (a single-file ControlNet checkpoint) count with their content too.
        params_files: dict = {}
        _weight_files(self.params, params_files, "", self.cache_dir / "weight_hashes.json")
        # default=str: tuples, paths and numbers all serialise the same way every run.
        self._params_blob = json.dumps({"params": _resolved(self.params), "params_files": params_files,
                                        "backend": self.identity, "half": bool(half)},
                                       sort_keys=True, default=str).encode()

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
            loaded = self._read(path, self.half)
            if loaded is not None:
                self.hits += 1
                out[i] = loaded
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
        loaded = self._read(path, half)
        if loaded is not None:
            self.hits += 1
            return loaded
        self.misses += 1
        return self._store(path, compute(), half)

    def _read(self, path: Path, half: bool) -> list[np.ndarray] | None:
        """The entry at ``path``, or None when there is none. An entry that cannot be read
        or holds another key than its name is reported, removed and so computed again."""
        if not path.is_file():
            return None
        try:
            return self._load(path, half)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            warnings.warn(f"feature cache: {path} is corrupt ({type(exc).__name__}: {exc}); "
                          "removed, computing it again", RuntimeWarning, stacklevel=3)
            path.unlink(missing_ok=True)
            self.repaired += 1
            return None

    @staticmethod
    def _load(path: Path, half: bool) -> list[np.ndarray]:
        with np.load(path, allow_pickle=False) as f:
            stored_key = str(f["__key__"]) if "__key__" in f.files else None
            if stored_key != path.stem:
                raise ValueError(f"it holds the entry of key {stored_key}, not {path.stem}")
            n = sum(1 for name in f.files if name.startswith("arr_"))
            arrays = [f[f"arr_{i}"] for i in range(n)]
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
            np.savez(f, *stored, __key__=np.array(path.stem))
        os.replace(tmp, path)  # atomic: readers never see a half-written file
        return arrays
