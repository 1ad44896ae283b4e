"""The batch runner's jobs through Dask distributed (``--executor dask``).

A local cluster of two worker processes runs a grid of three jobs of ``tests/fixtures/batch_fixture.ipynb``
(about a second a job); one worker is killed mid-job and one kernel too, and the table must be the
local executor's. A notebook error is reported once, never re-run by the engine. The option checks
start no cluster.
"""
import re
import signal
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from test_batch_faults import ROOT, _grid, _wait_for  # the fixture notebook's grids, polling

from freereg_lib.commands import batch, cluster

distributed = pytest.importorskip("distributed")
psutil = pytest.importorskip("psutil")  # a dependency of distributed


def _pids(pid_file: Path, tag: str) -> list[int]:
    lines = pid_file.read_text().splitlines() if pid_file.exists() else []
    return [int(line.split()[1]) for line in lines if line.split()[0] == tag]


def _tags(counter: Path) -> list[str]:
    return [line.split()[0] for line in counter.read_text().splitlines()]


# --------------------------------------------------------------------------------------
# Faults on a real cluster.

@pytest.mark.slow  # 20-40 s on a busy 2-core machine: eight notebook executions and a cluster
def test_a_killed_worker_or_kernel_reruns_its_job_once_and_the_table_is_the_local_one(tmp_path):
    hold, pids, counter = tmp_path / "hold.txt", tmp_path / "pids.txt", tmp_path / "counter.txt"
    grid = _grid(tmp_path, name="c", base={"n_pairs": 3, "hold_file": str(hold), "pid_file": str(pids),
                                           "counter_file": str(counter)},
                 grid={"seed": [0, 1, 2]})
    jobs = batch.load_grid(grid).jobs
    local = batch.run(grid, runs_dir=tmp_path / "local")
    assert local.ok and len(local.finished) == 3
    whole = pd.read_csv(tmp_path / "local" / "c" / "results.csv")
    pids.unlink()
    counter.unlink()

    # Two jobs held in their notebook, one on each worker (one GPU each).
    worker_job, kernel_job = "seed=0,scale=1.0", "seed=1,scale=1.0"
    hold.write_text(f"{worker_job}\n{kernel_job}\n")
    runs = tmp_path / "runs"
    out, err = open(tmp_path / "stdout.txt", "w"), open(tmp_path / "stderr.txt", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "freereg_lib.commands.batch", "run", str(grid), "--runs-dir", str(runs), "--executor", "dask",
         "--gpus", "0,1", "--resources", "GPU=1", "--retries", "1", "--dashboard", "127.0.0.1:0"],
        cwd=ROOT, stdout=out, stderr=err)
    try:
        first = {tag: _wait_for(lambda t=tag: _pids(pids, t), f"the kernel of {tag}")[0]
                 for tag in (worker_job, kernel_job)}
        kernels = {tag: psutil.Process(pid) for tag, pid in first.items()}
        # One worker per GPU: each kernel sees only its worker's GPU.
        assert sorted(k.environ().get("CUDA_VISIBLE_DEVICES") for k in kernels.values()) == ["0", "1"]
        worker = kernels[worker_job].parent()
        assert worker.pid != proc.pid and kernels[kernel_job].parent().pid != worker.pid
        worker.send_signal(signal.SIGKILL)  # the worker process dies mid-job (as on OOM)
        kernels[kernel_job].send_signal(signal.SIGKILL)  # a kernel dies under a live worker
        # The orphaned kernel ends by itself (ipykernel watches its parent); until it did, it must
        # not write rows, so the hold stays until then.
        _wait_for(lambda: not kernels[worker_job].is_running() or kernels[worker_job].status() == "zombie",
                  "the orphaned kernel to end", timeout=60)
        for tag in (worker_job, kernel_job):  # both jobs run again (held again)
            _wait_for(lambda t=tag: len(_pids(pids, t)) == 2, f"{tag} to run again")
    finally:
        hold.unlink(missing_ok=True)
        rc = proc.wait(timeout=180)
        out.close()
        err.close()
    stdout, stderr = (tmp_path / "stdout.txt").read_text(), (tmp_path / "stderr.txt").read_text()
    assert rc == 0, stdout + stderr
    assert "3 job(s) ran, 0 already done (skipped), 0 failed" in stdout
    assert "dask: a local cluster, 2 worker(s), dashboard http://127.0.0.1:" in stderr

    # Every job finished once: the two faulted ones ran twice, the other once, and each has
    # one finished execution (no shard folders, no leftover error).
    assert sorted(_tags(counter)) == sorted([worker_job, worker_job, kernel_job, kernel_job, "seed=2,scale=1.0"])
    for job in jobs:
        unit = runs / "c" / job.id
        # (verify_unit, not is_done: the library's fingerprint is not what this test is about)
        assert (unit / "done.json").is_file() and not batch.verify_unit(unit) and not (unit / "error.txt").exists()
        assert not list(unit.glob("shard-*"))
    table = pd.read_csv(runs / "c" / "results.csv")
    assert not table.duplicated(["job", "method", "solver"]).any() and len(table) == 12
    pd.testing.assert_frame_equal(table, whole)


