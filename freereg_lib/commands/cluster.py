"""The distributed engine of the batch runner: Dask distributed (``batch run --executor dask``).

This module owns everything about the engine and nothing about notebooks: choosing the
executor (command line over the grid's ``executor`` entry), starting a local cluster (one
worker process per GPU, each pinned to its GPU with ``CUDA_VISIBLE_DEVICES``) or connecting
to a running scheduler (a SLURM or PBS allocation), submitting one task per job or shard,
running a task again when the worker or kernel under it died (a bounded number of times),
the progress bar and the dashboard link. :mod:`freereg_lib.commands.batch` decides what a task is
(:func:`freereg_lib.commands.batch.execute_unit`: one papermill execution into its own folder) and
records what comes back; this module imports nothing from it, so there is no import cycle.

dask and distributed are imported only when the engine starts: the local executor, the
default, needs neither. Why Dask and not Ray: docs/real_data.md, "Several GPUs or machines".

Two kinds of failure, told apart on purpose:

- *the task's own*: the notebook raised. The task returns the one-line error; it is
  reported once and never re-run by the engine (re-running the grid re-runs it, as with the
  local executor).
- *the machinery's*: the worker process died (killed, out of memory, its node lost) or the
  notebook's kernel died. The scheduler runs a task whose worker died on another worker up to
  ``distributed.scheduler.allowed-failures`` times, then gives up with ``KilledWorker``; a
  task whose kernel died raises :class:`Retry` and is submitted again up to ``retries`` times.
"""
from __future__ import annotations

import re
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

