"""The README's gallery: compact copies of the key figures of a run, committed under ``figures/gallery/``.

``make reproduce`` calls :func:`write_gallery` after the notebooks ran (``freereg_lib.commands.reproduce``);
:data:`GALLERY` is the list of figures the README shows. They are drawn from committed numbers only
(:mod:`freereg_lib.report.committed_charts`), so a run on another CPU leaves them byte for byte as committed;
the one-pair pictures from the committed arrays of their pair, which

    python -m freereg_lib.commands.gallery --record-pictures runs/reproduce

replaces with a run's (only when the micro models or the pictures' code change on purpose). Beside the figures, ``FINGERPRINT.json`` holds
the SHA-256 of every file that drew them (:data:`FINGERPRINT_INPUTS`: the notebooks that draw them, the
library, the micro weights' checksum lists and the committed results the verdicts read), so
:func:`stale_inputs` names each file changed since the gallery was drawn (``tests/test_gallery.py``).
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Sequence

from freereg_lib.report.plots import compact_png

ROOT = Path.cwd()  # the project folder the command runs in (make runs there); never where this file lies
GALLERY_DIR = ROOT / "figures" / "gallery"
FINGERPRINT = "FINGERPRINT.json"

# The README's gallery: the key figures of the default run, each drawn from committed numbers (the
# test split's results) or committed arrays (the one-pair pictures), so they are the same on every machine.
GALLERY: tuple[str, ...] = ("01_pca_layers_committed", "03_matches_d_g_fused_committed", "04_table1_committed",
                            "04_rr_ladder_committed", "03_table4_committed", "01_table2_committed")
# The one-pair pictures' arrays: (the run's notebook folder, picture name); see :func:`record_pictures`.
PICTURES: tuple[tuple[str, str], ...] = (("01_diffusion_features", "01_pca_layers"), ("03_fusion", "03_matches_d_g_fused"))


# What draws the gallery, as globs under the project folder.
FINGERPRINT_INPUTS: tuple[str, ...] = (
    "notebooks/01_*.ipynb", "notebooks/03_*.ipynb", "notebooks/04_*.ipynb",
    "freereg_lib/*.py", "freereg_lib/geometry/**/*.py", "freereg_lib/data/**/*.py", "freereg_lib/models/**/*.py",
    "freereg_lib/features/**/*.py", "freereg_lib/pipeline/**/*.py", "freereg_lib/report/**/*.py",
    "freereg_lib/training/**/*.py", "freereg_lib/data/paper_tables/*.csv",
    "freereg_lib/models/micro/weights/*/SHA256SUMS", "freereg_lib/models/micro/weights/*.json",
    "freereg_lib/models/micro/weights/pictures/*",
)


def _digest(path: Path) -> str:
    data = path.read_bytes()
    if path.suffix == ".ipynb":  # what the notebook says, not what a run left in it
        nb = json.loads(data)
        data = json.dumps([[c.get("cell_type"), "".join(c.get("source", ""))] for c in nb.get("cells", [])]).encode()
    return hashlib.sha256(data).hexdigest()


def fingerprint(root: Path = ROOT, inputs: Sequence[str] = FINGERPRINT_INPUTS) -> dict[str, str]:
    """``{path: sha256}`` of every file under ``root`` that :data:`FINGERPRINT_INPUTS` names."""
    root = Path(root)
    files = sorted({p for pattern in inputs for p in root.glob(pattern) if p.is_file() and "__pycache__" not in p.parts})
    return {p.relative_to(root).as_posix(): _digest(p) for p in files}


def stale_inputs(root: Path = ROOT, gallery: Path = GALLERY_DIR, inputs: Sequence[str] = FINGERPRINT_INPUTS) -> list[str]:
    """The inputs changed, added or removed since ``gallery`` was drawn, each as ``"path (how)"``."""
    recorded = json.loads((Path(gallery) / FINGERPRINT).read_text(encoding="utf-8"))["files"]
    now = fingerprint(root, inputs)
    out = [f"{p} (changed)" for p in sorted(set(now) & set(recorded)) if now[p] != recorded[p]]
    out += [f"{p} (new)" for p in sorted(set(now) - set(recorded))]
    out += [f"{p} (removed)" for p in sorted(set(recorded) - set(now))]
    return out


def write_gallery(figures_dir: Path, out: Path = GALLERY_DIR, names: Sequence[str] = GALLERY,
                  max_width: int = 1000, max_bytes: int = 400_000, root: Path = ROOT) -> list[Path]:
    """Compact copies of the gallery's figures of ``figures_dir`` in ``out`` (missing ones are skipped,
    and named on stderr), and ``FINGERPRINT.json`` when every figure was drawn. Returns the files written."""
    written = []
    for name in names:
        src = Path(figures_dir) / f"{name}.png"
        if not src.is_file():
            print(f"gallery: {src} is missing (not drawn in this run); kept the old copy if any", file=sys.stderr)
            continue
        written.append(compact_png(src, Path(out) / f"{name}.png", max_width, max_bytes))
    if len(written) == len(names):
        print_ = {"what": "SHA-256 of the files that drew these figures (freereg_lib.commands.gallery)", "files": fingerprint(root)}
        (Path(out) / FINGERPRINT).write_text(json.dumps(print_, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return written


def record_pictures(run: Path, dest: Path | None = None) -> list[Path]:
    """Copy the one-pair pictures' arrays of a default run (``<run>/<notebook>/pictures/<name>.npz`` and
    ``.json``) to the committed folder; ``FileNotFoundError`` naming the first one missing."""
    import shutil

    from freereg_lib.report.committed_charts import picture_path

    copied = []
    for stem, name in PICTURES:
        for suffix in (".npz", ".json"):
            src = Path(run) / stem / "pictures" / f"{name}{suffix}"
            if not src.is_file():
                raise FileNotFoundError(f"{src}: not in the run (run the default notebooks first: make reproduce)")
            dst = (Path(dest) / name if dest else picture_path(name)).with_suffix(suffix)
            dst.parent.mkdir(parents=True, exist_ok=True)
            copied.append(Path(shutil.copyfile(src, dst)))
    return copied


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m freereg_lib.commands.gallery", description=__doc__.split("\n")[0])
    ap.add_argument("--record-pictures", metavar="RUN", required=True,
                    help="copy the one-pair pictures' arrays of this run folder to the committed ones")
    args = ap.parse_args(argv)
    try:
        copied = record_pictures(Path(args.record_pictures))
    except FileNotFoundError as exc:
        ap.error(str(exc))
    print("recorded: " + ", ".join(str(p) for p in copied))
    return 0


if __name__ == "__main__":
    sys.exit(main())
