"""One entry point for "give me n pairs of dataset X", used by the notebooks and the batch runner.

``synthetic_indoor`` / ``synthetic_outdoor`` are generated (seeded); ``icl`` is the embedded
real sample; ``3dmatch``, ``scannet``, ``kitti`` and ``demo`` read a user-given ``root``.
"""
from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np

from freereg_lib.data import synthetic
from freereg_lib.data.datasets import open_dataset
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.pair import Pair, UnreadablePair, load_or_record
from freereg_lib.data.shards import parse_shard, shard_items

# "synthetic_rooms" is the indoor world calibrated against real rooms; "synthetic_indoor" the blocks
# world the committed micro models were trained and measured in.
SYNTHETIC = ("synthetic_indoor", "synthetic_outdoor", "synthetic_rooms")
EMBEDDED = ("icl",)
ON_DISK = ("3dmatch", "scannet", "kitti", "kitti_dc", "demo")


def spread(n_items: int, n: int | None) -> list[int]:
    """``n`` indices spread evenly over ``range(n_items)``, first and last included (all when
    ``n`` is None or not smaller; none for ``n <= 0``). A fixed pair list is ordered by scene
    and frame, so its first ``n`` entries are one scene's smallest motions: a sample that
    flatters every method; an evenly spread one covers the list."""
    if n is None or n >= n_items:
        return list(range(n_items))
    if n <= 0:
        return []
    return sorted({int(round(k)) for k in np.linspace(0, n_items - 1, n)})


def selection(dataset: str, n_pairs: int | None = None, root: str | None = None) -> dict:
    """Which pairs :func:`iter_pairs` takes from a fixed pair list (``icl`` and the on-disk
    datasets): ``{"names": [...], "indices": [...], "total": N}`` (indices into the full list).
    Synthetic datasets have no list: ``None``."""
    name = dataset.lower().replace("-", "_")
    if name in SYNTHETIC:
        return None
    keys = [f"icl/{i:05d}-{j:05d}" for i, j in _icl(root).pair_list()] if name == "icl" else \
        [_entry_name(name, e) for e in _on_disk(name, dataset, root).pair_list()]
    idx = spread(len(keys), n_pairs)
    return {"names": [keys[k] for k in idx], "indices": idx, "total": len(keys)}


def describe_selection(dataset: str, n_pairs: int | None = None, root: str | None = None, max_names: int = 12) -> str:
    """One sentence naming the pairs :func:`iter_pairs` takes (for the notebooks)."""
    sel = selection(dataset, n_pairs, root)
    if sel is None:
        return f"{dataset}: {n_pairs if n_pairs is not None else 10} generated pair(s) (seeded scenes, no fixed list)"
    names = sel["names"]
    shown = ", ".join(names[:max_names]) + (f", ... ({len(names) - max_names} more)" if len(names) > max_names else "")
    how = "all of them" if len(names) == sel["total"] else "spread evenly over the list, first and last included"
    return (f"{dataset}: {len(names)} of its {sel['total']} listed pairs, {how} (list positions "
            f"{_ranges(sel['indices'])}): {shown}")


def _ranges(idx: list[int]) -> str:
    if len(idx) > 8:
        return f"{idx[0]}, {idx[1]}, ..., {idx[-1]}, every ~{(idx[-1] - idx[0]) / max(len(idx) - 1, 1):.1f}"
    return ", ".join(str(i) for i in idx)


def _icl(root):

    return ICLSample(root) if root else ICLSample()


def _on_disk(name: str, dataset: str, root):
    if root is None:
        raise ValueError(f"dataset {dataset!r} is read from disk: pass root=<its folder> (see README, 'Datasets')")

    return open_dataset(name, root)


def _entry_name(name: str, entry) -> str:
    return entry.key if entry.key.startswith(f"{name}/") else f"{name}/{entry.key}"


def iter_pairs(
    dataset: str, n_pairs: int | None = None, seed: int = 0, root: str | None = None, shard: str = "0/1"
) -> Iterator[Pair]:
    """Yield up to ``n_pairs`` pairs of ``dataset`` (all of an on-disk dataset when None).

    ``seed`` picks the synthetic scenes; ``icl`` and the on-disk datasets have fixed pair
    lists (as the paper's benchmarks), so it does not change their pairs. From a fixed list
    ``n_pairs`` takes an evenly spread subset (:func:`spread`: first and last included), not
    the first ``n_pairs``; :func:`describe_selection` names them.
    ``shard="i/n"`` keeps the k-th selected pair when ``k % n == i``, so n shards together
    cover exactly the pairs of one unsharded run.
    """

    index, count = parse_shard(shard)
    name = dataset.lower().replace("-", "_")
    if name in SYNTHETIC:

        kind = name.split("_")[1]
        world = "rooms" if kind == "rooms" else "blocks"
        for k in range(index, n_pairs if n_pairs is not None else 10, count):
            pair_seed = seed * 1_000_003 + k
            synthetic.check_eval_seed(pair_seed)  # raised, not recorded: no pair may be a training room
            yield load_or_record(f"synthetic-{kind}/seed{pair_seed:04d}", synthetic.make_pair,
                                 "outdoor" if kind == "outdoor" else "indoor", seed=pair_seed, world=world)
        return
    if name == "icl":
        sample = _icl(root)
        listed = sample.pair_list()
        chosen = [listed[k] for k in spread(len(listed), n_pairs)]
        for k, (i, j) in enumerate(chosen):
            if k % count == index:
                yield load_or_record(f"icl/{i:05d}-{j:05d}", sample.pair, i, j)
        return
    if name in ON_DISK:
        src = _on_disk(name, dataset, root)
        listed = src.pair_list()
        chosen = [listed[k] for k in spread(len(listed), n_pairs)]
        for entry in shard_items(chosen, shard):
            yield load_or_record(_entry_name(name, entry), src.pair, entry)
        return
    raise ValueError(f"unknown dataset {dataset!r}; expected one of {SYNTHETIC + EMBEDDED + ON_DISK}")


def first_readable(pairs: Iterable[Pair | UnreadablePair]) -> Pair | UnreadablePair | None:
    """The first pair of ``pairs`` that could be read, taken without reading further (a pair
    to show before a benchmark whose unreadable pairs are its failed rows). When none could be
    read, the first :class:`~freereg_lib.data.pair.UnreadablePair`, whose fields raise its
    error; None when ``pairs`` is empty."""
    first = None
    for pair in pairs:
        if not isinstance(pair, UnreadablePair):
            return pair
        first = first or pair
    return first


def config_name(dataset: str) -> str:
    """The :func:`~freereg_lib.config.config_for` name of ``dataset``."""
    return dataset.lower().replace("-", "_")
