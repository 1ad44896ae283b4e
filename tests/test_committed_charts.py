"""The figures of committed results (freereg_lib.report.committed_charts): the same bytes from the same
numbers, intervals where they belong, and the one-pair pictures' arrays round-tripped."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from freereg_lib.commands import gallery
from freereg_lib.data import paper
from freereg_lib.report import committed_charts as C
from freereg_lib.report.plots import save


def _split(n=100):
    stat = {"mean": 20.0, "ci": [15.0, 25.0]}
    res = {f"{m} {s}": {"FMR": stat, "IR": stat, "RR": {"mean": 10.0, "ci": [5.0, 16.0]},
                        "ladder": {"RR@5deg/0.1m": 0.0, "RR@10deg/0.2m": 2.0, "RR@15deg/0.3m": 5.0,
                                   "RR@20deg/0.5m": 10.0, "RR@25deg/0.5m": 10.0}}
           for m, s in C.VARIANTS}
    return {"n_pairs": n, "backend": "micro backend (details)", "config": {"fusion_w": 0.5}, "results": res}


def test_wilson_interval_exact_values():
    lo, hi = C.wilson_interval(17.0, 100)
    assert (round(lo, 2), round(hi, 2)) == (10.89, 25.55)
    assert C.wilson_interval(0.0, 100)[0] == 0.0 and round(C.wilson_interval(0.0, 100)[1], 2) == 3.70


def test_table1_markdown_puts_the_paper_beside_each_committed_value():
    text = C.table1_markdown(_split(), paper.table("table1_main"))
    assert "committed test split: 100 synthetic indoor pairs, micro backend, 95 % intervals" in text
    assert "| FreeReg | kabsch | 20.0 [15.0, 25.0] | 94.6 | 20.0 [15.0, 25.0] | 47.0 | 10.0 [5.0, 16.0] | 63.8 |" in text
    assert "| FreeReg-D | kabsch | 20.0 [15.0, 25.0] | - |" in text  # the paper has no such row


@pytest.mark.parametrize("draw", ["table1", "rr_ladder", "table4"])
def test_a_committed_figure_is_the_same_bytes_from_the_same_numbers(draw, tmp_path):
    tables = {"table1": "table1_main", "rr_ladder": "table_pnp_vs_kabsch", "table4": "table4_fusion_weight"}
    digests = []
    for k in range(2):
        fig = getattr(C, draw)(_split(), paper.table(tables[draw]))
        digests.append(hashlib.sha256(save(fig, f"{draw}_{k}", tmp_path).read_bytes()).hexdigest())
    assert digests[0] == digests[1]
    other = _split()
    other["results"]["FreeReg kabsch"]["RR"] = {"mean": 11.0, "ci": [5.0, 17.0]}
    other["results"]["FreeReg kabsch"]["ladder"]["RR@25deg/0.5m"] = 11.0
    fig = getattr(C, draw)(other, paper.table(tables[draw]))
    assert hashlib.sha256(save(fig, f"{draw}_other", tmp_path).read_bytes()).hexdigest() != digests[0]


def test_picture_arrays_round_trip_and_compare(tmp_path):
    panels = [np.full((4, 6, 3), 0.25 * k, dtype=np.float32) for k in range(4)]
    path = C.record_pca_layers(tmp_path / "run" / "01_pca_layers", panels, ["a", "b", "c", "d"],
                               {"pair": "p", "backend": "micro backend", "title": "t"})
    arrays, meta = C.load_picture(path)
    assert meta["titles"] == ["a", "b", "c", "d"] and "cpu" in meta["provenance"]
    assert C.same_arrays(arrays, {f"panel_{k}": p for k, p in enumerate(panels)})
    changed = dict(arrays, panel_3=arrays["panel_3"] + np.float32(1e-6))
    assert not C.same_arrays(arrays, changed)
    with pytest.raises(FileNotFoundError, match="no committed picture arrays"):
        C.load_picture(tmp_path / "nothing")


def test_record_pictures_copies_a_runs_arrays_and_names_a_missing_one(tmp_path):
    run = tmp_path / "run"
    for stem, name in gallery.PICTURES:
        C.save_picture(run / stem / "pictures" / name, {"pair": "p"}, x=np.arange(3))
    copied = gallery.record_pictures(run, tmp_path / "committed")
    assert sorted(p.name for p in copied) == sorted(f"{n}{s}" for _, n in gallery.PICTURES for s in (".npz", ".json"))
    assert json.loads((tmp_path / "committed" / "01_pca_layers.json").read_text()) == {"pair": "p"}
    (run / "03_fusion" / "pictures" / "03_matches_d_g_fused.npz").unlink()
    with pytest.raises(FileNotFoundError, match="03_matches_d_g_fused.npz: not in the run"):
        gallery.record_pictures(run, tmp_path / "again")


def test_the_committed_pictures_are_there_and_name_their_pair():
    for _, name in gallery.PICTURES:
        arrays, meta = C.load_picture(C.picture_path(name))
        assert meta["pair"].startswith("synthetic-indoor/") and meta["provenance"]["cpu"]["model"]
