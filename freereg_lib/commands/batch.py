"""Batch reproduction: a grid of notebooks run with papermill, resumable, shardable, tabulated.

Command line (run it from the repository root)::

    python -m freereg_lib batch run GRID.yaml [--name NAME] [--shard i/n] [--runs-dir runs]
                                              [--force] [--log-output] [--kernel python3]
                                              [--executor local|dask] [--workers N] [--gpus 0,1]
                                              [--scheduler ADDRESS] [--shards N] [--retries N]
                                              [--resources GPU=1] [--dashboard :8787]
    python -m freereg_lib batch merge GRID.yaml [--name NAME] [--runs-dir runs]

``run`` executes every job of the grid that has not finished yet, then writes the results
table; it exits 1 when a job failed. The local executor (the default) runs the jobs one
after the other in this process; ``--executor dask`` runs them as tasks of a Dask cluster
(:mod:`freereg_lib.commands.cluster`): a local one with ``--workers N`` or one worker per GPU of
``--gpus``, or the running scheduler at ``--scheduler``; ``--shards N`` splits every job into
N shards that the engine schedules, merged into the table at the end. ``merge`` only writes
the table, from whatever finished job or complete set of shards lies under ``runs/<name>/``
(copy the shard folders of other machines there first after ``--shard i/n`` runs by hand);
it exits 1 when a job is still incomplete.

The grid file (YAML)::

    name: table1                          # run name (default: the file's stem)
    notebooks: [notebooks/04_benchmark.ipynb]
    base: {backend: real}                 # parameters shared by every job
    sets:                                 # explicit parameter sets (default: one empty set)
      - {dataset: 3dmatch, data_root: data/3dmatch}
    grid: {seed: [0, 1]}                  # lists expanded as a cartesian product
    executor: {kind: dask, gpus: [0, 1]}  # optional; local (default) or dask with its options
                                          # (freereg_lib.commands.cluster.DaskOptions); flags override it

The jobs are notebooks x sets x grid points; a job's parameters are ``base | set | point``.
A mapping that repeats a key is refused, and so is a value outside the range of the config
field it sets (:func:`freereg_lib.report.params.range_problem`).
A relative notebook path is looked up in the working directory, then beside the grid file.

What lands on disk, under ``<runs-dir>/<name>/``::

    grid.yaml                    copy of the grid last run
    .runner.lock                 flock-ed by the runner while it runs: a second runner stops at once
    <job-id>/job.json            the job's notebook and parameters
    <job-id>/notebook.ipynb      the executed notebook (kept when it fails)
    <job-id>/out/                the notebook's ``out_dir``: pairs.csv, results.csv, config.json
    <job-id>/error.txt           why the job failed
    <job-id>/done.json           written last: the job finished
    <job-id>/shard-<i>of<n>/     the same five, per shard, when run with ``--shard i/n`` or ``--shards n``
    results.csv, results.md      one row per job x (method, solver), the paper's Table 1 beside

The contract with a benchmark notebook: its ``parameters`` cell declares ``out_dir`` (str)
and ``shard`` (str ``"i/n"``, default ``"0/1"``); it keeps its share of the pairs with
:func:`shard_items` and writes the rows of :func:`freereg_lib.pipeline.run_pairs` with
:func:`write_rows` (``<out_dir>/pairs.csv``) and its summary to ``<out_dir>/results.csv``.
The results table is always re-aggregated from ``pairs.csv`` with
:func:`freereg_lib.pipeline.summarize`, so sharded and unsharded runs give the same table.
"""
from __future__ import annotations

import argparse
import errno
import json
import re
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from freereg_lib.commands import cluster
from freereg_lib.commands.batch_files import LOCK_FILE, RunFolderLocked, lock_run_folder  # noqa: F401
from freereg_lib.commands.batch_grid import (  # noqa: F401
    CONTRACT_PARAMS, SOLVERS, Grid, Job, _declared_parameters, check_name, job_id, load_grid)
