"""The batch runner: grids, skipping finished jobs, failures, shards and the results table.

The jobs execute ``tests/fixtures/batch_fixture.ipynb`` through papermill: a notebook that
follows the batch contract but makes seeded fake rows, so each job takes about a second.
"""
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from freereg_lib.commands import batch
from freereg_lib.config import config_for

FIXTURE = Path(__file__).parent / "fixtures" / "batch_fixture.ipynb"
ROOT = Path(__file__).resolve().parent.parent


def _grid(tmp_path: Path, **spec) -> Path:
    spec.setdefault("notebooks", [str(FIXTURE)])
    path = tmp_path / f"{spec.pop('file', 'grid')}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.exists() else []


# --------------------------------------------------------------------------------------
# Notebook-side helpers.

def test_shard_items_split_is_deterministic_disjoint_and_complete():
    items = list(range(11))
    shards = [batch.shard_items(items, f"{i}/3") for i in range(3)]
    assert shards[0] == [0, 3, 6, 9] and shards[2] == [2, 5, 8]
    assert sorted(sum(shards, [])) == items
    assert batch.shard_items(items, "0/1") == items
    assert batch.shard_items(iter(items), " 1 / 3 ") == shards[1]


@pytest.mark.parametrize("bad", ["3/3", "1", "a/2", "-1/2", "0/0", "1/2/3", ""])
def test_bad_shard_strings_are_refused(bad):
    with pytest.raises(ValueError, match="shard must be 'i/n'"):
        batch.shard_items([1, 2], bad)


def test_rows_round_trip_exactly_with_nan_bool_and_empty_strings(tmp_path):
    rows = [
        {"pair": "007", "method": "FreeReg", "solver": "pnp", "w": 0.1 + 0.2, "IN": np.int64(12),
         "IR": np.float32(0.25), "RE": math.nan, "TE": float("inf"), "registered": np.bool_(False),
         "error": ""},
        {"pair": "a/b", "method": "FreeReg-D", "solver": "kabsch", "w": 1.0, "IN": 0, "IR": 0.0,
         "RE": 3.5, "TE": 0.1, "registered": True, "error": "ValueError: x, \"quoted\"\nline 2",
         "extra": "only here"},
    ]
    batch.write_rows(rows, tmp_path / "out")
    back = batch.read_rows(tmp_path / "out")
    assert back[0]["pair"] == "007" and back[0]["error"] == "" and back[0]["extra"] == ""
    assert back[0]["w"] == 0.1 + 0.2 and back[0]["IR"] == 0.25 and back[0]["TE"] == math.inf
    assert math.isnan(back[0]["RE"]) and back[0]["registered"] is False
    assert type(back[0]["IN"]) is int and back[1]["registered"] is True
    assert back[1]["error"] == rows[1]["error"] and back[1]["extra"] == "only here"


def test_config_is_recorded_and_read_back(tmp_path):
    cfg = config_for("kitti", kitti_trans_threshold=4.0)
    batch.write_rows([{"pair": "p", "method": "FreeReg", "solver": "pnp", "IR": 0.0, "IN": 0}], tmp_path, cfg)
    assert batch.read_config(tmp_path) == cfg
    assert batch.read_config(tmp_path / "nowhere") is None


# --------------------------------------------------------------------------------------
# Grids.

def test_grid_expands_sets_times_grid_with_stable_readable_ids(tmp_path):
    path = _grid(tmp_path, base={"n_pairs": 3}, sets=[{"dataset": "3dmatch"}, {"dataset": "kitti"}],
                 grid={"seed": [0, 1], "scale": [1.0, 0.5, 2.0]})
    grid = batch.load_grid(path)
    assert grid.name == "grid" and len(grid.jobs) == 12
    assert all(j.params["n_pairs"] == 3 for j in grid.jobs)
    first = grid.jobs[0]
    assert first.id.startswith("batch_fixture-dataset=3dmatch,seed=0,scale=1.0-")
    assert first.id == batch.load_grid(path).jobs[0].id  # stable across loads
    reordered = dict(reversed(list(first.params.items())))
    assert batch.job_id(first.notebook, reordered, first.label) == first.id
    assert batch.job_id(first.notebook, {**first.params, "seed": 5}, first.label) != first.id


