"""A fault in a batch run never becomes a result.

Wrong-typed grid values, configuration errors, YAML errors, OS errors, names that leave the
runs folder, truncated or cut ``pairs.csv`` given to ``merge``, a changed library, and runs
or kernels killed at any point. The jobs execute ``tests/fixtures/batch_fixture.ipynb``.
"""
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from freereg_lib.commands import batch

FIXTURE = Path(__file__).parent / "fixtures" / "batch_fixture.ipynb"
ROOT = Path(__file__).resolve().parent.parent
BENCHMARK = ROOT / "notebooks" / "04_benchmark.ipynb"


def _grid(tmp_path: Path, **spec) -> Path:
    spec.setdefault("notebooks", [str(FIXTURE)])
    path = tmp_path / f"{spec.pop('file', 'grid')}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


# --------------------------------------------------------------------------------------
# Configuration errors fail before anything runs.

@pytest.mark.parametrize("text, message", [
    ("grid: {seed: ['1']}", r"seed='1' is str, but the notebook's default is 0 \(int\).*YAML reads 5e4"),
    ("base: {n_pairs: 5e4}", r"n_pairs='5e4' is str"),
    ("base: {scale: 'false'}", r"scale='false' is str, but the notebook's default is 1.0 \(float\)"),
    ("base: {n_pairs: true}", r"n_pairs=True is bool"),
    ("base: {dataset: 3}", r"dataset=3 is int"),
    ("base: {dataset: nyu}", r"unknown dataset 'nyu'"),
])
def test_wrong_typed_grid_values_are_refused_before_any_job_runs(tmp_path, text, message):
    grid = tmp_path / "g.yaml"
    grid.write_text(f"notebooks: [{FIXTURE}]\n{text}\n")
    with pytest.raises(ValueError, match=message):
        batch.load_grid(grid)
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 2
    assert not (tmp_path / "runs").exists()  # nothing ran, nothing was written


@pytest.mark.skipif(not BENCHMARK.is_file(), reason="no notebook 04")
@pytest.mark.parametrize("base, message", [
    ({"ransac_iters": "2000"}, r"ransac_iters='2000' is str"),
    ({"config_overrides": {"kabsch_with_scale": "false"}}, r"kabsch_with_scale='false' is str, expected bool"),
    ({"config_overrides": {"ransac_iters": 5.5}}, r"ransac_iters=5.5 is float, expected int"),
    ({"variants": [["FreeReg", "PnP"]]}, r"variants \[\['FreeReg', 'PnP'\]\] are not \[method, solver\]"),
    ({"variants": [["FreeReg-X", "pnp"]]}, r"are not \[method, solver\]"),
])
def test_benchmark_configuration_errors_fail_the_grid_not_every_pair(tmp_path, base, message):
    grid = _grid(tmp_path, notebooks=[str(BENCHMARK)], base=base)
    with pytest.raises(ValueError, match=message):
        batch.load_grid(grid)


def test_a_configuration_error_on_every_pair_fails_the_job():
    rows = [{"pair": p, "method": "FreeReg", "solver": "PnP",
             "error": "ValueError: unknown solver 'PnP'; expected 'kabsch' or 'pnp' (pipeline.py:344)"}
            for p in "abc"]
    assert "failed with the same error" in batch.configuration_failure(rows)
    assert batch.configuration_failure(rows[:2] + [{**rows[2], "error": ""}]) == ""
    assert batch.configuration_failure([{**r, "error": "no pose"} for r in rows]) == ""


def test_yaml_syntax_error_is_one_line_naming_the_place(tmp_path, capsys):
    grid = tmp_path / "bad.yaml"
    grid.write_text(f"notebooks: [{FIXTURE}]\nbase: {{n_pairs: 3\ngrid: {{seed: [0, 1]}}\n")
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {grid}: line ") and "not valid YAML" in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


