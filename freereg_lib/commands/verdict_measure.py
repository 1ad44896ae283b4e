"""How often is ``freereg register``'s verdict wrong? Fitted on some real frames, reported on others.

The command says ``REGISTERED`` or ``FAILED`` without ground truth (:func:`freereg_lib.pipeline.register._verdict`:
enough RANSAC inliers, enough of the matches, a plausible Kabsch scale). Its thresholds are
:func:`fit_rule` of rows measured on the pairs within the first half of the shipped ICL living-room
trajectory, and its error rates are counted on the pairs within the second half (:data:`SPLIT`: no
frame is in both). ``tools/verdict_holdout.py`` writes the rows (each pair as ``freereg register
IMAGE CLOUD --depth-pose identity --image-depth DEPTH --backend stub`` runs it, with the stub's
monocular depth and with the true depth, by Kabsch and by PnP); this counts

* false negatives: ``FAILED`` for a pose within (5 deg, 0.1 m) of the truth (:data:`GOOD`);
* false positives: ``REGISTERED`` for a pose outside the paper's (20 deg, 0.5 m) (:data:`WRONG`),

each with its 95 % Clopper-Pearson interval::

    python -m freereg_lib.commands.verdict_measure --fit tests/fixtures/verdict_icl_fit_rows.csv \\
        --rows tests/fixtures/verdict_icl_report_rows.csv

It prints the rule fitted on ``--fit`` (and whether the command's constants are that rule), then
the command's verdict counted on ``--rows`` as the table of docs/your_data.md.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

GOOD = (5.0, 0.1)       # a pose this close must never be called FAILED
WRONG = (20.0, 0.5)     # a pose outside the paper's RR thresholds must not be called REGISTERED

# The frames of the shipped ICL sample (0, 10, ..., 210) the rule is fitted on and reported on: the
# first and the second half of the trajectory; pairs only within a half, so no frame is in both.
SPLIT = {"fit": tuple(range(0, 101, 10)), "report": tuple(range(110, 211, 10))}
GAPS = (10, 100)  # frame gaps of the pairs within a half: all of them

MARGIN = 0.8        # the fitted thresholds sit a fifth below the weakest right pose (fit_rule)
RATIO_STEP = 0.005  # the inlier ratio threshold is rounded down to half a percent
SCALE_STEP = 0.05   # the scale bound is rounded up to 0.05
SOLVERS = ("kabsch", "pnp")


def pairs_within(frames, min_gap: int = GAPS[0], max_gap: int = GAPS[1]) -> list[tuple[int, int]]:
    """The frame pairs ``(i, j)`` with both frames in ``frames`` and ``min_gap <= j - i <= max_gap``."""
    frames = sorted(frames)
    return [(i, j) for i in frames for j in frames if min_gap <= j - i <= max_gap]


def frames_of(table) -> set[int]:
    """The ICL frame numbers in the ``pair`` column (``icl/00000-00010``) of ``table``."""
    return {int(f) for name in table["pair"] for f in name.split("/")[-1].split("-")}


def _good(table) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return ((table["RE"] < GOOD[0]) & (table["TE"] < GOOD[1])).to_numpy()


def _wrong(table) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return ~((table["RE"] < WRONG[0]) & (table["TE"] < WRONG[1])).to_numpy()


def fit_rule(table) -> dict:
    """The verdict's thresholds fitted on ``table`` (rows with the columns ``solver, success,
    n_matches, n_inliers, scale, RE, TE``): ``{"min_inliers": {solver: int}, "min_ratio": {solver:
    float}, "max_scale": float}``, as :mod:`freereg_lib.pipeline.register` holds them.

    The criterion: the largest thresholds that call every right pose of ``table`` (a solved pose
    within :data:`GOOD`, (5 deg, 0.1 m), of the truth) ``REGISTERED`` with a safety margin, so
    that as many wrong poses as that allows are called ``FAILED``. Per solver, over its right
    poses (both depths):

    * ``min_inliers``: :data:`MARGIN` (0.8) times the fewest inliers, rounded down;
    * ``min_ratio``: 0.8 times the smallest inlier ratio (inliers / matches), rounded down to
      half a percent (:data:`RATIO_STEP`);
    * ``max_scale`` (Kabsch's similarity; PnP has none): the scale farthest from 1 (as
      ``max(s, 1 / s)``) with its logarithm widened by 1 / 0.8, rounded up to 0.05.

    Each threshold only rejects more poses as it rises (the scale bound as it tightens), and
    each right pose passes each one, so these are the largest admissible and reject every wrong
    pose any admissible rule rejects. Deterministic: no search, no randomness."""
    out: dict = {"min_inliers": {}, "min_ratio": {}}
    good = _good(table) & table["success"].astype(bool).to_numpy()
    for solver in SOLVERS:
        right = table[good & (table["solver"] == solver).to_numpy()]
        if right.empty:
            raise ValueError(f"no right {solver} pose to fit the verdict on")
        inliers = right["n_inliers"].to_numpy(dtype=float)
        ratio = inliers / right["n_matches"].to_numpy(dtype=float)
        out["min_inliers"][solver] = math.floor(MARGIN * inliers.min() + 1e-9)
        out["min_ratio"][solver] = round(math.floor(MARGIN * ratio.min() / RATIO_STEP + 1e-9) * RATIO_STEP, 4)
        if solver == "kabsch":
            scale = right["scale"].to_numpy(dtype=float)
            far = float(np.max(np.maximum(scale, 1 / scale)))
            out["max_scale"] = round(math.ceil(far ** (1 / MARGIN) / SCALE_STEP - 1e-9) * SCALE_STEP, 4)
    return out


def command_rule() -> dict:
    """The thresholds the command uses (:mod:`freereg_lib.pipeline.register`), as :func:`fit_rule` gives them."""
    from freereg_lib.pipeline import register as R

    return {"min_inliers": {s: R.MIN_INLIERS[s] for s in SOLVERS},
            "min_ratio": {s: R.MIN_INLIER_RATIO[s] for s in SOLVERS}, "max_scale": R.MAX_SCALE}


def verdicts(table, rule: dict | None = None) -> np.ndarray:
    """The command's verdict for each row of ``table``, computed by
    :func:`freereg_lib.pipeline.register._verdict` itself with ``rule`` (a :func:`fit_rule`
    result; default the command's thresholds)."""
    from types import SimpleNamespace

    from freereg_lib.pipeline import register as R

    rule = rule or command_rule()
    out = []
    for r in table.to_dict("records"):
        s = r["solver"]
        res = SimpleNamespace(success=bool(r["success"]), reason="", scale=float(r["scale"]),
                              n_inliers=int(r["n_inliers"]))
        ok, _ = R._verdict(res, {"matches": int(r["n_matches"]), "note": ""}, s,
                           rule["min_inliers"][s], rule["min_ratio"][s], rule["max_scale"])
        out.append(ok)
    return np.asarray(out, dtype=bool)


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) ``level`` interval of a proportion ``k / n``; (nan, nan) for n = 0."""
    from scipy.stats import beta

    if n == 0:
        return math.nan, math.nan
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def rates(table, ok: np.ndarray) -> dict:
    """False negatives (FAILED within ``GOOD``) and false positives (REGISTERED outside ``WRONG``),
    with their 95 % Clopper-Pearson intervals."""
    good, wrong = _good(table), _wrong(table)
    right = ~wrong
    fn, fp = int((good & ~ok).sum()), int((wrong & ok).sum())
    return {"rows": len(table), "good": int(good.sum()), "wrong": int(wrong.sum()),
            "FN": fn, "FN_rate": fn / max(int(good.sum()), 1), "FN_ci": clopper_pearson(fn, int(good.sum())),
            "FP": fp, "FP_rate": fp / max(int(wrong.sum()), 1), "FP_ci": clopper_pearson(fp, int(wrong.sum())),
            "registered": int(ok.sum()), "right": int(right.sum()), "missed_right": int((right & ~ok).sum())}


def _pct(x: float) -> str:
    return "-" if math.isnan(x) else "100" if x >= 0.995 else "0" if x == 0 else f"{100 * x:.2g}"


HEADER = ("| | poses | within (5 deg, 0.1 m) | FAILED among them (false negatives) | outside (20 deg, 0.5 m) "
          "| REGISTERED among them (false positives) | within (20 deg, 0.5 m) but FAILED |\n"
          "|---|---|---|---|---|---|---|")


def table_lines(table, rule: dict | None = None) -> list[str]:
    """docs/your_data.md's table of the verdict on ``table``: per solver and all."""
    lines = HEADER.split("\n")
    for name, sub in [("Kabsch", table[table["solver"] == "kabsch"]), ("PnP", table[table["solver"] == "pnp"]),
                      ("all", table)]:
        r = rates(sub, verdicts(sub, rule))
        fn = f"{r['FN']} ({_pct(r['FN_rate'])} %, [{_pct(r['FN_ci'][0])}, {_pct(r['FN_ci'][1])}])"
        fp = f"{r['FP']} ({_pct(r['FP_rate'])} %, [{_pct(r['FP_ci'][0])}, {_pct(r['FP_ci'][1])}])"
        lines.append(f"| {name} | {r['rows']} | {r['good']} | {fn} | {r['wrong']} | {fp} | "
                     f"{r['missed_right']} of {r['right']} |")
    return lines


