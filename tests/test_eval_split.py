"""The test split's evaluation (freereg_lib.training.evaluate_split): summaries of per-pair rows."""
import json

import numpy as np
import pytest

from freereg_lib.training import evaluate_split as ES
from freereg_lib.training import splits


def _rec(k, rng):
    rows = []
    for m in ES.METHODS:
        ir = float(rng.random() * 0.3)
        for s in ES.SOLVERS:
            reg = bool(rng.random() < 0.3)
            rows.append({"method": m, "solver": s, "w": 0.5, "n_matches": 40, "IR": ir, "IN": 5,
                         "RE": 5.0 if reg else None, "TE": 0.1 if reg else None, "registered": reg,
                         "n_evaluable": 40, "error": ""})
    return {"k": k, "pair_seed": splits.TEST.pair_seeds(k + 1)[k], "pair": f"p{k}", "seconds": 1.0,
            "label": "micro", "rows": rows}


def test_summary_uses_the_longest_complete_prefix_and_one_noise_seed(tmp_path):
    rng = np.random.default_rng(0)
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text("".join(json.dumps(_rec(k, rng)) + "\n" for k in (0, 2, 4, 6)))
    b.write_text("".join(json.dumps(_rec(k, rng)) + "\n" for k in (1, 3, 7)))  # 5 missing
    recs = ES.load_rows([a, b])
    assert [r["k"] for r in recs] == [0, 1, 2, 3, 4]
    res = ES.summarize(recs, "test")
    assert res["n_pairs"] == 5 and res["noise_seed"] == splits.TEST.noise_seed == splits.DEV.noise_seed
    fused = res["results"]["FreeReg kabsch"]
    assert np.isclose(fused["IR"]["mean"], 100 * np.mean(fused["IR_per_pair"]))
    assert fused["ladder"]["RR@20deg/0.5m"] == fused["RR"]["mean"]  # the ladder's RR rung is RR
    assert set(res["tests"]) >= {"IR: FreeReg - FreeReg-D", "IR: FreeReg - FreeReg-G"}


def test_the_splits_are_the_documented_ones():
    assert (splits.DEV.seed, splits.DEV.n_pairs, splits.DEV.noise_seed) == (2026, 30, 0)
    assert splits.TEST.seed == 4049 and splits.TEST.pair_seeds(2) == [4049 * 1_000_003, 4049 * 1_000_003 + 1]


def test_the_notebook_verdicts_read_the_committed_test_split():
    from freereg_lib.training import verdicts

    for table in (verdicts.table1, verdicts.table2, verdicts.table4, verdicts.table9):
        lines = table()
        assert lines[0].startswith("Committed test split"), lines[0]
        assert "100 synthetic indoor pairs" in lines[0]
    assert "disagree with the paper" in "\n".join(verdicts.table2())
    assert verdicts.glimpse(3).startswith("Glimpse: 3 live pair(s)")


def test_a_depth_error_without_the_stub_depth_is_refused_before_any_pair(tmp_path, capsys):
    rows = tmp_path / "rows.jsonl"
    with pytest.raises(SystemExit) as exc:
        ES.main(["--split", "rooms-dev", "--mono-mae", "0", "--rows", str(rows)])
    assert exc.value.code == 2 and "pass --mono-depth stub" in capsys.readouterr().err
    assert not rows.exists()


@pytest.mark.parametrize("mae, says", [(None, "the stub's designed error)"), (0.0, "the true depth"),
                                      (0.5, "the stub's designed error, MAE 0.5 m")])
def test_the_backend_label_names_the_monocular_depth_it_runs(mae, says):
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.models import get_backend

    assert says in get_backend("micro", FreeRegConfig(), device="cpu", mono_depth="stub", mono_mae=mae).label