@pytest.mark.parametrize("spec, message", [
    ({"grid": {"sede": [0, 1]}}, r"\['sede'\] are not in the `parameters` cell"),
    ({"grid": {"seed": 3}}, "must be a non-empty list"),
    ({"base": {"out_dir": "x"}}, "set by the runner"),
    ({"notebooks": ["no/such.ipynb"]}, "not found"),
    ({"grids": {}}, "unknown key"),
])
def test_bad_grids_get_clear_errors(tmp_path, spec, message):
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        batch.load_grid(_grid(tmp_path, **spec))


def test_table1_grid_names_the_benchmark_notebook_and_the_three_datasets():
    spec = yaml.safe_load((ROOT / "freereg_lib/data/grids/table1.yaml").read_text())
    assert spec["notebooks"] == ["notebooks/04_benchmark.ipynb"]
    assert {s["dataset"] for s in spec["sets"]} == {"3dmatch", "scannet", "kitti"}
    assert spec["base"]["backend"] == "real"
    if not (ROOT / "notebooks/04_benchmark.ipynb").is_file():
        pytest.skip("notebooks/04_benchmark.ipynb is not written yet")
    grid = batch.load_grid(ROOT / "freereg_lib/data/grids/table1.yaml")  # its parameters exist
    assert len(grid.jobs) == 3


# --------------------------------------------------------------------------------------
# Running (papermill).

def test_runner_reports_a_failure_skips_finished_jobs_and_completes_the_table(tmp_path, capsys):
    """2 x 1 grid; one job fails, a re-run retries only that one, then the table is whole.
    (Two jobs, not four: each is a kernel start, ~1 s of CPU, and one finished job to skip
    shows the skipping as well as three.)"""
    counter, flag = tmp_path / "count.txt", tmp_path / "fail.txt"
    grid = _grid(tmp_path, name="acc", base={"n_pairs": 3, "dataset": "3dmatch",
                                             "fail_flag": str(flag), "counter_file": str(counter)},
                 grid={"seed": [0, 1], "scale": [0.5]})
    runs = tmp_path / "runs"
    flag.write_text("seed=1,scale=0.5\n")
    assert batch.main(["run", str(grid), "--runs-dir", str(runs)]) == 1
    out = capsys.readouterr().out
    assert "1 job(s) ran, 0 already done (skipped), 1 failed" in out
    assert "FAILED batch_fixture-seed=1,scale=0.5-" in out and "simulated failure" in out
    run_dir = runs / "acc"
    jobs = batch.load_grid(grid).jobs
    bad = next(j for j in jobs if j.params["seed"] == 1 and j.params["scale"] == 0.5)
    assert (run_dir / bad.id / "notebook.ipynb").is_file()  # the executed copy is kept
    assert "simulated failure of seed=1,scale=0.5" in (run_dir / bad.id / "error.txt").read_text()
    assert not (run_dir / bad.id / "done.json").exists()
    table = pd.read_csv(run_dir / "results.csv")
    assert len(table) == 1 * 4 and bad.id not in set(table["job"])
    assert bad.id in (run_dir / "results.md").read_text().split("Not in the table:")[1]
    # Every job ran in this very interpreter (the python3 kernel resolved to the venv).
    executed = _lines(counter)
    assert len(executed) == 2
    assert {Path(line.split(" ", 1)[1]).resolve() for line in executed} == {Path(sys.executable).resolve()}

    stamps = {j.id: (run_dir / j.id / "done.json").stat().st_mtime_ns for j in jobs if j is not bad}
    flag.unlink()
    assert batch.main(["run", str(grid), "--runs-dir", str(runs)]) == 0
    assert "1 job(s) ran, 1 already done (skipped), 0 failed" in capsys.readouterr().out
    assert _lines(counter)[2:] == [f"seed=1,scale=0.5 {sys.executable}"]
    assert stamps == {j: (run_dir / j / "done.json").stat().st_mtime_ns for j in stamps}
    assert not (run_dir / bad.id / "error.txt").exists()
    table = pd.read_csv(run_dir / "results.csv")
    assert len(table) == 2 * 4 and set(table["job"]) == {j.id for j in jobs}
    assert table[["FMR", "IR", "IN", "RR"]].notna().all().all()
    assert (table["param_n_pairs"] == 3).all() and (table["n_pairs"] == 3).all()
    kabsch = table[(table["method"] == "FreeReg") & (table["solver"] == "kabsch")]
    assert (kabsch["paper_RR"] == 63.8).all() and (kabsch["paper_IN"] == 82.8).all()
    assert "Not in the table" not in (run_dir / "results.md").read_text()
    # The runner's table (re-aggregated from pairs.csv) agrees with the notebook's own.
    own = pd.read_csv(run_dir / bad.id / "out" / "results.csv")
    ours = table[table["job"] == bad.id].reset_index(drop=True)
    np.testing.assert_allclose(ours[["FMR", "IR", "IN", "RR", "RE", "TE"]], own[["FMR", "IR", "IN", "RR", "RE", "TE"]], rtol=1e-12)


