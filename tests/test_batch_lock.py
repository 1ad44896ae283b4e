"""A batch run folder is locked by its runner; a second runner says so in one line and
stops (exit 2) instead of executing every job a second time."""
import subprocess
import sys
import time
from pathlib import Path

import yaml

from freereg_lib.commands import batch

FIXTURE = Path(__file__).parent / "fixtures" / "batch_fixture.ipynb"
ROOT = Path(__file__).resolve().parent.parent


def _wait_for(check, what: str, timeout: float = 120.0):
    end = time.time() + timeout
    while time.time() < end:
        if check():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_a_second_runner_on_the_same_folder_stops_with_one_line(tmp_path, capsys):
    hold, counter = tmp_path / "hold.txt", tmp_path / "counter.txt"
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({"name": "l", "notebooks": [str(FIXTURE)],
                                    "base": {"n_pairs": 2, "hold_file": str(hold), "counter_file": str(counter)}}))
    runs = tmp_path / "runs"
    hold.write_text("seed=0,scale=1.0\n")
    first = subprocess.Popen([sys.executable, "-m", "freereg_lib.commands.batch", "run", str(grid), "--runs-dir", str(runs)],
                             cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: counter.exists() and counter.read_text().strip(), "the first runner's job")
        assert batch.main(["run", str(grid), "--runs-dir", str(runs)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert "is in use by another runner" in err and f"pid {first.pid}" in err and str(runs / "l") in err
    finally:
        hold.unlink()
        first.wait(timeout=120)
    assert first.returncode == 0, first.stderr.read()
    assert len(counter.read_text().splitlines()) == 1  # the job ran once, by the first runner
    # The lock ends with its runner: the next run goes on (and skips the finished job).
    report = batch.run(grid, runs_dir=runs)
    assert report.ok and len(report.skipped) == 1


def test_the_lock_is_released_when_the_block_ends_or_fails(tmp_path):
    with batch.lock_run_folder(tmp_path):
        pass
    try:
        with batch.lock_run_folder(tmp_path):
            raise KeyError("boom")
    except KeyError:
        pass
    with batch.lock_run_folder(tmp_path):
        holder = subprocess.run(
            [sys.executable, "-c", "import sys; from pathlib import Path; from freereg_lib.commands.batch import "
             "lock_run_folder\nwith lock_run_folder(Path(sys.argv[1])): pass", str(tmp_path)],
            cwd=ROOT, capture_output=True, text=True)
        assert holder.returncode != 0 and "RunFolderLocked" in holder.stderr and "in use by another runner" in holder.stderr
    assert (tmp_path / batch.LOCK_FILE).is_file()
