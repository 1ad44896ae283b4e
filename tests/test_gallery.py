"""The README's gallery carries the fingerprint of what drew it (``figures/gallery/FINGERPRINT.json``):
a change to a notebook, library file, weight or committed result that draws it, made without drawing
the gallery again (``make reproduce``), fails here, naming the file."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image

from freereg_lib.commands import gallery as G

ROOT = Path(__file__).resolve().parent.parent


def _tree(root: Path) -> None:
    (root / "freereg_lib" / "geometry").mkdir(parents=True)
    (root / "freereg_lib" / "geometry" / "pose.py").write_text("def kabsch():\n    return 1\n")
    (root / "freereg_lib" / "config.py").write_text("X = 1\n")
    (root / "notebooks").mkdir()
    nb = {"cells": [{"cell_type": "code", "source": "plot()", "outputs": []}], "metadata": {}, "nbformat": 4, "nbformat_minor": 5}
    (root / "notebooks" / "01_diffusion_features.ipynb").write_text(json.dumps(nb))
    (root / "figures").mkdir()
    for name in G.GALLERY:
        Image.new("RGB", (40, 30), (200, 10, 10)).save(root / "figures" / f"{name}.png")


def test_a_change_to_what_draws_the_gallery_is_named(tmp_path):
    _tree(tmp_path)
    gallery = tmp_path / "figures" / "gallery"
    written = G.write_gallery(tmp_path / "figures", out=gallery, root=tmp_path)
    assert len(written) == len(G.GALLERY) and (gallery / G.FINGERPRINT).is_file()
    assert G.stale_inputs(tmp_path, gallery) == []
    # Running a notebook (outputs) is not a change; editing its code is.
    nb_path = tmp_path / "notebooks" / "01_diffusion_features.ipynb"
    nb = json.loads(nb_path.read_text())
    nb["cells"][0]["outputs"] = [{"output_type": "stream", "name": "stdout", "text": "ran"}]
    nb_path.write_text(json.dumps(nb))
    assert G.stale_inputs(tmp_path, gallery) == []
    (tmp_path / "freereg_lib" / "geometry" / "pose.py").write_text("def kabsch():\n    return 2\n")
    (tmp_path / "freereg_lib" / "geometry" / "metrics.py").write_text("Y = 0\n")
    (tmp_path / "freereg_lib" / "config.py").unlink()
    assert G.stale_inputs(tmp_path, gallery) == ["freereg_lib/geometry/pose.py (changed)",
                                                 "freereg_lib/geometry/metrics.py (new)", "freereg_lib/config.py (removed)"]
    G.write_gallery(tmp_path / "figures", out=gallery, root=tmp_path)  # drawn again: current
    assert G.stale_inputs(tmp_path, gallery) == []


def test_a_partial_gallery_writes_no_fingerprint(tmp_path):
    _tree(tmp_path)
    (tmp_path / "figures" / f"{G.GALLERY[0]}.png").unlink()
    G.write_gallery(tmp_path / "figures", out=tmp_path / "g", root=tmp_path)
    assert not (tmp_path / "g" / G.FINGERPRINT).exists()


def test_the_committed_gallery_matches_the_tree():
    recorded = ROOT / "figures" / "gallery" / G.FINGERPRINT
    if not recorded.is_file():
        pytest.skip("the committed gallery has no fingerprint yet: `make reproduce` writes one with the figures")
    stale = G.stale_inputs(ROOT, recorded.parent)
    assert not stale, ("the gallery was drawn before these files changed; run `make reproduce` and commit "
                       "figures/gallery/:\n" + "\n".join(stale))
