"""The committed micro models on a split (:mod:`.splits`): FreeReg-D, FreeReg-G, fused FreeReg,
each with Kabsch-RANSAC and PnP-RANSAC, on the same pairs with the same noise draws.

    python -m freereg_lib.training.evaluate_split --split test [--pairs 100] [--shard 0/2]
        --rows runs/micro/test_split/rows.jsonl
    python -m freereg_lib.training.evaluate_split --split test --summarize
        --rows runs/micro/test_split/rows.jsonl --out freereg_lib/models/micro/weights/test_split.json

Per pair the micro backend's features are computed once (diffusion decoder layers 0, 4, 6; the
micro depth with FPFH, the backend's geometric default), then the three methods (w = 1, 0 and the
config's 0.5) are matched and solved with both solvers (:func:`freereg_lib.pipeline.variant_rows`),
under the config's defaults with ``seed`` = the split's noise seed (0) for every method. Each pair's
rows are appended to ``--rows`` (JSON lines) as it finishes, so shards can run as separate processes
and a stopped run resumes. ``--summarize`` reads the rows of the longest complete prefix of pairs
``0 .. n-1`` and writes IR, FMR and RR (%) with 95 % bootstrap intervals over pairs per method and
solver, the paired permutation tests of fused FreeReg against each half (IR; Kabsch RR), and the
command lines that made them.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from freereg_lib.training.evaluate import bootstrap_ci, paired_permutation_p
from freereg_lib.training.splits import SPLITS
from freereg_lib.training.verdicts import _points

METHODS = ("FreeReg-D", "FreeReg-G", "FreeReg")
SOLVERS = ("kabsch", "pnp")
VARIANTS = tuple((m, s) for m in METHODS for s in SOLVERS)
ROW_KEYS = ("method", "solver", "w", "n_matches", "IR", "IN", "RE", "TE", "registered", "n_evaluable", "error")


def _done(rows_path: Path) -> set[int]:
    if not rows_path.exists():
        return set()
    return {json.loads(line)["k"] for line in rows_path.read_text().splitlines() if line.strip()}


FEATURE_FIELDS = ("uv_image", "pts_image", "uv_depth", "pts_depth", "diff_image", "diff_depth", "geo_image", "geo_depth")


def save_features(feats, path: Path) -> None:
    """The arrays of a pair's :class:`~freereg_lib.pipeline.PairFeatures` that matching, both solvers and
    the scoring of a synthetic pair need (not the depth view: a synthetic pair's truth is its frame)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{f: getattr(feats, f) for f in FEATURE_FIELDS})


def load_features(path: Path):
    from freereg_lib.pipeline import PairFeatures

    with np.load(path) as z:
        return PairFeatures(**{f: z[f] for f in FEATURE_FIELDS}, mono_depth=None, view=None)


def run(split_name: str, n_pairs: int, rows_path: Path, shard: str = "0/1", weights_dir=None,
        progress: bool = True, cache: Path | None = None, ks=None, mono_depth: str = "micro",
        mono_mae: float | None = None) -> None:
    """Append the rows of the split's pairs ``k < n_pairs`` with ``k % n == i`` (``shard = "i/n"``)
    not yet in ``rows_path`` (only those in ``ks`` when given); with ``cache``, each pair's features
    are also saved there (``<k>.npz``, for choices made on the development set without recomputing them).
    ``mono_depth``, ``mono_mae``: the micro backend's monocular depth (``"stub"`` with ``mono_mae`` 0 is
    the true depth: the geometric half's ceiling)."""
    from tqdm import tqdm

    from freereg_lib import pipeline
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    split = SPLITS[split_name]
    i, n = parse_shard(shard)
    cfg = FreeRegConfig(seed=split.noise_seed)
    backend = get_backend("micro", cfg, device="cpu", weights_dir=weights_dir, mono_depth=mono_depth, mono_mae=mono_mae)
    done = _done(rows_path)
    todo = [k for k in (range(n_pairs) if ks is None else ks) if k % n == i and k not in done]
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    for k in tqdm(todo, desc=f"{split.name} split, shard {shard}", disable=not progress):
        seed = split.pair_seeds(k + 1)[k]
        synthetic.check_eval_seed(seed)
        t0 = time.time()
        pair = synthetic.make_pair("indoor", seed=seed, world=split.world)
        try:
            feats = pipeline.compute_features(pair, backend, cfg, True, True)
            if cache is not None:
                save_features(feats, Path(cache) / f"{k}.npz")
        except Exception as exc:  # a failed pair scores as run_pair scores it
            feats = exc
        rows = pipeline.variant_rows(pair, feats, cfg, VARIANTS)
        rec = {"k": k, "pair_seed": seed, "pair": pair.name, "seconds": round(time.time() - t0, 1),
               "label": backend.label,
               "rows": [{key: _plain(r.get(key)) for key in ROW_KEYS} for r in rows]}
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def _plain(v):
    if isinstance(v, (np.floating, float)):
        return None if math.isnan(float(v)) else float(v)
    if isinstance(v, (np.integer, np.bool_)):
        return v.item()
    return v


class RowsError(ValueError):
    """A rows file that cannot be summarized; the message is one line naming it."""


def load_rows(rows_paths) -> list[dict]:
    """The per-pair records (of one or more row files, e.g. one per shard) of the longest complete
    prefix ``k = 0 .. n-1``, one record per pair. A missing file, a line that is not a JSON
    record with an integer ``k`` raises :class:`RowsError` naming it; ``[]`` without pair 0."""
    recs = {}
    for path in [rows_paths] if isinstance(rows_paths, (str, Path)) else rows_paths:
        try:
            lines = Path(path).read_text().splitlines()
        except FileNotFoundError:
            raise RowsError(f"--rows {path}: cannot read it: no such file (run the command without --summarize "
                            "first)") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise RowsError(f"--rows {path}: cannot read it ({type(exc).__name__}: {exc.strerror or exc})") from None
        for no, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                r = json.loads(line)
                k = r["k"]
                if not isinstance(k, int) or isinstance(k, bool):
                    raise TypeError(f"'k' is {k!r}, not an integer")
            except (ValueError, KeyError, TypeError) as exc:
                raise RowsError(f"--rows {path}, line {no}: not a row of evaluate_split (a JSON object with an "
                                f"integer 'k'): {type(exc).__name__}: {' '.join(str(exc).split())[:100]}") from None
            recs.setdefault(k, r)
    n = 0
    while n in recs:
        n += 1
    return [recs[k] for k in range(n)]


def rows_to_summarize(parser, rows_paths) -> list[dict]:
    """:func:`load_rows` for a command's ``--summarize``: a rows file that cannot be read, or none
    with pair 0, stops the command with one line naming it (``parser.error``, exit 2)."""
    try:
        recs = load_rows(rows_paths)
    except RowsError as exc:
        parser.error(str(exc))
    if not recs:
        shown = rows_paths if isinstance(rows_paths, (str, Path)) else " ".join(map(str, rows_paths))
        parser.error(f"--rows {shown}: no row of pair k = 0, no complete pair 0..n-1 to summarize")
    return recs


def parse_shard(shard: str) -> tuple[int, int]:
    """``(i, n)`` of ``--shard i/n`` (``0 <= i < n``); ``ValueError`` naming it otherwise (``3/2`` ran
    no pair and said nothing)."""
    try:
        i, n = (int(x) for x in str(shard).split("/"))
    except ValueError:
        raise ValueError(f"--shard {shard}: expected i/n, two integers (e.g. 0/2)") from None
    if not 0 <= i < n:
        raise ValueError(f"--shard {shard}: expected 0 <= i < n (shard i of n), got i = {i}, n = {n}")
    return i, n


def _stat(v) -> dict:
    v = np.asarray(v, dtype=np.float64)
    lo, hi = bootstrap_ci(v)
    return {"mean": 100 * float(v.mean()), "ci": [100 * lo, 100 * hi]}


def paired_difference(a, b) -> dict:
    """Mean of ``a - b`` over pairs (rates in [0, 1]) in percentage points, its 95 % bootstrap interval
    and the two-sided paired permutation p-value."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return {"diff": 100 * float(d.mean()), "diff_ci": [100 * v for v in bootstrap_ci(d)],
            "p": paired_permutation_p(a, b)}


def difference_line(key: str, t: dict) -> str:
    """A report's line for one :func:`paired_difference`: points, interval, p."""
    return f"  {key}: {_points(t)}, p = {t['p']:.4f}"


def load_average_range(recs: list[dict]) -> list[float] | None:
    """The lowest and highest 1-minute load average the rows recorded (None without rows)."""
    return [min(r["load_average"] for r in recs), max(r["load_average"] for r in recs)] if recs else None


def summarize(recs: list[dict], split_name: str) -> dict:
    from freereg_lib.config import FreeRegConfig

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    per = {}
    for m, s in VARIANTS:
        rows = [next(r for r in rec["rows"] if r["method"] == m and r["solver"] == s) for rec in recs]
        ir = [r["IR"] for r in rows]
        reg = [float(bool(r["registered"])) for r in rows]
        ladder, ladder_per_pair = {}, {}
        for deg, metres in cfg.rr_ladder:  # Table 9's rungs from each pair's RE / TE (a failed pose: None)
            ok = [int(r["RE"] is not None and r["TE"] is not None and r["RE"] < deg and r["TE"] < metres) for r in rows]
            ladder[f"RR@{deg:g}deg/{metres:g}m"] = 100 * float(np.mean(ok))
            ladder_per_pair[f"RR@{deg:g}deg/{metres:g}m"] = ok
        per[f"{m} {s}"] = {"IR": _stat(ir), "FMR": _stat(np.asarray(ir) > cfg.fmr_ratio), "RR": _stat(reg),
                           "ladder": ladder, "ladder_per_pair": ladder_per_pair,
                           "errors": sum(1 for r in rows if r["error"]),
                           "IR_per_pair": ir, "registered_per_pair": [int(x) for x in reg]}
    tests = paired_tests(per)
    return {
        "split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed,
        "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(recs) - 1}",
        "n_pairs": len(recs), "use": split.use, "backend": recs[0]["label"] if recs else None,
        "config": {"fusion_w": cfg.fusion_w, "layers": list(cfg.layers), "geometric": cfg.geometric,
                   "ransac_iters": cfg.ransac_iters, "kabsch_scoring": cfg.kabsch_scoring,
                   "tau_c": cfg.tau_c, "fmr_ratio": cfg.fmr_ratio, "rr_rot_deg": cfg.rr_rot_deg,
                   "rr_trans_m": cfg.rr_trans_m},
        "results": per, "tests": tests,
        "seconds_per_pair": float(np.mean([r["seconds"] for r in recs])) if recs else None,
        "note": "IR per method is the same for both solvers (one set of matches per method); "
                "p: two-sided paired sign-flip permutation test over pairs; intervals: 95 % percentile bootstrap.",
    }


def paired_tests(per: dict) -> dict:
    """The split's headline paired tests from each variant's ``IR_per_pair`` and ``registered_per_pair``
    (``per["<method> <solver>"]``): fused FreeReg against each half (IR with Kabsch's matches; RR with
    each solver) and Kabsch against PnP per method, each ``{"diff": points, "p": paired permutation p}``."""
    tests = {}
    for other in ("FreeReg-D", "FreeReg-G"):
        a, b = per["FreeReg kabsch"]["IR_per_pair"], per[f"{other} kabsch"]["IR_per_pair"]
        tests[f"IR: FreeReg - {other}"] = {"diff": 100 * float(np.mean(a) - np.mean(b)),
                                           "p": paired_permutation_p(a, b)}
        for s in SOLVERS:
            a, b = per[f"FreeReg {s}"]["registered_per_pair"], per[f"{other} {s}"]["registered_per_pair"]
            tests[f"RR {s}: FreeReg - {other}"] = {"diff": 100 * float(np.mean(a) - np.mean(b)),
                                                  "p": paired_permutation_p(a, b)}
    for m in METHODS:
        a, b = per[f"{m} kabsch"]["registered_per_pair"], per[f"{m} pnp"]["registered_per_pair"]
        tests[f"RR {m}: kabsch - pnp"] = {"diff": 100 * float(np.mean(a) - np.mean(b)), "p": paired_permutation_p(a, b)}
    return tests


def report(res: dict) -> str:
    lines = [f"{res['split']} split: {res['n_pairs']} synthetic indoor pairs ({res['pair_seeds']}), "
             f"noise seed {res['noise_seed']}, {res['backend']}"]
    for key, r in res["results"].items():
        f = lambda s: f"{s['mean']:5.1f} [{s['ci'][0]:.1f}, {s['ci'][1]:.1f}]"  # noqa: E731
        lines.append(f"  {key:18s} IR {f(r['IR'])}  FMR {f(r['FMR'])}  RR {f(r['RR'])}")
    for key, t in res["tests"].items():
        lines.append(f"  {key}: {t['diff']:+.1f} points, p = {t['p']:.4f}")
    return "\n".join(lines)


def _git_head() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    except Exception:
        return None


def stamped(res: dict) -> dict:
    """``res`` with where it was made: ``git_head`` and ``machine`` (processor, cores, Python)."""
    res["git_head"] = _git_head()
    res["machine"] = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}"
    return res