EXECUTORS = ("local", "dask")
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def available_cores() -> int:
    """The CPUs this process may run on (its affinity where the OS has one)."""
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def worker_thread_env(n_workers: int, cores: int | None = None, environ=None) -> dict[str, str]:
    """The ``*_NUM_THREADS`` each of ``n_workers`` local workers gives its notebook kernels: the
    ``cores`` (this process's CPUs when None) shared out, at least one each; a variable set in
    ``environ`` (``os.environ`` when None) is the user's and is left to it.

    Without a cap every kernel's torch and OpenMP use all the cores and their threads spin
    against each other: two micro FreeReg-D runs at once on 2 cores took 8.5x the time of one
    after the other, one thread each 0.5x (benchmarks/README.md, "Threads of parallel kernels").
    """
    import os

    environ = os.environ if environ is None else environ
    cores = available_cores() if cores is None else cores
    share = str(max(1, cores // max(1, n_workers)))
    return {k: share for k in THREAD_VARIABLES if k not in environ}


_OPTION_KEYS = ("scheduler", "workers", "gpus", "shards", "resources", "retries", "dashboard", "connect_timeout")
# A scheduler address as distributed reads it: tcp://host:port, tls://..., or host:port.
_ADDRESS = re.compile(r"([a-z][a-z0-9+]*://)?[^\s/:]+(:\d+)?")


class EngineError(RuntimeError):
    """The engine cannot run: dask is not installed, the scheduler cannot be reached, or it
    dropped the run. The message is one line for the user."""


class Retry(Exception):
    """Raised by a task that failed for a reason outside itself (its kernel died), so that
    the engine runs it again instead of reporting a result."""


@dataclass
class DaskOptions:
    """How the dask executor runs (the grid's ``executor`` mapping, or the command line)."""

    scheduler: str | None = None  # tcp://host:port or a scheduler file; None: a cluster on this machine
    workers: int | None = None  # local cluster: worker processes (default: one per GPU, else 2)
    gpus: list[str] = field(default_factory=list)  # local cluster: one worker per GPU id
    shards: int = 1  # each job split into this many shards, scheduled as separate tasks
    resources: dict[str, float] = field(default_factory=dict)  # what a task needs of a worker
    retries: int = 2  # runs again after a worker (local cluster) or kernel died under the task
    dashboard: str = ":8787"  # local cluster: the dashboard's address; "" (or false): none
    connect_timeout: float = 10.0  # seconds to reach --scheduler before giving up


def executor_spec(value: Any, where: str) -> dict:
    """The grid's ``executor`` entry checked: ``{"kind": "local" | "dask", option: value ...}``.

    ``executor: dask`` is short for ``executor: {kind: dask}``; the options are
    :class:`DaskOptions` fields (``scheduler``, ``workers``, ``gpus``, ``shards``,
    ``resources``, ``retries``, ``dashboard``, ``connect_timeout``). Raises ``ValueError`` with one line.
    """
    spec = {"kind": value} if isinstance(value, str) or value is None else value
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: `executor` is local, dask, or a mapping {{kind: dask, workers: 2, ...}}")
    kind = spec.get("kind") or "local"
    check_kind(kind, f"{where}: executor")
    options = {k: v for k, v in spec.items() if k != "kind"}
    dask_options(options, where)  # checked now, before anything runs, even if the command line overrides it
    return {"kind": kind, **options}


def check_kind(kind: Any, what: str = "executor") -> str:
    """``kind`` when it names an executor, else ``ValueError`` (one line)."""
    if kind not in EXECUTORS:
        raise ValueError(f"unknown {what} {kind!r}; choose one of {list(EXECUTORS)}")
    return kind


def choose(grid_spec: dict, kind: str | None, overrides: dict | None, where: str) -> tuple[str, DaskOptions | None]:
    """The executor of a run and its options: the command line's ``kind`` and ``overrides``
    (DaskOptions fields; None values are "not given") over the grid's ``executor`` entry."""
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    kind = check_kind(kind or grid_spec.get("kind") or "local")
    if kind == "local":
        if given:
            flags = ", ".join(f"--{k}" for k in given)
            raise ValueError(f"{flags} go(es) with the dask executor; add --executor dask")
        return kind, None
    grid_options = {k: v for k, v in grid_spec.items() if k != "kind"}
    return kind, dask_options({**grid_options, **given}, f"{where} and the command line" if given else where)


def dask_options(values: dict, where: str = "dask options") -> DaskOptions:
    """:class:`DaskOptions` from a mapping, each value checked (``ValueError``, one line).

    ``gpus`` may be a list or a comma-separated string (``"0,1"``); ``resources`` a mapping
    or ``"GPU=1,MEM=2e9"``."""
    v = dict(values)
    unknown = sorted(set(v) - set(_OPTION_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown executor option(s) {unknown}; it takes kind and {list(_OPTION_KEYS)}")

    def fail(key: str, want: str):
        raise ValueError(f"{where}: executor {key}={v[key]!r}: expected {want}")

    def positive_int(key: str, low: int):
        value = v.get(key)
        if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < low):
            fail(key, f"an integer >= {low}")

    positive_int("workers", 1)
    positive_int("shards", 1)
    positive_int("retries", 0)
    timeout = v.get("connect_timeout")
    if timeout is not None and (not isinstance(timeout, (int, float)) or isinstance(timeout, bool) or timeout <= 0):
        fail("connect_timeout", "a number of seconds > 0")
    if v.get("gpus") is not None:
        gpus = v["gpus"]
        if isinstance(gpus, (str, int)) and not isinstance(gpus, bool):
            gpus = [g for g in str(gpus).split(",") if g.strip()]
        if not isinstance(gpus, list) or not gpus or not all(re.fullmatch(r"[\w-]+", str(g).strip()) for g in gpus):
            fail("gpus", "GPU ids such as [0, 1] or '0,1' (one worker per GPU)")
        v["gpus"] = [str(g).strip() for g in gpus]
        if len(set(v["gpus"])) != len(v["gpus"]):
            fail("gpus", "each GPU once")
    if v.get("resources") is not None:
        res = v["resources"]
        if isinstance(res, str):
            pairs = [p.split("=", 1) for p in res.split(",") if p.strip()]
            if not all(len(p) == 2 for p in pairs):
                fail("resources", "NAME=amount pairs such as 'GPU=1'")
            try:
                res = {name.strip(): float(amount) for name, amount in pairs}
            except ValueError:
                fail("resources", "NAME=amount pairs with numbers, such as 'GPU=1'")
        if not isinstance(res, dict) or not all(
                isinstance(a, (int, float)) and not isinstance(a, bool) and a > 0 for a in res.values()):
            fail("resources", "a mapping of resource names to positive amounts, such as {GPU: 1}")
        v["resources"] = res
    if v.get("dashboard") is False:
        v["dashboard"] = ""
    for key in ("scheduler", "dashboard"):
        if v.get(key) is not None and not isinstance(v[key], str):
            fail(key, "a string")
    if v.get("scheduler"):
        # Whether the file exists is seen when connecting: a scheduler deletes its file when it
        # stops, and a later `merge` of the same grid must still load it.
        if re.search(r"\s", v["scheduler"]):
            fail("scheduler", "an address such as tcp://10.0.0.5:8786, or a scheduler file")
        for key in ("workers", "gpus"):
            if v.get(key):
                raise ValueError(f"{where}: executor {key} sizes a cluster on this machine; with a scheduler "
                                 "the workers are the ones started for it (dask worker ADDRESS ...)")
    if v.get("workers") and v.get("gpus") and v["workers"] != len(v["gpus"]):
        raise ValueError(f"{where}: executor workers={v['workers']} but {len(v['gpus'])} GPU(s): a local "
                         "cluster has one worker per GPU; drop workers")
    if not v.get("scheduler"):
        offered = {"GPU": 1} if v.get("gpus") else {}
        missing = {k: a for k, a in (v.get("resources") or {}).items() if a > offered.get(k, 0)}
        if missing:
            raise ValueError(f"{where}: executor resources {missing}: no worker of a local cluster would offer "
                             "them, so the jobs would wait forever (give gpus to have GPU=1 per worker)")
    return DaskOptions(**{k: val for k, val in v.items() if val is not None})


@dataclass
class Outcome:
    """What became of one task. ``error`` is None when it finished; ``lost`` is True when the
    worker or kernel under it died every time, so the error is the engine's, not the notebook's."""

    name: str
    error: str | None
    attempts: int = 1
    lost: bool = False


class DaskExecutor:
    """Runs tasks on a Dask cluster: a local one it starts, or the one at ``options.scheduler``.

    Use as a context manager; :meth:`run` yields an :class:`Outcome` per task as tasks end.
    """

    def __init__(self, options: DaskOptions):
        self.options = options
        self.client = None
        self.cluster = None

    def __enter__(self) -> "DaskExecutor":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ----------------------------------------------------------------------------------
    def start(self) -> None:
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise EngineError("the dask executor needs the packages dask and distributed: "
                              "pip install -r environment/requirements.txt") from None
        if self.options.scheduler:
            self.client = self._connect(self.options.scheduler)
            try:  # a lambda travels by value: the scheduler need not import this library
                allowed = self.client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.allowed_failures)
            except Exception:  # a scheduler that refuses to run code: say what bounds it instead
                allowed = "its distributed.scheduler.allowed-failures"
            where = f"scheduler {self.client.scheduler.address}"
        else:
            from distributed import Client

            self.cluster = self._local_cluster()
            self.client = Client(self.cluster)
            allowed = self.options.retries
            where = "a local cluster"
        n_workers = len(self.client.scheduler_info().get("workers", {}))
        services = self.client.scheduler_info().get("services", {})
        link = self.client.dashboard_link if "dashboard" in services else "none"
        print(f"dask: {where}, {n_workers} worker(s), dashboard {link}; a task whose worker dies runs "
              f"again on another worker up to {allowed} time(s)", file=sys.stderr, flush=True)
        if self.options.scheduler and not n_workers:
            print("dask: no worker yet; the jobs wait until workers connect (dask worker ADDRESS ...)",
                  file=sys.stderr, flush=True)

    def _connect(self, target: str):
        from distributed import Client

        timeout = self.options.connect_timeout
        if not Path(target).is_file() and not _ADDRESS.fullmatch(target):
            raise EngineError(f"no scheduler file {target}, and it is not an address (tcp://host:8786): "
                              "has the scheduler started?")
        try:
            if Path(target).is_file():
                return Client(scheduler_file=target, timeout=timeout)
            return Client(target, timeout=timeout)
        except (OSError, TimeoutError, ValueError) as exc:
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise EngineError(f"cannot reach the Dask scheduler at {target} within {timeout:g} s ({reason}); "
                              "start one (dask scheduler) or check the address") from None

    def _local_cluster(self):
        import logging

        import dask
        from distributed import Nanny, Scheduler, SpecCluster

        opts = self.options
        gpus = opts.gpus or []
        names = [f"gpu{g}" for g in gpus] or [str(i) for i in range(opts.workers or 2)]
        threads = worker_thread_env(len(names))
        workers = {}
        for k, name in enumerate(names):
            # One thread: a worker runs one job (one kernel) at a time. No memory limit: the
            # job's memory is in its kernel, a child process the nanny does not measure; the
            # operating system's OOM killer ends a job that overflows (then Retry).
            options = {"nthreads": 1, "memory_limit": 0, "silence_logs": logging.WARNING, "dashboard": False,
                       "env": dict(threads)}
            if gpus:
                options["env"]["CUDA_VISIBLE_DEVICES"] = gpus[k]
                options["resources"] = {"GPU": 1}
            workers[name] = {"cls": Nanny, "options": options}
        scheduler = {"cls": Scheduler, "options": {
            "host": "127.0.0.1", "allowed_failures": opts.retries,
            "dashboard": bool(opts.dashboard), "dashboard_address": opts.dashboard or ":0"}}
        # Dask caps numpy's threads at one per worker process for its many-small-tasks use; a
        # job here is a whole notebook in its own kernel, whose share of the cores is set above
        # (worker_thread_env; the user's own *_NUM_THREADS still apply).
        config = {f"distributed.nanny.pre-spawn-environ.{k}": None for k in THREAD_VARIABLES}
        # A worker gets its next job only when it is free: jobs are long, and a job queued on a
        # worker that dies would be counted as one of the deaths it is allowed.
        config["distributed.scheduler.worker-saturation"] = 1.0
        with dask.config.set(config):
            return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.WARNING,
                               name="freereg-batch")

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        self.client = self.cluster = None

    # ----------------------------------------------------------------------------------
    def run(self, fn: Callable[..., str | None], tasks: dict[str, tuple], desc: str = "jobs") -> Iterator[Outcome]:
        """Run ``fn(*args)`` for each ``name: args`` of ``tasks``; yield an :class:`Outcome` as
        each one ends. ``fn`` returns None (finished) or its one-line error (not re-run); it
        raises :class:`Retry` to be run again, up to ``retries`` times; any other exception it
        raises (a full disk) stops the run and is raised here, the other tasks cancelled."""
        from distributed import KilledWorker, wait
        from tqdm.auto import tqdm

        token = uuid.uuid4().hex[:8]  # two runs on one scheduler never share a task key
        attempts = {name: 1 for name in tasks}
        pending = {self._submit(fn, name, args, 1, token): name for name, args in tasks.items()}
        failed = 0
        bar = tqdm(total=len(tasks), desc=desc, unit="job")
        try:
            while pending:
                try:
                    wait(list(pending), timeout=1.0, return_when="FIRST_COMPLETED")
                except TimeoutError:
                    pass  # nothing ended within the second: refresh the running count below
                for future in [f for f in pending if f.done()]:
                    name = pending.pop(future)
                    outcome = None
                    if future.status == "finished":
                        error = future.result()
                        outcome = Outcome(name, error, attempts[name])
                    elif future.status == "cancelled":
                        raise EngineError(f"the Dask scheduler dropped the task of {name} (was it restarted?); "
                                          "run the same command again")
                    else:
                        exc = future.exception()
                        if isinstance(exc, KilledWorker):
                            outcome = Outcome(name, f"KilledWorker: its worker died {exc.allowed_failures + 1} "
                                              "time(s) while running it (killed, or out of memory); see the "
                                              "worker logs", attempts[name], lost=True)
                        elif isinstance(exc, Retry) and attempts[name] <= self.options.retries:
                            attempts[name] += 1
                            pending[self._submit(fn, name, tasks[name], attempts[name], token)] = name
                        elif isinstance(exc, Retry):
                            outcome = Outcome(name, f"{exc} ({attempts[name]} attempts)", attempts[name], lost=True)
                        else:
                            raise exc
                    if outcome is not None:
                        failed += outcome.error is not None
                        bar.update(1)
                        yield outcome
                bar.set_postfix_str(f"running {self._running(pending)}, failed {failed}", refresh=True)
        finally:
            bar.close()
            if pending:  # stopped early (an error, Ctrl-C): nothing of this run stays queued
                self.client.cancel(list(pending))

    def _submit(self, fn, name: str, args: tuple, attempt: int, token: str):
        key = f"{name}-attempt{attempt}-{token}"
        return self.client.submit(fn, *args, key=key, pure=False, resources=self.options.resources or None)

    def _running(self, pending: dict) -> int:
        """How many of ``pending`` are on a worker now (the rest wait in the scheduler's queue)."""
        try:
            processing, threads = self.client.processing(), self.client.nthreads()
        except Exception:  # a progress figure is not worth failing a run over
            return 0
        keys = {f.key for f in pending}
        # A worker may hold more tasks than threads (queued there): count at most its threads.
        return sum(min(threads.get(w, 1), sum(k in keys for k in ks)) for w, ks in processing.items())

