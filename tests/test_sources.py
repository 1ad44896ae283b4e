"""Honest samples: ``n_pairs`` of a fixed pair list is an evenly spread subset, not
the list's first ``n`` (on 7-Scenes those are one scene's smallest motions, where matching each
pixel to the same pixel of the other view beat FreeReg-D), and the notebooks can say which."""
from __future__ import annotations

import pytest

from freereg_lib.data import sources
from freereg_lib.data.datasets import pairlists
from freereg_lib.data.datasets.icl import ICLSample


def test_spread_takes_first_last_and_evenly_between():
    assert sources.spread(10, 4) == [0, 3, 6, 9]
    assert sources.spread(78, 2) == [0, 77] and sources.spread(5, 1) == [0]
    assert sources.spread(5, None) == [0, 1, 2, 3, 4] == sources.spread(5, 9)
    assert sources.spread(5, 0) == []
    for n in range(1, 30):
        idx = sources.spread(29, n)
        assert len(idx) == n and idx == sorted(set(idx)) and idx[0] == 0 and (n == 1 or idx[-1] == 28)


def test_icl_n_pairs_are_spread_over_the_list_not_its_first():
    listed = [f"icl/{i:05d}-{j:05d}" for i, j in ICLSample().pair_list()]
    names = [p.name for p in sources.iter_pairs("icl", 4)]
    assert names != listed[:4]  # the first four are image 0 against its next four frames
    assert names[0] == listed[0] and names[-1] == listed[-1] and len(set(names)) == 4
    assert len({n.split("/")[1].split("-")[0] for n in names}) == 4  # four different image frames
    assert sources.selection("icl", 4)["names"] == names
    # Shards split the same selection.
    shards = [[p.name for p in sources.iter_pairs("icl", 4, shard=f"{k}/2")] for k in range(2)]
    assert sorted(shards[0] + shards[1]) == sorted(names)
    text = sources.describe_selection("icl", 4)
    assert "4 of its" in text and "spread evenly" in text and names[1] in text


class _Listed(pairlists.PairSource):
    dataset = "3dmatch"

    def __init__(self, n):
        self.entries = [pairlists.PairEntry("scene", str(k), str(k + 1), 0.5) for k in range(n)]

    def pair_list(self):
        return self.entries

    def pair(self, entry):
        raise FileNotFoundError(f"no files for {entry.key} in this test")  # recorded, not raised


def test_on_disk_n_pairs_are_spread_and_unreadable_ones_recorded(monkeypatch):
    monkeypatch.setattr(sources, "open_dataset", lambda name, root, **kw: _Listed(10))
    got = list(sources.iter_pairs("3dmatch", 3, root="anywhere"))
    assert [p.name for p in got] == ["3dmatch/scene/0-1", "3dmatch/scene/4-5", "3dmatch/scene/9-10"]
    assert all(type(p).__name__ == "UnreadablePair" for p in got)
    assert sources.selection("3dmatch", 3, root="anywhere")["indices"] == [0, 4, 9]
    assert len(list(sources.iter_pairs("3dmatch", None, root="anywhere"))) == 10
    with pytest.raises(ValueError, match="pass root="):
        list(sources.iter_pairs("3dmatch", 3))


def test_first_readable_skips_unreadable_pairs_and_reads_no_further(tmp_path):
    from test_loaders import POSES, make_scannet

    from freereg_lib.data.pair import UnreadablePair

    # Frames 0, 20 and 40: pairs (0, 20), (0, 40), (20, 40); frame 0's image is broken.
    root = make_scannet(tmp_path, frames={f: POSES[min(f // 20, 2)] for f in range(41)})[0]
    (root / "scene0707_00" / "color" / "0.jpg").write_bytes(b"\xff\xd8\xff not a jpeg")
    pairs = list(sources.iter_pairs("scannet", 3, root=str(root)))
    assert [type(p).__name__ for p in pairs] == ["UnreadablePair", "UnreadablePair", "Pair"]
    assert sources.first_readable(pairs) is pairs[2]

    def then_fail():
        yield from pairs
        raise AssertionError("read past the first readable pair")

    assert sources.first_readable(then_fail()) is pairs[2]
    # None readable: the first one, which raises its own error when used; none at all: None.
    assert sources.first_readable(pairs[:2]) is pairs[0]
    with pytest.raises(Exception, match="0.jpg"):
        pairs[0].validate()
    assert sources.first_readable([]) is None
    assert isinstance(sources.first_readable(iter(pairs[1:2])), UnreadablePair)