from freereg_lib.commands.batch_rows import (  # noqa: F401
    _MISSING,
    PAPER_DATASETS,
    PAPER_METRICS,
    _sha256,
    complete_units,
    job_table,
    library_fingerprint,
    read_config,
    read_done,
    read_rows,
    results_table,
    stale_reason,
    verify_unit,
    write_rows,
    write_table,
)
from freereg_lib.data.shards import parse_shard, shard_items  # noqa: F401 - the notebooks' contract, re-exported

# --------------------------------------------------------------------------------------
# The notebook side of the contract: shards and per-pair rows.

# parse_shard and shard_items live in freereg_lib.data.shards (the loaders use them too); re-exported above.


# --------------------------------------------------------------------------------------
# Grids and jobs.


# --------------------------------------------------------------------------------------
# Running.

def unit_dir(run_dir: Path, job: Job, shard: str) -> Path:
    """Where one execution of ``job`` lives: the job folder, or its ``shard-<i>of<n>`` folder."""
    i, n = parse_shard(shard)
    return run_dir / job.id if n == 1 else run_dir / job.id / f"shard-{i}of{n}"


def write_done(unit: Path, job: Job, shard: str, **facts) -> dict:
    """Write ``unit/done.json`` (atomically, last): the job, its row count and the SHA-256 of
    ``out/pairs.csv``, the library fingerprint, the notebook's hash and the effective
    configuration (``out/config.json``); ``facts`` are added. Returns what it wrote."""
    pairs = unit / "out" / "pairs.csv"
    config = unit / "out" / "config.json"
    done = {"notebook": job.notebook, "params": job.params, "shard": shard,
            "rows": len(read_rows(unit / "out")), "pairs_sha256": _sha256(pairs),
            "library": library_fingerprint(), "notebook_sha256": _sha256(job.path),
            "config": json.loads(config.read_text()) if config.is_file() else None, **facts}
    tmp = unit / "done.json.tmp"
    tmp.write_text(json.dumps(done, indent=1))
    tmp.replace(unit / "done.json")  # atomic: a marker is never half written
    return done


def is_done(unit: Path, job: Job, shard: str) -> bool:
    """True when ``unit`` holds a finished execution of ``job`` with the same parameters, by
    the current library and notebook, whose ``pairs.csv`` is intact (:func:`verify_unit`)."""
    done = read_done(unit)
    if done is None or done.get("params") != job.params or done.get("shard") != shard:
        return False
    return not verify_unit(unit) and not stale_reason(unit, job)


def run_job(job: Job, unit: Path, shard: str, kernel: str = "python3", log_output: bool = False) -> str | None:
    """Execute ``job`` into ``unit``; returns None when it finished, else the error in one line.

    The previous outputs of ``unit`` are cleared first. On failure the executed notebook
    stays (papermill saves it with the failing cell) and ``error.txt`` holds the error and
    its traceback; ``done.json`` is written only after the notebook finished and wrote
    ``pairs.csv``, so an interrupted job simply runs again next time.
    """
    import papermill as pm

    out = unit / "out"
    unit.mkdir(parents=True, exist_ok=True)
    for stale in ("done.json", "error.txt"):
        (unit / stale).unlink(missing_ok=True)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    params = {**job.params, "out_dir": str(out.resolve()), "shard": shard}
    # A notebook's figures go to its own job folder, not the checkout's shared ../figures: two
    # runs in one checkout overwrote each other's PNGs there (FileNotFoundError, "broken PNG"),
    # and the run's lock covers only its run folder.
    if "figures_dir" not in job.params and "figures_dir" in _declared_parameters(job.path):
        shutil.rmtree(unit / "figures", ignore_errors=True)
        params["figures_dir"] = str((unit / "figures").resolve())
    job_facts = {"notebook": job.notebook, "params": job.params, "shard": shard}
    (unit / "job.json").write_text(json.dumps(job_facts, indent=1))
    start = time.time()
    try:
        pm.execute_notebook(
            str(job.path), str(unit / "notebook.ipynb"),
            parameters=params,
            # "python3" is the ipykernel of the running interpreter: jupyter_client swaps the
            # spec's bare `python` for sys.executable, so jobs use this very environment.
            kernel_name=kernel, cwd=str(job.path.parent), progress_bar=False,
            # The notebook's streams go straight to ours; papermill's own log_output would
            # print stderr a second time through its logger.
            stdout_file=sys.stdout if log_output else None, stderr_file=sys.stderr if log_output else None,
            # The notebook has run and been saved: kill its kernel. A graceful exit tears down
            # torch, diffusers and Open3D (~1 s of CPU a kernel) and now and then waits 2.5 s more.
            shutdown_kernel="immediate",
        )
        if not (out / "pairs.csv").is_file():
            raise RuntimeError(
                f"the notebook finished without writing {out / 'pairs.csv'} "
                "(a batch notebook writes its rows with freereg_lib.commands.batch.write_rows(rows, out_dir))"
            )
        same_error = configuration_failure(read_rows(out))
        if same_error:
            raise RuntimeError(same_error)
    except Exception as exc:  # any failure is recorded per job so the others go on
        if isinstance(exc, OSError) and exc.errno in _FATAL_ERRNOS:
            raise  # a full disk or a read-only folder stops the run: every next job would fail too
        headline, detail = _describe_failure(exc)
        (unit / "error.txt").write_text(f"{headline}\n\n{detail}\n")
        return headline
    write_done(unit, job, shard, seconds=round(time.time() - start, 3),
               finished=time.strftime("%Y-%m-%dT%H:%M:%S"))
    return None


