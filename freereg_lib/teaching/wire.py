"""Inputs and answers as data: arrays in an ``.npz`` and the structure around them as JSON.

The student's process writes its answers with :func:`save`; the grader reads them with
:func:`load` (``np.load(allow_pickle=False)``, numeric arrays only, a size cap, a depth cap):
nothing the student writes is ever executed or unpickled by the grader. Values that travel:
``None``, bools, ints, floats (NaN and inf included), strings, tuples, lists, dicts with
string keys, NumPy arrays and scalars of bool / integer / float dtype. It imports only the
standard library and NumPy: it runs in the student's process too (see :mod:`.student`).
"""
from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

META = "__structure__"
MAX_BYTES = 64 * 2**20   # an answers file larger than this is not read
MAX_DEPTH = 8
_KINDS = "biuf"          # bool, int, unsigned, float


class WireError(ValueError):
    """Data that is not a value of the format (wrong type, too big, too deep, unreadable)."""


def encode(obj: Any, arrays: dict[str, np.ndarray], depth: int = 0) -> Any:
    """``obj`` as JSON-able structure; its arrays go into ``arrays`` (referenced by key)."""
    if depth > MAX_DEPTH:
        raise WireError("nested too deeply")
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, float)):
        return {"num": repr(obj)} if isinstance(obj, float) and not np.isfinite(obj) else obj
    if isinstance(obj, np.generic):
        obj = np.asarray(obj)
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in _KINDS:
            raise WireError(f"an array of dtype {obj.dtype} is not numbers")
        key = f"a{len(arrays)}"
        arrays[key] = np.ascontiguousarray(obj)
        return {"nd": key}
    if isinstance(obj, (tuple, list)):
        return {"tuple" if isinstance(obj, tuple) else "list": [encode(x, arrays, depth + 1) for x in obj]}
    if isinstance(obj, dict):
        if not all(isinstance(k, str) for k in obj):
            raise WireError("dict keys must be strings")
        return {"dict": {k: encode(v, arrays, depth + 1) for k, v in obj.items()}}
    raise WireError(f"a {type(obj).__name__} is not numbers")


def decode(data: Any, arrays: dict[str, np.ndarray], depth: int = 0) -> Any:
    """The value :func:`encode` described."""
    if depth > MAX_DEPTH:
        raise WireError("nested too deeply")
    if data is None or isinstance(data, (bool, int, float, str)):
        return data
    if isinstance(data, dict) and len(data) == 1:
        (tag, value), = data.items()
        if tag == "num" and value in ("nan", "inf", "-inf"):
            return float(value)
        if tag == "nd":
            if value not in arrays:
                raise WireError(f"no array {value!r}")
            return arrays[value]
        if tag in ("tuple", "list") and isinstance(value, list):
            items = [decode(x, arrays, depth + 1) for x in value]
            return tuple(items) if tag == "tuple" else items
        if tag == "dict" and isinstance(value, dict):
            return {str(k): decode(v, arrays, depth + 1) for k, v in value.items()}
    raise WireError(f"not a value of the format: {str(data)[:80]}")


def save(path: str | Path, obj: Any) -> None:
    """Write ``obj`` to ``path`` (an ``.npz``), atomically (a reader never sees half a file)."""
    arrays: dict[str, np.ndarray] = {}
    structure = encode(obj, arrays)
    arrays[META] = np.frombuffer(json.dumps(structure).encode(), dtype=np.uint8)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def load(path: str | Path, max_bytes: int = MAX_BYTES) -> Any:
    """Read what :func:`save` wrote; :class:`WireError` for anything else (never unpickles)."""
    path = Path(path)
    try:
        if path.is_symlink() or not path.is_file():
            raise WireError(f"{path.name}: not a plain file")
        if path.stat().st_size > max_bytes:
            raise WireError(f"{path.name}: larger than {max_bytes // 2**20} MiB")
        with np.load(path, allow_pickle=False) as z:
            total = sum(z.zip.getinfo(n).file_size for n in z.zip.namelist())
            if total > 4 * max_bytes:
                raise WireError(f"{path.name}: unpacks to more than {4 * max_bytes // 2**20} MiB")
            arrays = {k: z[k] for k in z.files}
    except WireError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise WireError(f"{path.name}: not readable as data ({type(e).__name__}: {str(e)[:120]})") from None
    meta = arrays.pop(META, None)
    if meta is None or meta.dtype != np.uint8 or meta.ndim != 1:
        raise WireError(f"{path.name}: no structure")
    for k, a in arrays.items():
        if a.dtype.kind not in _KINDS:
            raise WireError(f"{path.name}: array {k} of dtype {a.dtype} is not numbers")
    try:
        return decode(json.loads(meta.tobytes().decode()), arrays)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise WireError(f"{path.name}: structure is not JSON of the format ({str(e)[:120]})") from None
