"""The README's gallery: compact copies of the key figures of a run, committed under ``figures/gallery/``.

``make reproduce`` calls :func:`write_gallery` after the notebooks ran (``freereg_lib.commands.reproduce``);
:data:`GALLERY` is the list of figures the README shows.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

from freereg_lib.report.plots import compact_png

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
GALLERY_DIR = ROOT / "figures" / "gallery"

# The README's gallery: the key figures of the default run.
GALLERY: tuple[str, ...] = ("01_pca_layers", "03_matches_d_g_fused", "04_table1_side_by_side", "04_rr_ladder",
                            "03_table4_fusion_weight", "01_table2_ir")


def write_gallery(figures_dir: Path, out: Path = GALLERY_DIR, names: Sequence[str] = GALLERY,
                  max_width: int = 1000, max_bytes: int = 400_000) -> list[Path]:
    """Compact copies of the gallery's figures of ``figures_dir`` in ``out`` (missing ones are skipped,
    and named on stderr). Returns the files written."""
    written = []
    for name in names:
        src = Path(figures_dir) / f"{name}.png"
        if not src.is_file():
            print(f"gallery: {src} is missing (not drawn in this run); kept the old copy if any", file=sys.stderr)
            continue
        written.append(compact_png(src, Path(out) / f"{name}.png", max_width, max_bytes))
    return written
