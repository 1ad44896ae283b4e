"""This machine against the committed results: recompute committed test-split pairs and compare.

    python -m freereg_lib.commands.agreement --pairs 100 --out runs/agreement

A micro model's outcome on one pair is not portable across CPUs (docs/reproducibility.md): another
instruction set moves the feature maps by about 1e-6, and FPFH, mutual nearest neighbours and RANSAC
can turn that into another match set or pose. What must hold on every machine is the committed
conclusions. So this command recomputes ``--pairs`` pairs of the committed test split
(``freereg_lib/models/micro/weights/test_split.json``, spread evenly over its 100 pairs) with the
committed models and config, and compares

* each pair's committed fields (per method and solver: IR and the registered outcome) with the
  recomputed ones: ``identical`` (every field bit-equal), ``close`` (IR within
  :data:`IR_TOLERANCE`, every outcome the same), ``differs`` (IR further off, outcomes the same),
  ``flipped`` (a registered outcome differs);
* each headline verdict of the split (fused FreeReg against each half, Kabsch against PnP: the
  paired tests in the JSON): recomputed on the 100 pairs with this machine's rows in place of the
  committed ones, its direction and significance at 5 % against the committed verdict.

It prints one line ("this machine reproduces the committed results: ...") and writes
``agreement.json`` and ``agreement.md`` (per pair and field, per verdict) with the recomputed rows
(``rows/<k>.jsonl``, kept: a pair already there is not recomputed when the command runs again,
unless ``--fresh``) in ``--out``. ``make reproduce`` runs it on
10 pairs. Exit status: 0 when every verdict is unchanged, 1 when one changed, 2 on bad arguments.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from freereg_lib.commands.process_io import redirect_stderr
from freereg_lib.training.evaluate_split import VARIANTS, paired_tests
from freereg_lib.training.provenance import machine_record

IR_TOLERANCE = 0.02  # one match more or fewer among about 50 moves a pair's IR by 0.02
SIGNIFICANCE = 0.05
MIN_PAIRS = 10  # make reproduce's sample: each verdict's rows change by at most a tenth


class AgreementError(ValueError):
    """A committed file or an argument the check cannot use; the message is one line naming it."""


def sample_pairs(n_total: int, n: int) -> list[int]:
    """``n`` pair indices spread evenly over ``0 .. n_total - 1`` (all of them when ``n >= n_total``)."""
    if n < 1:
        raise AgreementError(f"--pairs must be at least 1, got {n}")
    n = min(n, n_total)
    return sorted({int(i * n_total // n) for i in range(n)})


def load_committed(path: Path) -> dict:
    """The committed split JSON, checked for what the comparison reads; :class:`AgreementError` naming
    the file and field otherwise."""
    try:
        res = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise AgreementError(f"{path}: cannot read a committed split JSON ({type(exc).__name__}: {exc})") from None
    n = res.get("n_pairs") if isinstance(res, dict) else None
    if not isinstance(n, int) or n < 1:
        raise AgreementError(f"{path}: 'n_pairs' must be a positive integer, got {n!r}")
    for m, s in VARIANTS:
        r = res.get("results", {}).get(f"{m} {s}")
        if not isinstance(r, dict) or len(r.get("IR_per_pair") or []) != n or len(r.get("registered_per_pair") or []) != n:
            raise AgreementError(f"{path}: results['{m} {s}'] needs IR_per_pair and registered_per_pair of "
                                 f"{n} values (the split's n_pairs)")
    return res


def _quiet_worker(log: Path) -> None:
    """A recomputing process: no model-loading progress bars, its standard error to ``log``."""
    redirect_stderr(log)
    from diffusers.utils import logging as diffusers_logging
    from transformers.utils import logging as transformers_logging

    transformers_logging.disable_progress_bar()
    diffusers_logging.disable_progress_bar()


def _one_pair(k: int, folder: Path) -> None:
    from freereg_lib.training import evaluate_split

    evaluate_split.run("test", k + 1, folder / f"{k}.jsonl", ks=[k], progress=False)


def recompute(ks: list[int], folder: Path, jobs: int = 1, progress: bool = True, fresh: bool = False) -> list[dict]:
    """The rows of the test split's pairs ``ks`` (:func:`~freereg_lib.training.evaluate_split.run`),
    ``jobs`` processes side by side, one file a pair in ``folder`` (``<k>.jsonl``; a pair already
    there is not recomputed unless ``fresh``, which replaces the files of ``ks``)."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from tqdm.auto import tqdm

    folder.mkdir(parents=True, exist_ok=True)
    if fresh:  # only the files this function writes
        for k in ks:
            (folder / f"{k}.jsonl").unlink(missing_ok=True)

    def done(k: int) -> bool:
        path = folder / f"{k}.jsonl"
        return path.is_file() and bool(path.read_text().strip())

    todo = [k for k in ks if not done(k)]
    if todo:
        with ProcessPoolExecutor(max_workers=jobs, initializer=_quiet_worker, initargs=(folder / "workers.log",)) as pool:
            futures = [pool.submit(_one_pair, k, folder) for k in todo]
            for fut in tqdm(as_completed(futures), total=len(futures), desc="committed pairs recomputed",
                            disable=not progress):
                fut.result()
    recs = []
    for k in ks:
        lines = [line for line in (folder / f"{k}.jsonl").read_text().splitlines() if line.strip()]
        recs.append(json.loads(lines[0]))
    return recs


