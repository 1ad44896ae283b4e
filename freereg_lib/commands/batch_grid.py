"""The batch runner's grid: the YAML file read and checked, its jobs and their ids.

:func:`load_grid` reads a grid file (:mod:`freereg_lib.commands.batch` documents its keys) and
refuses, with one line naming the file and the key, a repeated key, an unknown notebook or
parameter, a value of the wrong type and a value outside the range of the config field it sets.
"""
from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from freereg_lib.commands import cluster
from freereg_lib.commands.batch_files import unique_key_loader
from freereg_lib.commands.batch_rows import _MISSING
from freereg_lib.config import FreeRegConfig, config_for

_GRID_KEYS = {"name", "notebook", "notebooks", "base", "sets", "grid", "executor"}
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._+-]*")
SOLVERS = ("pnp", "kabsch")  # pipeline.solve's
CONTRACT_PARAMS = ("out_dir", "shard")


@dataclass(frozen=True)
class Job:
    """One notebook with one parameter set.

    ``notebook`` is the path as the grid wrote it (it enters the id), ``path`` the file
    found; ``label`` holds the parameters that vary across the grid (for a readable id).
    """

    notebook: str
    path: Path
    params: dict
    label: dict = field(default_factory=dict)

    @property
    def id(self) -> str:
        return job_id(self.notebook, self.params, self.label)


def job_id(notebook: str, params: dict, label: dict | None = None) -> str:
    """``<notebook stem>-<k=v of label>-<10 hex>``: the hash covers the notebook path and
    every parameter, so it is stable across runs and machines; the middle part is only for
    reading (it is cut to 60 characters)."""
    blob = json.dumps({"notebook": Path(notebook).as_posix(), "params": params}, sort_keys=True)
    digest = hashlib.sha1(blob.encode()).hexdigest()[:10]
    readable = ",".join(f"{k}={_short(v)}" for k, v in (label or {}).items())
    readable = re.sub(r"[^A-Za-z0-9._=,+-]+", "-", readable)[:60]
    return "-".join(p for p in (Path(notebook).stem, readable, digest) if p)


def _short(v) -> str:
    return Path(v).name if isinstance(v, str) and "/" in v else str(v)


@dataclass
class Grid:
    name: str
    path: Path
    jobs: list[Job]
    executor: dict = field(default_factory=lambda: {"kind": "local"})  # cluster.executor_spec's


def load_grid(path: str | os.PathLike) -> Grid:
    """Read and check a grid file (format in the module docstring).

    Raises ``FileNotFoundError`` for a missing grid or notebook and ``ValueError`` for a
    malformed grid, a notebook without the contract parameters, or a job parameter the
    notebook does not declare (a typo would otherwise be ignored silently).
    """
    import yaml

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"missing grid file {path}")
    try:
        spec = yaml.load(path.read_text(), Loader=unique_key_loader()) or {}
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ValueError(f"{path}:{where}: not valid YAML ({problem})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: a grid is a mapping with keys {sorted(_GRID_KEYS)}")
    unknown = sorted(set(spec) - _GRID_KEYS)
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown}; a grid has {sorted(_GRID_KEYS)}")
    notebooks = spec.get("notebooks", [spec["notebook"]] if "notebook" in spec else [])
    if isinstance(notebooks, str):
        notebooks = [notebooks]
    if not notebooks:
        raise ValueError(f"{path}: no notebook; give `notebooks: [path, ...]`")
    base = _mapping(spec.get("base", {}), "base", path)
    sets = spec.get("sets", [{}]) or [{}]
    if not isinstance(sets, list):
        raise ValueError(f"{path}: `sets` must be a list of parameter mappings")
    sets = [_mapping(s, "sets[]", path) for s in sets]
    axes = _mapping(spec.get("grid", {}), "grid", path)
    for k, values in axes.items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"{path}: grid.{k} must be a non-empty list, got {values!r}")
    jobs = []
    name = str(spec.get("name") or path.stem)
    check_name(name, f"{path}: `name`")
    executor = cluster.executor_spec(spec.get("executor"), str(path))
    for nb in notebooks:
        nb_path = _find_notebook(str(nb), path)
        declared = _declared_parameters(nb_path)
        for s in sets:
            for point in itertools.product(*axes.values()):
                varying = {**s, **dict(zip(axes, point))}
                params = {**base, **varying}
                _check_params(params, declared, nb_path, path)
                _check_param_types(params, declared, nb_path, path)
                _check_config(params, declared, path)
                jobs.append(Job(str(nb), nb_path, params, varying))
    ids = [j.id for j in jobs]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{path}: the grid repeats a job (same notebook and parameters)")
    return Grid(name, path, jobs, executor)


def check_name(name: str, what: str = "run name") -> str:
    """``name`` when it is one plain folder name (letters, digits, ``._+-``; no ``/``, no ``..``),
    so that ``<runs-dir>/<name>`` cannot be outside the runs folder; else ``ValueError``."""
    if not isinstance(name, str) or not _NAME.fullmatch(name) or ".." in name:
        raise ValueError(
            f"{what} {name!r} is not a plain folder name: use letters, digits and . _ + - "
            "(no '/', no '..'), so the run stays inside the runs folder"
        )
    return name


