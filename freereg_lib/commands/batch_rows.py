"""The output side of :mod:`freereg_lib.commands.batch`: a notebook's per-pair rows on disk and the
results table aggregated from them (moved here from ``batch.py``, which re-exports every name).

* :func:`write_rows` / :func:`read_rows` / :func:`read_config`: ``<out_dir>/pairs.csv`` and
  ``config.json``, written by a batch notebook, read back with their types;
* :func:`write_table` and its parts: ``results.csv`` and ``results.md`` of a run folder, one
  row per job x (method, solver), the paper's Table 1 beside.
* :func:`verify_unit` / :func:`stale_reason`: whether a finished unit's ``done.json`` still
  matches its rows, and whether the current library and notebook made it (the table reads both).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
from pathlib import Path

from freereg_lib.config import FreeRegConfig, config_for

# Table 1 of the paper names datasets its own way; keys are the ``dataset`` parameter.
PAPER_DATASETS = {"3dmatch": "3DMatch", "scannet": "ScanNet", "kitti": "Kitti-DC", "kitti_dc": "Kitti-DC"}
PAPER_METRICS = ("FMR", "IR", "IN", "RR")
_STRING_COLUMNS = {"pair", "method", "solver", "error"}  # never parsed as numbers by read_rows


# --------------------------------------------------------------------------------------
# Per-pair rows.

def write_rows(rows: list[dict], out_dir: str | os.PathLike, cfg: FreeRegConfig | None = None) -> Path:
    """Write per-pair ``rows`` to ``<out_dir>/pairs.csv``; returns that path.

    Floats are written with ``repr`` (exact round trip, ``nan`` for NaN), booleans as
    ``True`` / ``False``; rows may have different keys (missing cells stay empty). With
    ``cfg``, ``<out_dir>/config.json`` records the configuration, which the results table
    then aggregates with (its RR thresholds, FMR ratio and ladder).
    """
    import csv

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "pairs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow([_cell(r[c]) if c in r else "" for c in columns])
    if cfg is not None:
        (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=1, default=str))
    return out / "pairs.csv"


def _cell(v) -> str:
    import numpy as np

    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))  # repr is the shortest string that reads back bit-identical
    return "" if v is None else str(v)


def read_rows(out_dir: str | os.PathLike) -> list[dict]:
    """The rows of ``<out_dir>/pairs.csv`` (see :func:`write_rows`) with their types back.

    A column is int if every cell is an integer, float if every cell is a number, ``nan``
    or empty (empty -> NaN), bool if every cell is ``True`` / ``False``, else str;
    ``pair``, ``method``, ``solver`` and ``error`` are always str. A row's missing cell
    reads back as NaN in a float column, ``""`` in a text column, and is left out of the
    row's dict in an int or bool column.
    """
    import csv

    path = Path(out_dir) / "pairs.csv"
    if not path.is_file():
        raise FileNotFoundError(f"missing {path}: the notebook did not write its per-pair rows")
    with open(path, newline="") as f:
        table = list(csv.reader(f))
    if not table:
        raise ValueError(f"{path} is empty; expected a header line")
    header, body = table[0], table[1:]
    for k, line in enumerate(body, start=2):
        if len(line) != len(header):
            raise ValueError(
                f"{path} line {k} has {len(line)} cell(s) for {len(header)} column(s): the file is cut "
                "or was edited; re-run the job (run ... --force)"
            )
    parsers = {c: _column_parser(c, [line[k] for line in body]) for k, c in enumerate(header)}
    rows = []
    for line in body:
        row = {}
        for c, text in zip(header, line):
            parsed = parsers[c](text)
            if parsed is not _MISSING:
                row[c] = parsed
        rows.append(row)
    return rows


_MISSING = object()


def _column_parser(name: str, cells: list[str]):
    filled = [c for c in cells if c != ""]
    if name in _STRING_COLUMNS or not filled:
        return str
    if all(_parses(int, c) for c in filled):
        return lambda c: int(c) if c != "" else _MISSING
    if all(_parses(float, c) for c in filled):
        return lambda c: float(c) if c != "" else math.nan
    if all(c in ("True", "False") for c in filled):
        return lambda c: (c == "True") if c != "" else _MISSING
    return str


def _parses(kind, text: str) -> bool:
    try:
        kind(text)
    except ValueError:
        return False
    return True


def read_config(out_dir: str | os.PathLike) -> FreeRegConfig | None:
    """The configuration :func:`write_rows` recorded in ``out_dir``, or None.

    Fields unknown to this version of :class:`FreeRegConfig` are ignored.
    """
    path = Path(out_dir) / "config.json"
    if not path.is_file():
        return None
    stored = json.loads(path.read_text())
    known = {f.name: f for f in dataclasses.fields(FreeRegConfig)}
    values = {k: _as_tuples(v) if k != "extra" else v for k, v in stored.items() if k in known}
    return FreeRegConfig(**values)


def _as_tuples(v):
    return tuple(_as_tuples(x) for x in v) if isinstance(v, list) else v


# --------------------------------------------------------------------------------------
# A finished unit's marker, done.json (written by freereg_lib.commands.batch.write_done): can it be trusted, is it current?

def library_fingerprint() -> str:
    """``<version>+<12 hex>``: the library's version and a hash of its sources (every
    ``freereg_lib/**/*.py``), so a job run by another library is known as such."""
    if not _FINGERPRINT:
        from freereg_lib import __version__

        root = Path(__file__).resolve().parents[1]  # the whole freereg_lib package
        h = hashlib.sha256()
        for f in sorted(root.rglob("*.py")):
            h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
        _FINGERPRINT.append(f"{__version__}+{h.hexdigest()[:12]}")
    return _FINGERPRINT[0]


_FINGERPRINT: list[str] = []


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_done(unit: Path) -> dict | None:
    """The ``done.json`` of ``unit``, or None when it is missing or unreadable."""
    try:
        done = json.loads((unit / "done.json").read_text())
    except (OSError, ValueError):
        return None
    return done if isinstance(done, dict) else None


def verify_unit(unit: Path) -> str:
    """Why the finished ``unit`` cannot be trusted (``""`` when it can): ``pairs.csv`` must
    still have the row count and SHA-256 that ``done.json`` recorded."""
    done = read_done(unit)
    if done is None:
        return f"{unit / 'done.json'} is missing or unreadable"
    pairs = unit / "out" / "pairs.csv"
    if "pairs_sha256" not in done or "rows" not in done:
        return f"{unit / 'done.json'} records no row count and hash of pairs.csv (an older runner): re-run the job"
    if not pairs.is_file():
        return f"{pairs} is missing although the job finished: re-run the job (run ... --force)"
    if _sha256(pairs) != done["pairs_sha256"]:
        try:
            now = f"{len(read_rows(unit / 'out'))} now"
        except ValueError as exc:
            now = str(exc)
        return (f"{pairs} changed since the job finished ({done['rows']} rows recorded, {now}); it is "
                "truncated, cut or edited: re-run the job (run ... --force) or restore the file")
    return ""


def stale_reason(unit: Path, job: Job) -> str:
    """Why a finished ``unit`` is out of date (``""`` when it is not): another library or
    notebook than the current ones made it."""
    done = read_done(unit) or {}
    why = []
    if done.get("library") != library_fingerprint():
        why.append(f"library {done.get('library')} (now {library_fingerprint()})")
    if done.get("notebook_sha256") != _sha256(job.path):
        why.append(f"another version of {job.notebook}")
    return "finished with " + " and ".join(why) if why else ""


# --------------------------------------------------------------------------------------
# The results table.

def complete_units(job_dir: Path) -> tuple[list[Path] | None, str]:
    """The folders whose rows make up a job: the job folder when it finished unsharded,
    else a complete set of finished shards ``shard-0ofn .. shard-(n-1)ofn`` (smallest n
    first). Returns ``(None, reason)`` when there is neither."""
    broken = []
    if (job_dir / "done.json").is_file():
        why = verify_unit(job_dir)
        if not why:
            return [job_dir], ""
        broken.append(why)
    by_n: dict[int, dict[int, Path]] = {}
    for d in job_dir.glob("shard-*of*"):
        m = re.fullmatch(r"shard-(\d+)of(\d+)", d.name)
        if m and (d / "done.json").is_file():
            why = verify_unit(d)
            if why:
                broken.append(why)
            else:
                by_n.setdefault(int(m[2]), {})[int(m[1])] = d
    for n in sorted(by_n):
        if set(by_n[n]) == set(range(n)):
            return [by_n[n][i] for i in range(n)], ""
    reasons = broken + [f"shards {sorted(d)} of {n} done" for n, d in sorted(by_n.items())]
    for d in [job_dir, *sorted(job_dir.glob("shard-*of*"))]:
        if (d / "error.txt").is_file():
            where = "" if d == job_dir else f"{d.name} "
            reasons.append(f"{where}failed: " + (d / "error.txt").read_text().splitlines()[0])
    return None, "; ".join(reasons) or "not run yet"


def job_table(job: Job, units: list[Path]):
    """The summary rows of one job: :func:`pipeline.summarize` over the rows of all its units.

    Rows are ordered by pair name first, so the table is bit-identical however the pairs
    were sharded. Raises ``ValueError`` when there is no row at all, or when a pair appears
    in two shards (a notebook that ignores its ``shard`` parameter would otherwise be counted
    n times). A shard may be empty (more shards than pairs).
    """
    from freereg_lib.pipeline import summarize

    rows, seen = [], {}
    for unit in units:
        unit_rows = read_rows(unit / "out")
        for pair in {r.get("pair") for r in unit_rows}:
            if pair in seen:
                raise ValueError(
                    f"pair {pair!r} is in both {seen[pair]} and {unit}: does the notebook pass "
                    "its `shard` parameter to freereg_lib.commands.batch.shard_items?"
                )
            seen[pair] = unit
        rows += unit_rows
    if not rows:
        raise ValueError(f"no per-pair rows in {[str(u / 'out' / 'pairs.csv') for u in units]}")
    rows.sort(key=lambda r: str(r.get("pair", "")))  # stable: keeps the variant order in a pair
    cfg = read_config(units[0] / "out") or _config_from_params(job.params)
    return summarize(rows, cfg)


def _config_from_params(params: dict) -> FreeRegConfig:
    return config_for(params["dataset"]) if "dataset" in params else FreeRegConfig()


def results_table(run_dir: Path, jobs: list[Job], flagged: dict | None = None):
    """All jobs' summaries as one DataFrame, and ``{job id: reason}`` for those left out.

    Columns: ``job``, ``notebook``, ``shards``, the jobs' parameters (``param_<name>``
    when the name is also a summary column, e.g. ``param_n_pairs``), then the summary
    columns of :func:`pipeline.summarize`, then ``paper_FMR`` .. ``paper_RR`` from Table 1
    where the job's ``dataset`` / method / solver is there (NaN elsewhere).
    """
    import pandas as pd

    parts, left_out = [], {}
    param_cols = list(dict.fromkeys(k for j in jobs for k in j.params))
    for job in jobs:
        units, why = complete_units(run_dir / job.id)
        if units is None:
            left_out[job.id] = why
            continue
        try:
            table = job_table(job, units)
        except (ValueError, FileNotFoundError, KeyError) as exc:
            left_out[job.id] = str(exc)
            continue
        stale = sorted({why for u in units if (why := stale_reason(u, job))})
        if stale and flagged is not None:
            flagged[job.id] = "; ".join(stale)
        front = {"job": job.id, "notebook": job.notebook, "shards": len(units)}
        # A parameter named like a summary column (n_pairs, say) gets a ``param_`` prefix.
        front.update({(f"param_{k}" if k in table.columns else k): _plain(job.params.get(k)) for k in param_cols})
        for k, (col, value) in enumerate(front.items()):
            table.insert(k, col, [value] * len(table))
        parts.append(_with_paper(table, job.params.get("dataset")))
    if not parts:
        return pd.DataFrame(columns=["job", "notebook", "shards", *param_cols, "method", "solver"]), left_out
    return pd.concat(parts, ignore_index=True), left_out


def _plain(v):
    """Lists and mappings become JSON text so that they fit one CSV cell."""
    return json.dumps(v) if isinstance(v, (list, dict)) else v


def _with_paper(table, dataset):
    from freereg_lib.data.paper import table as paper_table

    paper = paper_table("table1_main")
    name = PAPER_DATASETS.get(str(dataset).lower().replace("-", "_"))
    for metric in PAPER_METRICS:
        values = []
        for method, solver in zip(table["method"], table["solver"]):
            hit = paper[(paper["dataset"] == name) & (paper["method"] == method)
                        & (paper["solver"].str.lower() == str(solver).lower())]
            values.append(float(hit[metric].iloc[0]) if len(hit) else math.nan)
        table[f"paper_{metric}"] = values
    return table


def write_table(run_dir: Path, jobs: list[Job], flagged: dict | None = None) -> dict[str, str]:
    """Write ``results.csv`` (every column) and ``results.md`` (the columns a reader compares)
    in ``run_dir``; returns the jobs left out, with the reason. Jobs in the table that another
    library or notebook version made are listed in ``results.md`` and put in ``flagged``."""
    flagged = {} if flagged is None else flagged
    table, left_out = results_table(run_dir, jobs, flagged)
    table.to_csv(run_dir / "results.csv", index=False)
    lines = [
        f"# Results of {run_dir.name}",
        "",
        "FMR, IR, RR in %, IN a count per pair, RE in degrees and TE in metres (means over pairs "
        "with a pose); `paper_*` are the paper's Table 1 (ICLR 2024) for the same dataset, method "
        "and solver. Only the `real` backend is comparable with the paper. results.csv beside "
        "this file also has medians and RR over the threshold ladder.",
    ]
    if len(table):
        cols = list(table.columns)
        front = cols[: cols.index("method")]  # job, notebook, shards and the parameters
        # Columns with one value over the whole table are stated once, above it.
        same = [c for c in front if len(table) > 1 and table[c].astype(str).nunique() == 1]
        lines += ["", *[f"- `{c}`: {table[c].iloc[0]}" for c in same]]
        shown = [c for c in front if c not in same or c == "job"] + [
            c for c in (*_SUMMARY_ORDER, *(f"paper_{m}" for m in PAPER_METRICS))
            if c in table.columns and not (c.startswith("paper_") and table[c].isna().all())]
        view = table[shown].astype(object).where(table[shown].notna(), None)
        lines += ["", view.to_markdown(index=False, floatfmt=".1f", missingval="-")]
    else:
        lines += ["", "(no finished job yet)"]
    if flagged:
        lines += ["", "Out of date (in the table, but `run` would re-run them):", ""] + [
            f"- `{j}`: {why}" for j, why in flagged.items()]
    if left_out:
        lines += ["", "Not in the table:", ""] + [f"- `{j}`: {why}" for j, why in left_out.items()]
    (run_dir / "results.md").write_text("\n".join(lines) + "\n")
    return left_out


_SUMMARY_ORDER = ("method", "solver", "n_pairs", "n_failed", "FMR", "IR", "IN", "RR", "RE", "TE")