def test_a_notebook_error_is_reported_once_and_a_rerun_runs_only_that_job(tmp_path, capsys):
    # A cluster started beforehand, reached through its address (as on SLURM), from the grid; one
    # worker is enough to see a failed job reported once and its shards merged.
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        flag, counter = tmp_path / "fail.txt", tmp_path / "counter.txt"
        grid = _grid(tmp_path, name="e", base={"n_pairs": 2, "fail_flag": str(flag), "counter_file": str(counter)},
                     grid={"seed": [0, 1]}, executor={"kind": "dask", "scheduler": c.scheduler_address})
        good, bad = batch.load_grid(grid).jobs
        flag.write_text("seed=1,scale=1.0\n")
        runs = tmp_path / "runs"
        assert batch.main(["run", str(grid), "--runs-dir", str(runs)]) == 1
        captured = capsys.readouterr()
        assert f"dask: scheduler {c.scheduler_address}, 1 worker(s)" in captured.err
        assert f"FAILED {bad.id}: RuntimeError: simulated failure of seed=1,scale=1.0" in captured.out
        assert captured.out.count("FAILED") == 1 and f"finished {good.id}" in captured.out
        assert sorted(_tags(counter)) == ["seed=0,scale=1.0", "seed=1,scale=1.0"]  # not retried
        assert "simulated failure" in (runs / "e" / bad.id / "error.txt").read_text()
        assert list(pd.read_csv(runs / "e" / "results.csv")["job"].unique()) == [good.id]

        # Fixed, run again with each job split into two shards: only the failed job runs (both
        # of its shards), and the table merges them.
        flag.unlink()
        assert batch.main(["run", str(grid), "--runs-dir", str(runs), "--shards", "2"]) == 0
        stdout = capsys.readouterr().out
        assert "2 job(s) ran, 1 already done (skipped), 0 failed" in stdout
        assert f"finished {bad.id} [shard 0/2]" in stdout and f"finished {bad.id} [shard 1/2]" in stdout
        assert sorted(_tags(counter)) == ["seed=0,scale=1.0"] + ["seed=1,scale=1.0"] * 3
        table = pd.read_csv(runs / "e" / "results.csv")
        assert table.groupby("job")["shards"].first().to_dict() == {good.id: 1, bad.id: 2}
        assert (table["n_pairs"] == 2).all() and len(table) == 8


# --------------------------------------------------------------------------------------
# Options: checked before anything runs, one line each; no cluster is started.

