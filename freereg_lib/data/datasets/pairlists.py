"""Pair lists, and what every dataset loader shares.

A benchmark's pairs are fixed in a text file: the list is built once from the dataset (an
overlap or distance rule), written next to the data or to a path the user gives, and read
back on every later run, so the pairs are the same on every machine and can be cited::

    # freereg pair list
    # dataset: 3dmatch
    # rule: overlap > 0.3
    # source: /data/3dmatch
    # columns: scene image_frame cloud_frame score
    7-scenes-redkitchen 0 12 0.5512

``score`` is the quantity the rule tested (an overlap fraction, or a distance in metres).
A pair is the RGB image of ``image_frame`` against the point cloud of ``cloud_frame``.
Every loader is a :class:`PairSource`; the registry :func:`freereg_lib.data.datasets.registry.open_dataset`,
which sits above the loaders, builds one by name (the loaders never import it).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from freereg_lib.data.pair import Pair, load_or_record
from freereg_lib.data.shards import shard_items
from freereg_lib.geometry import cameras

HEADER = "# freereg pair list"


@dataclass(frozen=True)
class PairEntry:
    """One line of a pair list. Frames are kept as the strings the dataset names them by."""

    scene: str
    image_frame: str
    cloud_frame: str
    score: float

    @property
    def key(self) -> str:
        return f"{self.scene}/{self.image_frame}-{self.cloud_frame}"


def write_pair_list(path: str | Path, entries: list[PairEntry], dataset: str, rule: str, source: str = "") -> Path:
    """Write ``entries`` with a header naming ``dataset``, ``rule`` and ``source``."""
    path = Path(path)
    lines = [HEADER, f"# dataset: {dataset}", f"# rule: {rule}", f"# source: {source}",
             "# columns: scene image_frame cloud_frame score"]
    for e in entries:
        if any(len(str(v).split()) != 1 for v in (e.scene, e.image_frame, e.cloud_frame)):
            raise ValueError(f"pair list fields must be single words without spaces: {e}")
        lines.append(f"{e.scene} {e.image_frame} {e.cloud_frame} {e.score:.6g}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # Atomic, because the shards of a batch run may build the same list at once.
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text("\n".join(lines) + "\n")
        tmp.replace(path)
    except OSError as exc:
        raise OSError(f"cannot write the pair list {path} ({exc}); pass pair_list=<a writable path>") from exc
    return path


def read_pair_list(path: str | Path) -> tuple[dict[str, str], list[PairEntry]]:
    """The header fields (``dataset``, ``rule``, ``source``) and the entries of a pair list."""
    path = Path(path)
    text = path.read_text().splitlines()
    if not text or text[0].strip() != HEADER:
        raise ValueError(f"{path} is not a pair list (its first line should be {HEADER!r})")
    header, entries = {}, []
    for n, line in enumerate(text[1:], start=2):
        if line.startswith("#"):
            key, _, value = line[1:].partition(":")
            header[key.strip()] = value.strip()
        elif line.strip():
            parts = line.split()
            if len(parts) != 4:
                raise ValueError(f"{path}:{n}: expected 'scene image_frame cloud_frame score', got {line!r}")
            entries.append(PairEntry(parts[0], parts[1], parts[2], float(parts[3])))
    return header, entries


def load_or_build(path: str | Path, dataset: str, rule: str, source: str,
                  build: Callable[[], list[PairEntry]]) -> list[PairEntry]:
    """The entries of the pair list at ``path``; built with ``build()`` and written first
    when the file does not exist. A file made for another dataset or rule is refused."""
    path = Path(path)
    if not path.is_file():
        entries = build()
        if not entries:
            raise ValueError(f"no pair of {source} satisfies '{rule}'; nothing to benchmark")
        write_pair_list(path, entries, dataset, rule, source)
        return entries
    header, entries = read_pair_list(path)
    if (header.get("dataset"), header.get("rule")) != (dataset, rule):
        raise ValueError(
            f"{path} lists {header.get('dataset')} pairs with rule '{header.get('rule')}', not "
            f"{dataset} with '{rule}'; pass another pair_list path, or delete the file to rebuild it"
        )
    return entries


class PairSource:
    """A dataset loader: a fixed pair list and the :class:`Pair` of each entry.

    Subclasses set ``dataset`` and implement ``pair_list()`` and ``pair(entry)``.
    """

    dataset = "base"

    def pair_list(self) -> list[PairEntry]:
        raise NotImplementedError

    def pair(self, entry: PairEntry) -> Pair:
        raise NotImplementedError

    def __len__(self) -> int:
        return len(self.pair_list())

    def pairs(self, n: int | None = None, shard: str = "0/1") -> Iterator[Pair]:
        """The pairs of the first ``n`` entries (all with None), shard ``shard`` of them.

        The list is cut to ``n`` before sharding, so n shards together cover exactly the
        pairs of one unsharded run. A pair whose files cannot be read comes as an
        :class:`~freereg_lib.data.pair.UnreadablePair` holding the error, so a benchmark records
        it and goes on (``pair(entry)`` raises it directly).
        """

        entries = self.pair_list()[: n if n is not None else None]
        for entry in shard_items(entries, shard):
            name = entry.key if entry.key.startswith(f"{self.dataset}/") else f"{self.dataset}/{entry.key}"
            yield load_or_record(name, self.pair, entry)


# --------------------------------------------------------------------------------------
# Pieces the loaders share.

def require(path: str | Path, what: str, layout: str) -> Path:
    """``path`` when it exists, else a ``FileNotFoundError`` naming it and the layout expected."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"missing {what}: {path}\nexpected layout:\n{layout}")
    return path


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied ``voxel``-sized cell (the mean of its points), ``(M, 3)``.

    The same as Open3D's ``voxel_down_sample``, in NumPy; cells come out in lexicographic
    order of their integer coordinates, so the result is deterministic.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return pts.copy()
    cells = np.floor(pts / voxel).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, pts)
    return sums / counts[:, None]


def depth_in_image(depth: np.ndarray, K_depth: np.ndarray, K_image: np.ndarray,
                   image_size: tuple[int, int]) -> np.ndarray:
    """A depth map ``(H_d, W_d)`` seen by a co-located camera with other intrinsics.

    Both cameras share centre and orientation (ScanNet's colour and depth sensors after
    registration), so a colour pixel sees along the same ray as the depth pixel
    ``K_depth @ inv(K_image) @ (u, v, 1)``, at the same z; each colour pixel takes that
    depth pixel's value (nearest, 0 outside). Returns ``(H, W) float64`` for
    ``image_size = (H, W)``. With equal intrinsics and sizes it is a copy.
    """
    H, W = image_size
    grid = cameras.pixel_grid(H, W).reshape(-1, 2)
    rays = np.concatenate([grid, np.ones((len(grid), 1))], axis=1) @ np.linalg.inv(K_image).T
    uv, _ = cameras.project(rays, K_depth)
    u, v = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    Hd, Wd = depth.shape
    inside = (u >= 0) & (u < Wd) & (v >= 0) & (v < Hd)
    out = np.zeros(H * W)
    out[inside] = np.asarray(depth, dtype=np.float64)[v[inside], u[inside]]
    return out.reshape(H, W)