_FATAL_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EPERM, errno.EDQUOT}
_EXCEPTION_TEXT = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception)\b")


def configuration_failure(rows: list[dict]) -> str:
    """A message when every row failed with the same exception (a configuration error such
    as an unknown solver repeated on every pair, not a result), else ``""``."""
    errors = {str(r.get("error", "")) for r in rows}
    if not rows or len(errors) != 1:
        return ""
    error = errors.pop()
    if not _EXCEPTION_TEXT.match(error):
        return ""
    return (f"every one of the {len(rows)} row(s) failed with the same error, so the job has no "
            f"result (a configuration error?): {error}")


def _describe_failure(exc: Exception) -> tuple[str, str]:
    """A one-line headline and the full detail (the notebook's traceback without colours)."""
    if hasattr(exc, "ename") and hasattr(exc, "traceback"):  # papermill's PapermillExecutionError
        where = f" (In [{exc.exec_count}])" if getattr(exc, "exec_count", None) is not None else ""
        detail = re.sub(r"\x1b\[[0-9;]*m", "", "\n".join(exc.traceback))
        return f"{exc.ename}: {exc.evalue}{where}", detail
    return f"{type(exc).__name__}: {exc}", "".join(traceback.format_exception(exc))


@dataclass
class Report:
    """What a ``run`` or ``merge`` did. Ids of finished, skipped and failed (with the error)
    jobs, and the jobs missing from the table with the reason."""

    run_dir: Path
    finished: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    incomplete: dict[str, str] = field(default_factory=dict)
    rerun: dict[str, str] = field(default_factory=dict)    # finished before, run again: why
    flagged: dict[str, str] = field(default_factory=dict)  # in the table, but out of date: why

    @property
    def ok(self) -> bool:
        return not self.failed and not self.incomplete

    def summary(self) -> str:
        lines = [f"{self.run_dir}: {len(self.finished)} job(s) ran, {len(self.skipped)} already "
                 f"done (skipped), {len(self.failed)} failed"]
        lines += [f"  finished {j}" + (f" (run again: {self.rerun[j]})" if j in self.rerun else "")
                  for j in self.finished]
        lines += [f"  OUT OF DATE {j}: {why}; `run` re-runs it" for j, why in self.flagged.items()]
        lines += [f"  FAILED {j}: {e}\n         see {self.run_dir / j}" for j, e in self.failed.items()]
        lines += [f"  not in the table: {j}: {why}" for j, why in self.incomplete.items() if j not in self.failed]
        lines.append(f"results: {self.run_dir / 'results.csv'} and results.md")
        return "\n".join(lines)


