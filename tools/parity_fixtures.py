"""The parity command's files in and lines out (``tools/parity.py``): reading the fixtures
(``<function>/<case>.npz`` and ``manifest.json``), with one line naming the file for each that
cannot be read, and the result line of a function."""
from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np


class BadFixture(ValueError):
    """A fixture file or manifest that cannot be read; its message names the file."""


def load_case(path: Path) -> tuple[dict, dict]:
    """``(inputs, outputs)`` of one ``.npz`` fixture, keyed without the ``in_`` / ``out_`` prefix.
    Raises :class:`BadFixture` naming ``path`` for a file that is no readable ``.npz`` (empty,
    cut, text, a folder, pickled objects), a key that is neither ``in_*`` nor ``out_*`` (``OUT_x``
    compares nothing), and a case with no ``out_*`` array (nothing to compare: not a pass)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            ins = {k[3:]: z[k] for k in z.files if k.startswith("in_")}
            outs = {k[4:]: z[k] for k in z.files if k.startswith("out_")}
            odd = [k for k in z.files if not k.startswith(("in_", "out_"))]
    except (OSError, ValueError, EOFError, KeyError, AttributeError, zipfile.BadZipFile) as exc:
        raise BadFixture(f"{path}: not a readable .npz fixture ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:120] or 'empty'})") from None
    if odd:
        raise BadFixture(f"{path}: key(s) {odd} are neither in_<name> nor out_<name> (lower case)")
    if not outs:
        raise BadFixture(f"{path}: no out_<name> array: the case has no expected output to compare")
    return ins, outs


def read_manifest(path: Path) -> dict:
    """The ``functions`` object of ``manifest.json`` (``{}`` when there is no such file);
    :class:`BadFixture` naming it when it is not JSON of that shape."""
    if not path.exists():
        return {}
    try:
        manifest = json.loads(path.read_text()).get("functions", {})
        if not isinstance(manifest, dict):
            raise ValueError(f"'functions' is a {type(manifest).__name__}, not an object")
    except (OSError, ValueError, UnicodeDecodeError, AttributeError) as exc:
        raise BadFixture(f"{path}: not a fixture manifest ({' '.join(str(exc).split())[:120]}); expected JSON "
                         '{"functions": {"<name>": {...}}}') from None
    return manifest


def _fmt(x: float) -> str:
    if x == 0:
        return "0"
    if math.isinf(x):
        return "inf"
    return f"{x:.3g}"


def format_line(r: dict) -> str:
    if r["status"] == "skipped":
        return f"{r['name']}: skipped ({r['reason']})"
    line = f"{r['name']}: max error {_fmt(r['error'])} (tolerance {_fmt(r['tol'])}) {r['status']}"
    if r["status"] == "FAIL" and r["reason"]:
        line += f" [{r['reason']}]"
    return line