def _mapping(value, what: str, path: Path) -> dict:
    if not isinstance(value, dict):
        raise ValueError(f"{path}: `{what}` must be a mapping of parameter names to values")
    for k, v in value.items():
        if k in CONTRACT_PARAMS:
            raise ValueError(f"{path}: `{k}` is set by the runner, not by the grid")
        try:
            json.dumps(v)
        except TypeError:
            raise ValueError(f"{path}: parameter {k}={v!r} is not a plain YAML value") from None
    return value


def _find_notebook(name: str, grid_path: Path) -> Path:
    tried = [Path(name)] if Path(name).is_absolute() else [Path.cwd() / name, grid_path.parent / name]
    for p in tried:
        if p.is_file():
            return p.resolve()
    raise FileNotFoundError(f"notebook {name!r} not found; looked at {[str(p) for p in tried]}")


def _declared_parameters(nb_path: Path) -> dict[str, dict]:
    """The notebook's parameters as papermill reads them: ``{name: {"default": source, ...}}``."""
    import papermill as pm

    declared = pm.inspect_notebook(str(nb_path))
    missing = [p for p in CONTRACT_PARAMS if p not in declared]
    if missing:
        raise ValueError(
            f"{nb_path} does not declare {missing} in its `parameters` cell; a batch notebook "
            f"takes out_dir (str) and shard (str 'i/n', default '0/1') (see freereg_lib.commands.batch)"
        )
    return declared


def _check_params(params: dict, declared, nb_path: Path, grid_path: Path) -> None:
    unknown = sorted(set(params) - set(declared))
    if unknown:
        raise ValueError(
            f"{grid_path}: parameter(s) {unknown} are not in the `parameters` cell of {nb_path}; "
            f"it declares {sorted(declared)}"
        )


def _default_value(declared: dict, name: str):
    """The notebook's default of parameter ``name`` as a Python value (``_MISSING`` when it is
    not a literal)."""
    import ast

    try:
        return ast.literal_eval(declared[name].get("default", ""))
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        return _MISSING


def _check_param_types(params: dict, declared: dict, nb_path: Path, grid_path: Path) -> None:
    """Each grid value must have the type of the notebook's default for that parameter.

    ``None`` is accepted anywhere (the notebooks use it for "the default behaviour"), an int
    where the default is a float, a list where it is a tuple; a default of None or of a form
    that is not a literal accepts anything. YAML reads ``5e4`` and quoted numbers as strings.
    """
    problems = []
    for k, v in params.items():
        default = _default_value(declared, k)
        if v is None or default is None or default is _MISSING:
            continue
        want = type(default)
        if want is bool:
            ok = isinstance(v, bool)
        elif want is int:
            ok = isinstance(v, int) and not isinstance(v, bool)
        elif want is float:
            ok = isinstance(v, (int, float)) and not isinstance(v, bool)
        elif want in (list, tuple):
            ok = isinstance(v, list)
        else:
            ok = isinstance(v, want)
        if not ok:
            hint = (" (YAML reads 5e4 and quoted numbers as strings: write 50000 or 5.0e+4, and "
                    "true / false unquoted)" if isinstance(v, str) else "")
            problems.append(f"{k}={v!r} is {type(v).__name__}, but the notebook's default is "
                            f"{declared[k].get('default')} ({want.__name__}){hint}")
    if problems:
        raise ValueError(f"{grid_path}: wrong type for {nb_path.name}: " + "; ".join(problems))


def _check_config(params: dict, declared: dict, grid_path: Path) -> None:
    """A job's configuration must be valid before anything runs, so that a configuration
    error fails the grid here, not as a failed row on every pair of every job.

    Checked when the notebook declares them: ``dataset`` with the parameters named like
    :class:`FreeRegConfig` fields and ``config_overrides`` (built with :func:`config_for`,
    which checks the fields' types), and ``variants`` (known methods, ``pnp`` / ``kabsch``).
    """
    where = f"{grid_path}: job {json.dumps(params, sort_keys=True, default=str)}"
    from freereg_lib.report.params import (
        range_problem,  # the range each config field declares (notebooks check the same)
    )

    for k, v in params.items():
        problem = range_problem(k, v)
        if problem:
            raise ValueError(f"{where}: {problem}")
    if "dataset" in declared:
        dataset = params.get("dataset", _default_value(declared, "dataset"))
        fields = {f.name for f in dataclasses.fields(FreeRegConfig)}
        overrides = params.get("config_overrides", {})
        if not isinstance(overrides, dict):
            raise ValueError(f"{where}: config_overrides must be a mapping of FreeRegConfig fields")
        changes = {k: v for k, v in params.items() if k in fields}
        changes.update(overrides)
        if isinstance(dataset, str):
            try:
                config_for(dataset, **changes)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where}: {exc}") from None
    if "variants" in params:
        from freereg_lib.pipeline import METHODS

        variants = params["variants"]
        bad = [v for v in (variants if isinstance(variants, list) else [variants])
               if not (isinstance(v, (list, tuple)) and len(v) == 2 and v[0] in METHODS and v[1] in SOLVERS)]
        if bad or not isinstance(variants, list):
            raise ValueError(f"{where}: variants {bad or variants!r} are not [method, solver] with a method "
                             f"in {list(METHODS)} and a solver in {list(SOLVERS)} (lower case)")
