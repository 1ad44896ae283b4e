"""Table 8 (layer combinations on the validation scene) on the development set: the summary's
ranking, ranks and test on hand-made rows, and the verdict lines read from its JSON."""
from __future__ import annotations

import json

from freereg_lib.training import evaluate_combinations as EC
from freereg_lib.training import verdicts


def _recs(n: int = 4) -> list[dict]:
    sets = EC.combinations()
    recs = []
    for k in range(n):
        rows = {}
        for rank, row in enumerate(sets):  # IR falls with the row's position; (0, 4, 6) is the last row, u
            rows[row] = {"IR": 0.5 - 0.01 * rank + 0.001 * k, "IN": 40 - rank, "n_matches": 100}
        recs.append({"k": k, "pair_seed": k, "pair": f"p{k}", "label": "micro", "rows": rows, "seconds": 1.0})
    return recs


def test_the_paper_table_gives_21_combinations_with_the_chosen_one():
    sets = EC.combinations()
    assert len(sets) == 21 and sets["a"] == [0, 4, 7] and sets["u"] == [0, 4, 6]


def test_the_summary_ranks_the_rows_and_tests_the_best_against_the_chosen():
    res = EC.summarize(_recs(), "dev")
    assert res["chosen"] == "u" and res["n_pairs"] == 4
    v = res["verdict"]["IR"]
    assert v["micro_best"] == "a" and v["chosen_rank_micro"] == 21 and v["n_rows"] == 21
    assert v["paper_best"] == "q" and v["paper_best_layers"] == [0, 1, 2, 6]
    assert 0 < v["p_best_vs_chosen"] < 0.2  # a every pair ahead: four pairs, two-sided sign flips, p = 1/8
    assert abs(res["rows"]["a"]["IR"]["mean"] - 50.15) < 1e-9 and res["rows"]["a"]["IN"]["mean"] == 40.0
    assert -1.0 <= v["rank_correlation"] <= 1.0


def test_the_verdict_reads_the_committed_json(tmp_path, monkeypatch):
    (tmp_path / verdicts.COMBINATIONS_JSON).write_text(json.dumps(EC.summarize(_recs(), "dev")))
    monkeypatch.setattr(verdicts, "load", lambda name: json.loads((tmp_path / name).read_text()))
    lines = verdicts.table8()
    assert "by IR: best (0, 4, 7) 50.1" in lines[1] and "ranks 21 of 21" in lines[1], lines
    assert "the paper's best (0, 1, 2, 6), its (0, 4, 6) ranks" in lines[1], lines
