"""The acceleration table's command (training/evaluate_ddim): its summary on hand-made rows, and its
bad arguments. The committed run is read by notebook 06's verdict (training/verdicts.table13)."""
from __future__ import annotations

import json

import pytest

from freereg_lib.training import evaluate_ddim, verdicts


def _rec(k: int, registered: dict[int, bool], seconds: dict[int, float]) -> dict:
    by = {}
    for s in (5, 20):
        by[str(s)] = {"seconds_diffusion": seconds[s], "rows": [
            {"solver": solver, "n_matches": 100, "IR": 0.5 if s == 20 else 0.25, "IN": 50 if s == 20 else 25,
             "RE": 1.0, "TE": 0.1, "registered": registered[s] if solver == "kabsch" else False, "error": None}
            for solver in ("kabsch", "pnp")]}
    return {"k": k, "pair_seed": k, "pair": f"p{k}", "label": "micro", "load_average": 1.0,
            "seconds_geometric": 2.0, "by_steps": by}


def test_the_summary_counts_recall_time_and_the_paired_difference():
    recs = [_rec(0, {5: True, 20: True}, {5: 1.0, 20: 4.0}), _rec(1, {5: False, 20: True}, {5: 1.0, 20: 4.0}),
            _rec(2, {5: False, 20: True}, {5: 2.0, 20: 5.0}), _rec(3, {5: True, 20: True}, {5: 2.0, 20: 5.0})]
    res = evaluate_ddim.summarize(recs, "test")
    assert res["steps"] == [5, 20] and res["n_pairs"] == 4
    assert res["results"]["5 kabsch"]["RR"]["mean"] == 50.0 and res["results"]["20 kabsch"]["RR"]["mean"] == 100.0
    assert res["results"]["5 kabsch"]["IR"]["mean"] == 25.0 and res["results"]["20 kabsch"]["IN"] == 50.0
    assert res["results"]["5 seconds"] == 1.5 and res["results"]["20 seconds"] == 4.5  # medians
    t = res["tests"]["RR kabsch: 5 - 20 iterations"]
    assert t["diff"] == -50.0 and t["diff_ci"][0] <= -50.0 <= t["diff_ci"][1] and 0 < t["p"] <= 1
    assert res["tests"]["RR pnp: 5 - 20 iterations"] == {"diff": 0.0, "diff_ci": [0.0, 0.0], "p": 1.0}


def test_the_verdict_reads_the_committed_json(tmp_path, monkeypatch):
    recs = [_rec(k, {5: True, 20: True}, {5: 1.0, 20: 4.0}) for k in range(3)]
    (tmp_path / verdicts.DDIM_JSON).write_text(json.dumps(evaluate_ddim.summarize(recs, "test")))
    monkeypatch.setattr(verdicts, "load", lambda name: json.loads((tmp_path / name).read_text()))
    lines = verdicts.table13()
    assert "faster with 5 iterations: yes (1.00 s against 4.00 s, x4.0" in lines[-2], lines
    assert "+0.0 points" in lines[-1] and "cannot be told (3 pairs, fewer than 30)" in lines[-1], lines


@pytest.mark.parametrize("argv, message", [
    (["--pairs", "0", "--rows", "r.jsonl"], "--pairs and --steps must be >= 1"),
    (["--steps", "0", "5", "--rows", "r.jsonl"], "--pairs and --steps must be >= 1"),
    (["--summarize", "--rows", "missing.jsonl"], "no such file"),
])
def test_bad_arguments_stop_with_one_line(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        evaluate_ddim.main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_an_empty_rows_file_is_refused(tmp_path, capsys):
    rows = tmp_path / "rows.jsonl"
    rows.write_text("")
    with pytest.raises(SystemExit):
        evaluate_ddim.main(["--summarize", "--rows", str(rows)])
    assert "no complete pair" in capsys.readouterr().err


def test_a_malformed_rows_file_stops_with_one_line_naming_it(tmp_path, capsys):
    from freereg_lib.training import evaluate_combinations, evaluate_layers

    rows = tmp_path / "rows.jsonl"
    rows.write_text('{"k": 0}\nnot json\n')
    for main in (evaluate_ddim.main, evaluate_combinations.main, evaluate_layers.main):
        with pytest.raises(SystemExit) as exc:
            main(["--summarize", "--rows", str(rows)])
        assert exc.value.code == 2 and f"--rows {rows}, line 2: not a row" in capsys.readouterr().err
