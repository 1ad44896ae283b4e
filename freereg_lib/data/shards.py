"""Shards of a list of pairs: ``"i/n"`` takes item ``k`` when ``k % n == i``.

The batch runner (:mod:`freereg_lib.commands.batch`, which re-exports both), the notebooks and the dataset
loaders (:meth:`freereg_lib.data.datasets.pairlists.PairSource.pairs`) split work alike with these.
"""
from __future__ import annotations

import re


def parse_shard(shard: str) -> tuple[int, int]:
    """``"i/n"`` -> ``(i, n)``; raises ``ValueError`` unless ``0 <= i < n``."""
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(shard))
    if not m or not int(m[1]) < int(m[2]):
        raise ValueError(
            f"shard must be 'i/n' with 0 <= i < n (e.g. '0/1' for everything, '1/4' for the "
            f"second of four); got {shard!r}"
        )
    return int(m[1]), int(m[2])


def shard_items(items, shard: str) -> list:
    """Shard ``i/n`` of ``items``: item ``k`` goes to shard ``k % n`` (deterministic, in order).

    The ``n`` shards are disjoint and together hold every item. Cut a list to its first
    ``n_pairs`` *before* sharding, so a sharded benchmark covers the same pairs.
    """
    i, n = parse_shard(shard)
    return list(items)[i::n]