def describe(rule: dict) -> str:
    """A rule as one line: per solver its inliers, ratio and (Kabsch) scale bound."""
    return "; ".join(f"{s}: >= {rule['min_inliers'][s]} inliers, >= {rule['min_ratio'][s]:.1%} of the matches"
                     + (f", scale within [{1 / rule['max_scale']:.2f}, {rule['max_scale']:g}]" if s == "kabsch" else "")
                     for s in SOLVERS)


def main(argv=None) -> None:
    import pandas as pd

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fit", required=True, help="the rows to fit the rule on (tools/verdict_holdout.py fit)")
    p.add_argument("--rows", required=True, help="the rows to count it on (tools/verdict_holdout.py report)")
    a = p.parse_args(argv)
    fit, report = pd.read_csv(a.fit), pd.read_csv(a.rows)
    rule = fit_rule(fit)
    shared = frames_of(fit) & frames_of(report)
    print(f"fitted on {fit['pair'].nunique()} pairs ({len(fit)} poses) of frames {sorted(frames_of(fit))}: {describe(rule)}")
    print("the command's rule: " + ("the same" if rule == command_rule() else describe(command_rule())))
    print(f"counted on {report['pair'].nunique()} pairs ({len(report)} poses) of frames {sorted(frames_of(report))}"
          + (f"; frames in both: {sorted(shared)}" if shared else "; no frame in both"))
    print("\n".join(table_lines(report, rule)))


if __name__ == "__main__":
    main()