def publish(res: dict, report_text: str, out: str | None) -> None:
    """Print ``report_text`` and write ``res`` as JSON to ``out`` when given, with what produced it
    (``provenance``: :func:`~freereg_lib.training.provenance.machine_record`): the end of every split command."""
    from freereg_lib.training.provenance import machine_record

    print(report_text)
    res.setdefault("provenance", machine_record())
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(res, indent=1) + "\n")


def result_lines(res: dict, width: int) -> list[str]:
    """A split summary's report lines after its header: per row FMR, IR, IN and RR with its
    interval and failures (row names padded to ``width``), the paired differences, the median
    seconds a pair."""
    lines = []
    for key, r in res["results"].items():
        lines.append(f"  {key:{width}s} {r['FMR']['mean']:5.1f}  {r['IR']['mean']:5.1f}  {r['IN']:6.1f}  {r['RR']['mean']:5.1f} "
                     f"[{r['RR']['ci'][0]:.1f}, {r['RR']['ci'][1]:.1f}]  ({r['errors']} failed)")
    lines += [difference_line(key, t) for key, t in res["tests"].items()]
    lines.append(f"  seconds a pair (median): {res['seconds_per_pair']}")
    return lines


def split_command(module: str, doc: str, run, summarize, report, argv=None) -> int:
    """The command line of a split evaluation on one rows file: ``--split --pairs --backend --rows``
    appends the rows of the pairs not yet there (``run(split, n_pairs, rows_path, backend)``);
    ``--summarize [--out]`` prints ``report`` of ``summarize(rows, split)`` and writes it stamped,
    with the two commands of ``python -m module`` that made it."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--split", default="test", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=None, help="default: the split's size")
    p.add_argument("--backend", default="micro", choices=("micro", "stub"))
    p.add_argument("--rows", required=True, help="per-pair rows (JSON lines), appended to or summarized")
    p.add_argument("--summarize", action="store_true")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.pairs is not None and args.pairs < 1:
        p.error(f"--pairs must be >= 1, got {args.pairs}")
    if not args.summarize:
        run(args.split, args.pairs or SPLITS[args.split].n_pairs, Path(args.rows), args.backend)
        return 0
    recs = rows_to_summarize(p, args.rows)
    res = summarize(recs, args.split)
    res["commands"] = [f"python -m {module} --split {args.split} --pairs {len(recs)} --rows {args.rows}",
                       f"python -m {module} --split {args.split} --summarize --rows {args.rows}"
                       + (f" --out {args.out}" if args.out else "")]
    publish(stamped(res), report(res), args.out)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="test", choices=sorted(SPLITS))
    p.add_argument("--pairs", type=int, default=None, help="default: the split's size")
    p.add_argument("--shard", default="0/1", help="i/n: this process runs pairs k with k %% n == i")
    p.add_argument("--weights", default=None, help="micro weights folder (default: the committed ones)")
    p.add_argument("--rows", nargs="+", required=True,
                   help="per-pair rows (JSON lines): appended to (the first), or summarized (all)")
    p.add_argument("--summarize", action="store_true", help="summarize --rows into --out instead of running")
    p.add_argument("--cache", default=None, help="also save each pair's features here (<k>.npz)")
    p.add_argument("--mono-depth", default="micro", choices=("micro", "stub"),
                   help="the monocular depth: the micro ZoeDepth, or the stub's designed error of the true depth")
    p.add_argument("--mono-mae", type=float, default=None,
                   help="with --mono-depth stub: its mean error in metres (0: the true depth)")
    p.add_argument("--out", default=None)
    p.add_argument("--run-command", action="append", default=[],
                   help="(with --summarize) a command line that produced the rows, recorded in the JSON")
    args = p.parse_args(argv)
    split = SPLITS[args.split]
    try:  # bad values stop here with one line (exit 2), before any pair runs
        parse_shard(args.shard)
        if args.mono_mae is not None and args.mono_depth != "stub":
            raise ValueError("--mono-mae sets the stub's depth error: pass --mono-depth stub with it")
        if args.pairs is not None and args.pairs < 1:
            raise ValueError(f"--pairs must be >= 1, got {args.pairs}")
    except ValueError as exc:
        p.error(str(exc))
    recs = rows_to_summarize(p, args.rows) if args.summarize else None
    if not args.summarize:
        run(args.split, args.pairs or split.n_pairs, Path(args.rows[0]), args.shard, args.weights,
            cache=Path(args.cache) if args.cache else None, mono_depth=args.mono_depth, mono_mae=args.mono_mae)
        return 0
    res = summarize(recs, args.split)
    res["commands"] = args.run_command + [
        f"python -m freereg_lib.training.evaluate_split --split {args.split} --summarize --rows {' '.join(args.rows)}"
        + (f" --out {args.out}" if args.out else "")]
    res["git_head"] = _git_head()
    res["machine"] = f"{platform.processor() or platform.machine()}, {platform.python_version()}"
    publish(res, report(res), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