def run(grid_path, name: str | None = None, shard: str = "0/1", runs_dir="runs", force: bool = False,
        log_output: bool = False, kernel: str = "python3", executor: str | None = None,
        engine: dict | None = None) -> Report:
    """Run every unfinished job of the grid (shard ``shard`` of each), then write the table.

    ``force`` re-runs finished jobs; ``log_output`` streams what the notebooks print to
    this terminal (text only: a tqdm bar that renders as a Jupyter widget does not stream).
    ``executor`` is ``"local"`` (jobs one after the other here) or ``"dask"`` (tasks of a Dask
    cluster, :mod:`freereg_lib.commands.cluster`); None takes the grid's ``executor``, else local.
    ``engine`` holds dask options (:class:`cluster.DaskOptions` fields, None = not given) that
    override the grid's.
    """
    parse_shard(shard)
    grid = load_grid(grid_path)
    kind, options = cluster.choose(grid.executor, executor, engine, str(grid.path))
    if kind == "dask" and shard != "0/1":
        raise ValueError("--shard i/n splits the pairs by hand for the local executor; with the dask "
                         "executor use --shards N and the engine schedules the shards")
    run_dir = Path(runs_dir) / check_name(name or grid.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    with lock_run_folder(run_dir):
        shutil.copyfile(grid.path, run_dir / "grid.yaml")
        report = Report(run_dir)
        if kind == "local":
            _run_here(grid, run_dir, shard, force, log_output, kernel, report)
        else:
            _run_on_dask(grid, run_dir, options, force, log_output, kernel, report)
        report.incomplete = write_table(run_dir, grid.jobs, report.flagged)
    return report


def _needs_run(job: Job, unit: Path, shard: str, force: bool, report: Report, label: str) -> bool:
    """Whether ``unit`` must run; notes in ``report.rerun`` why a finished one runs again."""
    if not force and is_done(unit, job, shard):
        return False
    if read_done(unit) is not None and not force:
        why = verify_unit(unit) or stale_reason(unit, job)
        if why:
            report.rerun[label] = why
    return True


def _run_here(grid: Grid, run_dir: Path, shard: str, force: bool, log_output: bool, kernel: str,
              report: Report) -> None:
    """The local executor: the jobs one after the other in this process."""
    from tqdm.auto import tqdm

    bar = tqdm(grid.jobs, desc=f"{run_dir.name} [{shard}]", unit="job")
    for job in bar:
        unit = unit_dir(run_dir, job, shard)
        if not _needs_run(job, unit, shard, force, report, job.id):
            report.skipped.append(job.id)
            continue
        bar.set_postfix_str(job.id, refresh=True)
        error = run_job(job, unit, shard, kernel, log_output)
        if error is None:
            report.finished.append(job.id)
        else:
            report.failed[job.id] = error
    bar.close()


def _run_on_dask(grid: Grid, run_dir: Path, options: cluster.DaskOptions, force: bool, log_output: bool,
                 kernel: str, report: Report) -> None:
    """The dask executor: every unfinished job, or each unfinished shard of it, one task.

    A job counts as finished when it finished unsharded or every one of its ``options.shards``
    shards did; the table then merges whichever it has (:func:`complete_units`).
    """
    # Workers may run elsewhere (another node of a shared file system, another working folder).
    where = run_dir.resolve()
    n = options.shards
    shards = [f"{i}/{n}" for i in range(n)]
    tasks: dict[str, tuple] = {}
    for job in grid.jobs:
        if not force and (is_done(where / job.id, job, "0/1")
                          or all(is_done(unit_dir(where, job, s), job, s) for s in shards)):
            report.skipped.append(job.id)
            continue
        if n > 1:  # an unsharded result still here (out of date, or --force) would win in the table
            (where / job.id / "done.json").unlink(missing_ok=True)
        for s in shards:
            label = job.id if n == 1 else f"{job.id} [shard {s}]"
            unit = unit_dir(where, job, s)
            if _needs_run(job, unit, s, force, report, label):
                tasks[label] = (job, unit, s, kernel, log_output)
    if not tasks:
        return
    with cluster.DaskExecutor(options) as engine:
        for outcome in engine.run(execute_unit, tasks, desc=f"{run_dir.name} [dask]"):
            if outcome.error is None:
                report.finished.append(outcome.name)
                continue
            report.failed[outcome.name] = outcome.error
            if outcome.lost:  # the worker or kernel died each time: say so first in error.txt
                unit = tasks[outcome.name][1]
                unit.mkdir(parents=True, exist_ok=True)
                error_file = unit / "error.txt"
                before = error_file.read_text() if error_file.is_file() else ""
                last = f"\nThe last attempt's error:\n{before}" if before else ""
                error_file.write_text(f"{outcome.error}\n{last}")


def execute_unit(job: Job, unit: Path, shard: str, kernel: str = "python3", log_output: bool = False) -> str | None:
    """:func:`run_job` as a task of the dask executor (it runs on a worker).

    A job whose kernel died (killed, out of memory) raises :class:`cluster.Retry`, so the
    engine runs it again, a bounded number of times; any other failure is the job's own (an
    error in the notebook) and comes back as its one-line error, to be reported once.
    """
    error = run_job(job, unit, shard, kernel, log_output)
    if error is not None and error.startswith("DeadKernelError"):
        raise cluster.Retry(error)
    return error


def merge(grid_path, name: str | None = None, runs_dir="runs") -> Report:
    """Write the results table of a run from the finished jobs and complete shard sets."""
    grid = load_grid(grid_path)
    run_dir = Path(runs_dir) / check_name(name or grid.name)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run folder {run_dir}; run the grid (or copy its shards there) first")
    report = Report(run_dir)
    report.incomplete = write_table(run_dir, grid.jobs, report.flagged)
    return report


# --------------------------------------------------------------------------------------
# Command line.

def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m freereg_lib batch``; returns the exit status."""
    parser = argparse.ArgumentParser(prog="freereg batch", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for cmd, text in (("run", "run the grid's unfinished jobs, then write the results table"),
                      ("merge", "write the results table from finished jobs and complete shard sets")):
        p = sub.add_parser(cmd, help=text, description=text)
        p.add_argument("grid", help="grid YAML file")
        p.add_argument("--name", help="run name (default: the grid's `name`, else its file stem)")
        p.add_argument("--runs-dir", default="runs", help="parent folder of runs (default: runs)")
        if cmd == "run":
            p.add_argument("--shard", default="0/1", help="run shard i/n of every job's pairs (default 0/1)")
            p.add_argument("--force", action="store_true", help="re-run jobs that already finished")
            p.add_argument("--log-output", action="store_true", help="stream the notebooks' output here")
            p.add_argument("--kernel", default="python3", help="Jupyter kernel name (default python3)")
            g = p.add_argument_group("engine", "where the jobs run (default: the grid's `executor`, else local)")
            g.add_argument("--executor", help="local (one job after the other, here) or dask")
            g.add_argument("--scheduler", help="dask: address (tcp://host:8786) or scheduler file of a running "
                                               "scheduler; default: a cluster on this machine")
            g.add_argument("--workers", type=int, help="dask, local cluster: worker processes (default 2)")
            g.add_argument("--gpus", help="dask, local cluster: one worker per GPU id, e.g. 0,1,2,3")
            g.add_argument("--shards", type=int, help="dask: split every job into N shards (default 1)")
            g.add_argument("--retries", type=int, help="dask: runs again after the worker or kernel under a "
                                                       "job died (default 2)")
            g.add_argument("--resources", help="dask: what a job needs of a worker, e.g. GPU=1")
            g.add_argument("--dashboard", help="dask, local cluster: dashboard address (default :8787; '' for none)")
    args = parser.parse_args(argv)
    try:
        if args.command == "run":
            engine = {k: getattr(args, k) for k in ("scheduler", "workers", "gpus", "shards", "retries",
                                                    "resources", "dashboard")}
            report = run(args.grid, args.name, args.shard, args.runs_dir, args.force, args.log_output, args.kernel,
                         args.executor, engine)
        else:
            report = merge(args.grid, args.name, args.runs_dir)
    except (FileNotFoundError, ValueError, cluster.EngineError, RunFolderLocked) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a read-only or full disk, a file where a folder should be
        where = f" {exc.filename}" if exc.filename else ""
        print(f"error: cannot write or read{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(report.summary())
    if args.command == "run":
        return 1 if report.failed else 0
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