def _field(committed: dict, key: str, k: int) -> tuple:
    r = committed["results"][key]
    return r["IR_per_pair"][k], int(r["registered_per_pair"][k])


def compare_pair(committed: dict, rec: dict, tol: float = IR_TOLERANCE) -> dict:
    """One recomputed pair against its committed row: per variant the two IRs and outcomes, and the
    pair's status (``identical`` / ``close`` / ``differs`` / ``flipped``)."""
    fields, worst = {}, "identical"
    order = ("identical", "close", "differs", "flipped")
    for row in rec["rows"]:
        key = f"{row['method']} {row['solver']}"
        ir_c, reg_c = _field(committed, key, rec["k"])
        ir_n, reg_n = row["IR"], int(bool(row["registered"]))
        if reg_c != reg_n:
            status = "flipped"
        elif ir_c == ir_n:
            status = "identical"
        elif ir_c is not None and ir_n is not None and abs(ir_c - ir_n) <= tol:
            status = "close"
        else:
            status = "differs"
        fields[key] = {"IR_committed": ir_c, "IR_here": ir_n, "registered_committed": reg_c,
                       "registered_here": reg_n, "status": status}
        worst = max(worst, status, key=order.index)
    return {"k": rec["k"], "pair": rec.get("pair"), "status": worst, "fields": fields}


def verdict_class(diff: float, p: float) -> str:
    """A paired difference's direction and significance, the unit in which two machines must agree."""
    if diff == 0:
        return "level"
    return f"{'above' if diff > 0 else 'below'}, {'significant' if p < SIGNIFICANCE else 'not significant'}"


def compare_verdicts(committed: dict, recs: list[dict]) -> dict:
    """Each headline test on the committed rows and on the same rows with this machine's recomputed
    pairs in place: ``{name: {committed, here, unchanged}}``, each side ``[difference, p, class]``."""
    def per_variant(replace: dict) -> dict:
        per = {}
        for m, s in VARIANTS:
            key = f"{m} {s}"
            ir = list(committed["results"][key]["IR_per_pair"])
            reg = [int(v) for v in committed["results"][key]["registered_per_pair"]]
            for k, rows in replace.items():
                ir[k], reg[k] = rows[key]["IR"], int(bool(rows[key]["registered"]))
            per[key] = {"IR_per_pair": ir, "registered_per_pair": reg}
        return per

    here_rows = {rec["k"]: {f"{r['method']} {r['solver']}": r for r in rec["rows"]} for rec in recs}
    before, after = paired_tests(per_variant({})), paired_tests(per_variant(here_rows))
    out = {}
    for name in before:
        a, b = before[name], after[name]
        ca, cb = verdict_class(a["diff"], a["p"]), verdict_class(b["diff"], b["p"])
        out[name] = {"committed": [a["diff"], a["p"], ca], "here": [b["diff"], b["p"], cb], "unchanged": ca == cb}
    return out