@pytest.mark.parametrize("how", ["grid", "option"])
@pytest.mark.parametrize("name", ["../escape", "..", "a/../../b", "/abs", "x/y", ""])
def test_names_cannot_leave_the_runs_folder(tmp_path, capsys, how, name):
    spec = {"name": name} if how == "grid" and name else {}
    grid = _grid(tmp_path, base={"n_pairs": 1}, **spec)
    argv = ["run", str(grid), "--runs-dir", str(tmp_path / "runs" / "inner")]
    if how == "option":
        argv += ["--name", name]
    if how == "grid" and not name:
        pytest.skip("an empty grid name falls back to the file stem")
    if how == "option" and not name:
        argv[-1] = ".."  # an empty --name is the grid's own name
    assert batch.main(argv) == 2
    assert "is not a plain folder name" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grid.yaml"]


def test_a_read_only_or_full_runs_folder_ends_with_one_line(tmp_path, capsys, monkeypatch):
    grid = _grid(tmp_path, base={"n_pairs": 1})
    blocker = tmp_path / "runs"
    blocker.write_text("a file where the runs folder should be")
    assert batch.main(["run", str(grid), "--runs-dir", str(blocker)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: cannot write or read") and len(err.splitlines()) == 1

    def read_only(*args, **kw):  # as root, chmod does not stop writes: simulate EROFS / ENOSPC
        raise OSError(errno.EROFS, "Read-only file system", str(tmp_path / "ro" / "grid" / "grid.yaml"))

    monkeypatch.setattr(batch.shutil, "copyfile", read_only)
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "ro")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: cannot write or read {tmp_path / 'ro' / 'grid' / 'grid.yaml'}: Read-only file system"
    monkeypatch.undo()

    real_write = batch.write_done

    def full(*args, **kw):
        raise OSError(errno.ENOSPC, "No space left on device", "done.json.tmp")

    monkeypatch.setattr(batch, "write_done", full)
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "full")]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # after the progress bar
    assert err[-1] == "error: cannot write or read done.json.tmp: No space left on device"
    assert not any("Traceback" in line for line in err)
    monkeypatch.setattr(batch, "write_done", real_write)


# --------------------------------------------------------------------------------------
# merge verifies pairs.csv against done.json.

@pytest.fixture(scope="module")
def finished_job(tmp_path_factory):
    """A folder with a grid of one job and its finished run (``grid.yaml``, ``runs/``), run once
    for the module; each test gets its own copy (:func:`_one_finished_job`)."""
    folder = tmp_path_factory.mktemp("finished")
    grid = _grid(folder, name="m", base={"n_pairs": 4, "seed": 2})
    assert batch.main(["run", str(grid), "--runs-dir", str(folder / "runs")]) == 0
    return folder


def _one_finished_job(tmp_path, finished_job, name="m"):
    shutil.copytree(finished_job, tmp_path, dirs_exist_ok=True)
    grid = tmp_path / "grid.yaml"
    job = batch.load_grid(grid).jobs[0]
    unit = tmp_path / "runs" / name / job.id
    done = json.loads((unit / "done.json").read_text())
    assert done["rows"] == 16 and len(done["pairs_sha256"]) == 64
    assert done["library"] == batch.library_fingerprint() and done["config"]["tau_c"] == 0.3
    assert batch.is_done(unit, job, "0/1")  # the copy is a finished job, as the run left it
    return grid, job, unit