def test_sharded_run_merges_into_the_unsharded_table(tmp_path, capsys):
    grid = _grid(tmp_path, name="one", base={"n_pairs": 7, "seed": 3, "dataset": "kitti"})
    runs = tmp_path / "runs"
    assert batch.main(["run", str(grid), "--runs-dir", str(runs), "--name", "whole"]) == 0
    assert batch.main(["run", str(grid), "--runs-dir", str(runs), "--name", "split", "--shard", "1/2"]) == 0
    assert "shards [1] of 2 done" in capsys.readouterr().out  # half a job is not tabulated
    assert batch.main(["merge", str(grid), "--runs-dir", str(runs), "--name", "split"]) == 1
    assert batch.main(["run", str(grid), "--runs-dir", str(runs), "--name", "split", "--shard", "0/2"]) == 0
    assert batch.main(["merge", str(grid), "--runs-dir", str(runs), "--name", "split"]) == 0
    whole = pd.read_csv(runs / "whole" / "results.csv")
    split = pd.read_csv(runs / "split" / "results.csv")
    assert list(split["shards"]) == [2] * 4 and list(whole["shards"]) == [1] * 4
    pd.testing.assert_frame_equal(whole.drop(columns="shards"), split.drop(columns="shards"))
    assert (whole["n_pairs"] == 7).all()
    job = batch.load_grid(grid).jobs[0]
    sizes = [len({r["pair"] for r in batch.read_rows(runs / "split" / job.id / f"shard-{i}of2" / "out")}) for i in (0, 1)]
    assert sizes == [4, 3]


def _fake_shards(tmp_path, name, pairs_per_shard):
    """Write finished shard folders by hand (no notebook): shard i holds ``pairs_per_shard[i]``."""
    grid = _grid(tmp_path, name=name, base={"n_pairs": 2})
    job = batch.load_grid(grid).jobs[0]
    n = len(pairs_per_shard)
    for i, pairs in enumerate(pairs_per_shard):
        unit = tmp_path / "runs" / name / job.id / f"shard-{i}of{n}"
        batch.write_rows([{"pair": p, "method": "FreeReg", "solver": "pnp", "IR": 0.5, "IN": 3,
                           "RE": 1.0, "TE": 0.1} for p in pairs], unit / "out")
        batch.write_done(unit, job, f"{i}/{n}")
    return grid, job


def test_merge_refuses_a_pair_present_in_two_shards(tmp_path):
    """A notebook that ignores ``shard`` would otherwise count every pair n times."""
    grid, job = _fake_shards(tmp_path, "dup", [["same"], ["same"]])
    report = batch.merge(grid, runs_dir=tmp_path / "runs")
    assert not report.ok and "is in both" in report.incomplete[job.id]
    assert "does the notebook pass its `shard`" in (tmp_path / "runs" / "dup" / "results.md").read_text()


def test_merge_accepts_empty_shards_but_not_an_empty_job(tmp_path):
    grid, job = _fake_shards(tmp_path, "more", [["a"], ["b"], []])  # 3 shards, 2 pairs
    assert batch.merge(grid, runs_dir=tmp_path / "runs").ok
    assert list(pd.read_csv(tmp_path / "runs" / "more" / "results.csv")["n_pairs"]) == [2]
    grid, job = _fake_shards(tmp_path, "none", [[], []])
    report = batch.merge(grid, runs_dir=tmp_path / "runs")
    assert "no per-pair rows" in report.incomplete[job.id]