def summary_line(pairs: list[dict], verdicts: dict) -> str:
    """The one line ``make reproduce`` prints."""
    count = {s: sum(p["status"] == s for p in pairs) for s in ("identical", "close", "differs", "flipped")}
    changed = [name for name, v in verdicts.items() if not v["unchanged"]]
    tail = (f"verdicts unchanged ({len(verdicts)} of {len(verdicts)})" if not changed else
            f"{len(changed)} of {len(verdicts)} verdicts CHANGED ({'; '.join(changed)})")
    return (f"this machine reproduces the committed results: {count['identical']} of {len(pairs)} pairs identical, "
            f"{count['close']} within IR {IR_TOLERANCE:g}, {count['differs']} with other matches, "
            f"{count['flipped']} flipped (a registered outcome differs); {tail}")


def report_md(pairs: list[dict], verdicts: dict, committed_path: Path) -> str:
    lines = [f"# This machine against {committed_path}", "",
             f"Status per pair: identical (every field bit-equal), close (IR within {IR_TOLERANCE:g}, outcomes "
             "equal), differs (IR further off, outcomes equal), flipped (a registered outcome differs).", "",
             "| k | pair | status | fields that are not identical |", "|---|---|---|---|"]
    for p in pairs:
        odd = [f"{key}: IR {f['IR_committed']} -> {f['IR_here']}, registered {f['registered_committed']} -> "
               f"{f['registered_here']}" for key, f in p["fields"].items() if f["status"] != "identical"]
        lines.append(f"| {p['k']} | {p['pair']} | {p['status']} | {'; '.join(odd) or '-'} |")
    lines += ["", "Headline verdicts on the whole committed split: the committed rows against the same rows with "
              "this machine's pairs in place (difference in points, two-sided paired permutation p):", "",
              "| test | committed | here | unchanged |", "|---|---|---|---|"]
    for name, v in verdicts.items():
        c, h = v["committed"], v["here"]
        lines.append(f"| {name} | {c[0]:+.1f}, p = {c[1]:.4f} ({c[2]}) | {h[0]:+.1f}, p = {h[1]:.4f} ({h[2]}) | "
                     f"{'yes' if v['unchanged'] else 'NO'} |")
    return "\n".join(lines) + "\n"


def check(n_pairs: int, out: Path, committed_path: Path, jobs: int = 1, progress: bool = True,
          fresh: bool = False) -> tuple[str, dict]:
    """Recompute ``n_pairs`` committed pairs into ``out`` and compare; ``(summary line, result)``.
    ``fresh`` recomputes pairs whose rows ``out`` already holds (``make reproduce`` checks the code
    as it is now, not an earlier run's rows)."""
    committed = load_committed(committed_path)
    ks = sample_pairs(committed["n_pairs"], n_pairs)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    recs = recompute(ks, out / "rows", jobs, progress, fresh)
    pairs = [compare_pair(committed, rec) for rec in recs]
    verdicts = compare_verdicts(committed, recs)
    line = summary_line(pairs, verdicts)
    result = {"committed": str(committed_path), "committed_machine": committed.get("provenance") or committed.get("machine"),
              "pairs_checked": [p["k"] for p in pairs], "ir_tolerance": IR_TOLERANCE, "summary": line,
              "seconds": round(time.perf_counter() - t0, 1), "pairs": pairs, "verdicts": verdicts,
              "provenance": machine_record()}
    (out / "agreement.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "agreement.md").write_text(report_md(pairs, verdicts, committed_path))
    return line, result


def main(argv: list[str] | None = None) -> int:
    from freereg_lib.models.micro.diffusion import WEIGHTS_DIR

    ap = argparse.ArgumentParser(prog="python -m freereg_lib.commands.agreement", description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=MIN_PAIRS, help=f"pairs to recompute (default {MIN_PAIRS}; 100: all)")
    ap.add_argument("--out", default="runs/agreement", help="folder for the recomputed rows and the report")
    ap.add_argument("--committed", default=str(Path(WEIGHTS_DIR) / "test_split.json"), help="the committed split JSON")
    ap.add_argument("--jobs", type=int, default=1, help="processes side by side (one thread each)")
    ap.add_argument("--fresh", action="store_true", help="recompute pairs whose rows --out already holds")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs must be at least 1, got {args.jobs}")
    try:
        line, result = check(args.pairs, Path(args.out), Path(args.committed), args.jobs, fresh=args.fresh)
    except AgreementError as exc:
        ap.error(str(exc))
    print(line)
    print(f"details: {Path(args.out) / 'agreement.md'}")
    return 0 if all(v["unchanged"] for v in result["verdicts"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
