"""One entry point for "give me n pairs of dataset X", used by the notebooks and the batch runner.

``synthetic_indoor`` / ``synthetic_outdoor`` are generated (seeded); ``icl`` is the embedded
real sample; ``3dmatch``, ``scannet``, ``kitti`` and ``demo`` read a user-given ``root``.
"""
from __future__ import annotations

from typing import Iterator

from .pair import Pair, load_or_record

SYNTHETIC = ("synthetic_indoor", "synthetic_outdoor")
EMBEDDED = ("icl",)
ON_DISK = ("3dmatch", "scannet", "kitti", "kitti_dc", "demo")


def iter_pairs(
    dataset: str, n_pairs: int | None = None, seed: int = 0, root: str | None = None, shard: str = "0/1"
) -> Iterator[Pair]:
    """Yield up to ``n_pairs`` pairs of ``dataset`` (all of an on-disk dataset when None).

    ``seed`` picks the synthetic scenes; ``icl`` and the on-disk datasets have fixed pair
    lists (as the paper's benchmarks), so it does not change their pairs.
    ``shard="i/n"`` keeps pair k of the first ``n_pairs`` when ``k % n == i``, so n shards
    together cover exactly the pairs of one unsharded run.
    """
    from .batch import parse_shard

    index, count = parse_shard(shard)
    name = dataset.lower().replace("-", "_")
    if name in SYNTHETIC:
        from . import synthetic

        kind = name.split("_")[1]
        for k in range(index, n_pairs if n_pairs is not None else 10, count):
            pair_seed = seed * 1_000_003 + k
            yield load_or_record(f"synthetic-{kind}/seed{pair_seed:04d}", synthetic.make_pair, kind, seed=pair_seed)
        return
    if name == "icl":
        from .datasets.icl import ICLSample

        for k, pair in enumerate((ICLSample(root) if root else ICLSample()).pairs(n_pairs)):
            if k % count == index:
                yield pair
        return
    if name in ON_DISK:
        if root is None:
            raise ValueError(f"dataset {dataset!r} is read from disk: pass root=<its folder> (see README, 'Datasets')")
        from .datasets import open_dataset

        yield from open_dataset(name, root).pairs(n_pairs, shard=shard)
        return
    raise ValueError(f"unknown dataset {dataset!r}; expected one of {SYNTHETIC + EMBEDDED + ON_DISK}")


def config_name(dataset: str) -> str:
    """The :func:`~freereg_lib.config.config_for` name of ``dataset``."""
    return dataset.lower().replace("-", "_")