@pytest.mark.parametrize("argv, message", [
    (["--executor", "spark"], "unknown executor 'spark'; choose one of ['local', 'dask']"),
    (["--workers", "2"], "--workers go(es) with the dask executor; add --executor dask"),
    (["--executor", "dask", "--shard", "1/2"], "with the dask executor use --shards N"),
    (["--executor", "dask", "--workers", "0"], "executor workers=0: expected an integer >= 1"),
    (["--executor", "dask", "--gpus", "0,1", "--workers", "3"], "a local cluster has one worker per GPU"),
    (["--executor", "dask", "--resources", "GPU=1"], "no worker of a local cluster would offer them"),
    (["--executor", "dask", "--resources", "GPU"], "expected NAME=amount pairs"),
    (["--executor", "dask", "--scheduler", "tcp://h:1", "--workers", "2"], "workers sizes a cluster on this machine"),
    (["--executor", "dask", "--scheduler", "no such file"], "an address such as tcp://10.0.0.5:8786, or a scheduler"),
])
def test_bad_engine_options_are_one_line_errors(tmp_path, capsys, argv, message):
    grid = _grid(tmp_path, base={"n_pairs": 1})
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("executor, message", [
    ("ray", "executor 'ray'; choose one of"),
    ({"kind": "dask", "worker": 2}, "unknown executor option(s) ['worker']"),
    ({"kind": "dask", "gpus": [0, 0]}, "expected each GPU once"),
    ([1], "`executor` is local, dask, or a mapping"),
])
def test_bad_executor_entries_in_the_grid_are_refused(tmp_path, executor, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        batch.load_grid(_grid(tmp_path, executor=executor))


def test_an_unreachable_scheduler_is_one_line(tmp_path, capsys):
    grid = _grid(tmp_path, base={"n_pairs": 1},
                 executor={"kind": "dask", "scheduler": "tcp://127.0.0.1:9", "connect_timeout": 1})
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: cannot reach the Dask scheduler at tcp://127.0.0.1:9 within 1 s (")
    assert err.endswith("start one (dask scheduler) or check the address") and len(err.splitlines()) == 1
    missing = tmp_path / "gone.json"  # a scheduler deletes its file when it stops
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs"), "--scheduler", str(missing)]) == 2
    assert capsys.readouterr().err.strip() == (f"error: no scheduler file {missing}, and it is not an address "
                                               "(tcp://host:8786): has the scheduler started?")


def test_the_local_executor_needs_no_dask():
    code = ("import sys, freereg_lib.commands.batch, freereg_lib.commands.cluster; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_grid_and_command_line_choose_the_executor_together():
    spec = cluster.executor_spec({"kind": "dask", "gpus": "0,1", "shards": 4}, "g.yaml")
    kind, options = cluster.choose(spec, None, {"shards": 2, "workers": None}, "g.yaml")
    assert kind == "dask" and options.gpus == ["0", "1"] and options.shards == 2 and options.retries == 2
    assert cluster.choose(spec, "local", {}, "g.yaml") == ("local", None)
    assert cluster.choose({"kind": "local"}, None, None, "g.yaml") == ("local", None)
    assert cluster.executor_spec("dask", "g.yaml") == {"kind": "dask"}
    remote = cluster.dask_options({"resources": "GPU=1, MEM=2e9", "scheduler": "tcp://10.0.0.5:8786"})
    assert remote.resources == {"GPU": 1.0, "MEM": 2e9} and remote.gpus == []


def test_local_workers_share_the_cores_out_and_leave_the_users_thread_settings():
    assert cluster.worker_thread_env(2, cores=2, environ={}) == dict.fromkeys(cluster.THREAD_VARIABLES, "1")
    assert cluster.worker_thread_env(2, cores=16, environ={})["OMP_NUM_THREADS"] == "8"
    assert cluster.worker_thread_env(3, cores=2, environ={})["MKL_NUM_THREADS"] == "1"  # at least one
    assert cluster.worker_thread_env(2, cores=16, environ={"OMP_NUM_THREADS": "4"}) == {
        "MKL_NUM_THREADS": "8", "OPENBLAS_NUM_THREADS": "8"}


def test_a_local_clusters_worker_processes_see_their_share(monkeypatch):
    import os

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")  # the user's: kept
    with cluster.DaskExecutor(cluster.dask_options({"workers": 2})) as ex:
        seen = ex.client.run(lambda: (os.environ.get("OMP_NUM_THREADS"), os.environ.get("MKL_NUM_THREADS")))
    share = str(max(1, cluster.available_cores() // 2))
    assert sorted(seen.values()) == [(share, "3"), (share, "3")]