def test_merge_refuses_a_truncated_pairs_csv(tmp_path, capsys, finished_job):
    grid, job, unit = _one_finished_job(tmp_path, finished_job)
    lines = (unit / "out" / "pairs.csv").read_text().splitlines(keepends=True)
    (unit / "out" / "pairs.csv").write_text("".join(lines[:-4]))  # whole rows lost: 12 of 16
    assert batch.main(["merge", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 1
    out = capsys.readouterr().out
    assert "changed since the job finished (16 rows recorded, 12 now)" in out
    assert pd.read_csv(tmp_path / "runs" / "m" / "results.csv").empty
    # run sees it too, and re-runs the job.
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 0
    assert "1 job(s) ran" in capsys.readouterr().out
    assert (pd.read_csv(tmp_path / "runs" / "m" / "results.csv")["n_pairs"] == 4).all()


def test_merge_refuses_a_cut_row_without_a_traceback(tmp_path, capsys, finished_job):
    grid, job, unit = _one_finished_job(tmp_path, finished_job)
    text = (unit / "out" / "pairs.csv").read_text()
    (unit / "out" / "pairs.csv").write_text(text[: len(text) - 40])  # the last row cut mid-way
    assert batch.main(["merge", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 1
    out = capsys.readouterr().out
    assert "changed since the job finished (16 rows recorded" in out and "cell(s) for" in out
    with pytest.raises(ValueError, match=r"line 17 has \d+ cell\(s\) for 13 column\(s\)"):
        batch.read_rows(unit / "out")


def test_a_job_of_another_library_is_flagged_by_merge_and_rerun_by_run(tmp_path, capsys, finished_job):
    grid, job, unit = _one_finished_job(tmp_path, finished_job)
    done = json.loads((unit / "done.json").read_text())
    (unit / "done.json").write_text(json.dumps({**done, "library": "0.0.1+000000000000"}))
    assert batch.main(["merge", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 0
    out = capsys.readouterr().out
    assert f"OUT OF DATE {job.id}: finished with library 0.0.1+000000000000" in out
    assert "Out of date" in (tmp_path / "runs" / "m" / "results.md").read_text()
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs")]) == 0
    out = capsys.readouterr().out
    assert "1 job(s) ran, 0 already done" in out and "run again: finished with library" in out
    assert json.loads((unit / "done.json").read_text())["library"] == batch.library_fingerprint()


# --------------------------------------------------------------------------------------
# Killing a run or a kernel at any point, then re-running, gives the uninterrupted table.

def _start(grid: Path, runs: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "freereg_lib.commands.batch", "run", str(grid), "--runs-dir", str(runs)],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _wait_for(check, what: str, timeout: float = 120.0):
    end = time.time() + timeout
    while time.time() < end:
        found = check()
        if found:
            return found
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _pid_of(pid_file: Path, tag: str) -> int | None:
    lines = pid_file.read_text().splitlines() if pid_file.exists() else []
    pids = [int(line.split()[1]) for line in lines if line.split()[0] == tag]
    return pids[-1] if pids else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_killing_the_run_or_a_kernel_then_rerunning_gives_the_uninterrupted_table(tmp_path):
    hold, pids = tmp_path / "hold.txt", tmp_path / "pids.txt"
    grid = _grid(tmp_path, name="k", base={"n_pairs": 3, "hold_file": str(hold), "pid_file": str(pids)},
                 grid={"seed": [0, 1]})
    jobs = batch.load_grid(grid).jobs
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "whole")]) == 0
    whole = pd.read_csv(tmp_path / "whole" / "k" / "results.csv")
    runs = tmp_path / "runs"
    pids.unlink()

    # 1. The runner killed (SIGKILL) while the second job's kernel is running.
    hold.write_text("seed=1,scale=1.0\n")
    proc = _start(grid, runs)
    kernel = _wait_for(lambda: _pid_of(pids, "seed=1,scale=1.0"), "the second job's kernel")
    assert (runs / "k" / jobs[0].id / "done.json").is_file()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    hold.unlink()  # an orphaned kernel that lives on writes its rows to a job that is not done
    _wait_for(lambda: not _alive(kernel), "the orphaned kernel to end", timeout=60)  # ipykernel: ~2 s
    assert not (runs / "k" / jobs[1].id / "done.json").exists()

    # 2. Run again: the finished job is skipped, and the unfinished one's kernel killed mid-job:
    # the job fails, the run ends with status 1.
    hold.write_text("seed=1,scale=1.0\n")
    proc = _start(grid, runs)
    kernel = _wait_for(lambda: _pid_of(pids, "seed=1,scale=1.0") != kernel and _pid_of(pids, "seed=1,scale=1.0"),
                       "the second job's kernel again")
    os.kill(kernel, signal.SIGKILL)
    assert proc.wait(timeout=120) == 1
    hold.unlink()
    assert (runs / "k" / jobs[1].id / "error.txt").is_file()
    assert not (runs / "k" / jobs[1].id / "done.json").exists()
    assert [line.split()[0] for line in pids.read_text().splitlines()] == ["seed=0,scale=1.0"] + ["seed=1,scale=1.0"] * 2

    # 3. Re-run: only the unfinished job runs, and the table is the uninterrupted one.
    report = batch.run(grid, runs_dir=runs)
    assert report.ok and report.finished == [jobs[1].id] and len(report.skipped) == 1
    pd.testing.assert_frame_equal(pd.read_csv(runs / "k" / "results.csv"), whole)
