"""How often is ``freereg register``'s verdict wrong? Fitted on some real frames, reported on others.

The command says ``REGISTERED`` or ``FAILED`` without ground truth (:mod:`freereg_lib.pipeline.verdict`:
a plausible Kabsch scale and a **support**, the pose's inliers over what the same solver reaches on
the matches shuffled, computed per run). Its one fitted constant per solver, ``MIN_SUPPORT``, is
:func:`fit_rule` of rows measured on the pairs within the first half of the shipped ICL living-room
trajectory, and its error rates are counted on the pairs within the second half (:data:`SPLIT`: no
frame is in both) and on the official demo (another sensor). ``tools/verdict_holdout.py`` writes
the rows (each pair as ``freereg register IMAGE CLOUD --depth-pose identity --image-depth DEPTH
--backend stub`` runs it, with the stub's monocular depth and with the true depth, by Kabsch and by
PnP, with the per-run null); this counts

* false negatives: ``FAILED`` for a pose within (5 deg, 0.1 m) of the truth (:data:`GOOD`);
* false positives: ``REGISTERED`` for a pose outside the paper's (20 deg, 0.5 m) (:data:`WRONG`),

each with its 95 % Clopper-Pearson interval::

    python -m freereg_lib.commands.verdict_measure --fit tests/fixtures/verdict_icl_fit_rows.csv \\
        --rows tests/fixtures/verdict_icl_report_rows.csv

It prints the rule fitted on ``--fit`` (and whether the command's constants are that rule), then
the command's verdict counted on ``--rows`` as the table of docs/your_data.md. ``--rows`` may be
the ``.json`` of ``tools/verdict_holdout.py sample`` (another sensor's frames, ``--root``);
``--targets`` adds the acceptance table per solver and depth (:func:`target_lines`)::

    python -m freereg_lib.commands.verdict_measure --fit tests/fixtures/verdict_icl_fit_rows.csv \\
        --rows tests/fixtures/verdict_tum_rows.json --targets

``--candidates ROWS ...`` adds other statistics than the support (:data:`STATISTICS`: the inlier
fraction, the inliers, a binomial p-value against the null's inlier rate, ...), each fitted on
``--fit`` (and on ``--fit`` plus ``--fit-also``) and counted on each ``ROWS`` (:func:`candidate_lines`),
then two of them (or the number of matches) combined by AND / OR and a logistic regression, fitted on
``--fit``, with a bound chosen on the last ``ROWS`` (:func:`combined_lines`).
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

GOOD = (5.0, 0.1)       # a pose this close must never be called FAILED
WRONG = (20.0, 0.5)     # a pose outside the paper's RR thresholds must not be called REGISTERED

# The frames of the shipped ICL sample (0, 10, ..., 210) the rule is fitted on and reported on: the
# first and the second half of the trajectory; pairs only within a half, so no frame is in both.
SPLIT = {"fit": tuple(range(0, 101, 10)), "report": tuple(range(110, 211, 10))}
GAPS = (10, 100)  # frame gaps of the pairs within a half: all of them

SUPPORT_STEP = 0.25  # the fitted support is the next quarter above the strongest wrong fit pose
SOLVERS = ("kabsch", "pnp")


def pairs_within(frames, min_gap: int = GAPS[0], max_gap: int = GAPS[1]) -> list[tuple[int, int]]:
    """The frame pairs ``(i, j)`` with both frames in ``frames`` and ``min_gap <= j - i <= max_gap``."""
    frames = sorted(frames)
    return [(i, j) for i in frames for j in frames if min_gap <= j - i <= max_gap]


TARGETS = {"right_FAILED": 0.10, "wrong_REGISTERED": 0.05}  # the acceptance targets on another sensor


def read_rows(path: str):
    """The rows of a CSV, or of the ``.json`` of ``tools/verdict_holdout.py`` (its ``rows``), as a table."""
    import json

    import pandas as pd

    if str(path).endswith(".json"):
        with open(path) as f:
            return pd.DataFrame(json.load(f)["rows"])
    return pd.read_csv(path)


def frames_of(table, prefix: str = "icl/") -> set[int]:
    """The frame numbers in the ``pair`` column (``icl/00000-00010``) of ``table`` whose name starts with ``prefix``."""
    return {int(f) for name in table["pair"] if str(name).startswith(prefix) for f in name.split("/")[-1].split("-")}


def _good(table) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return ((table["RE"] < GOOD[0]) & (table["TE"] < GOOD[1])).to_numpy()


def _wrong(table) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return ~((table["RE"] < WRONG[0]) & (table["TE"] < WRONG[1])).to_numpy()


def _config():
    from freereg_lib.config import config_for

    return config_for("3dmatch")  # the solvers' minimum matches (the null's floor) are every setting's


def nulls_of(cell) -> list[int]:
    """The ``null_inliers`` cell (``"0;11;11;11"``) as counts."""
    text = "" if cell is None or (isinstance(cell, float) and math.isnan(cell)) else str(cell)
    return [int(float(v)) for v in text.split(";") if v.strip()]


def supports(table) -> np.ndarray:
    """Each row's support: its inliers over its null (:func:`freereg_lib.pipeline.verdict.null_of`)."""
    from freereg_lib.pipeline import verdict

    cfg = _config()
    return np.array([int(r["n_inliers"]) / verdict.null_of(nulls_of(r["null_inliers"]), r["solver"], cfg)
                     for r in table.to_dict("records")], dtype=float)


def fit_rule(table) -> dict:
    """The verdict's ``MIN_SUPPORT`` fitted on ``table`` (rows with the columns ``solver, success,
    n_matches, n_inliers, scale, null_inliers, RE, TE``): ``{"min_support": {solver: float},
    "max_scale": float}``, as :mod:`freereg_lib.pipeline.verdict` holds them.

    The criterion puts false positives first: per solver, the smallest support on a grid of
    :data:`SUPPORT_STEP` that lies above every wrong pose of ``table`` (solved, outside
    :data:`WRONG`, (20 deg, 0.5 m), with a Kabsch scale the verdict's bound lets through), so no
    wrong fit pose is called REGISTERED and as few right ones as that allows are called FAILED.
    ``max_scale`` is not fitted (a sanity bound, :data:`freereg_lib.pipeline.verdict.MAX_SCALE`).
    Deterministic: no search, no randomness."""
    from freereg_lib.pipeline import verdict

    out: dict = {"min_support": {}, "max_scale": verdict.MAX_SCALE}
    sup = supports(table)
    wrong = _wrong(table) & table["success"].astype(bool).to_numpy()
    scale = table["scale"].to_numpy(dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        plausible = np.maximum(scale, 1 / scale) <= verdict.MAX_SCALE
    for solver in SOLVERS:
        mine = (table["solver"] == solver).to_numpy()
        if not (mine & _good(table)).any():
            raise ValueError(f"no right {solver} pose to fit the verdict on")
        beaten = sup[mine & wrong & (plausible | (solver != "kabsch"))]
        top = float(beaten.max()) if len(beaten) else 1.0
        out["min_support"][solver] = round((math.floor(top / SUPPORT_STEP + 1e-9) + 1) * SUPPORT_STEP, 4)
    return out


def command_rule() -> dict:
    """The constants the command uses (:mod:`freereg_lib.pipeline.verdict`), as :func:`fit_rule` gives them."""
    from freereg_lib.pipeline import verdict

    return {"min_support": {s: verdict.MIN_SUPPORT[s] for s in SOLVERS}, "max_scale": verdict.MAX_SCALE}


def verdicts(table, rule: dict | None = None) -> np.ndarray:
    """The command's verdict for each row of ``table``, computed by
    :func:`freereg_lib.pipeline.verdict.decide` itself with ``rule`` (a :func:`fit_rule`
    result; default the command's constants)."""
    from types import SimpleNamespace

    from freereg_lib.pipeline import verdict

    rule, cfg = rule or command_rule(), _config()
    out = []
    for r in table.to_dict("records"):
        s = r["solver"]
        res = SimpleNamespace(success=bool(r["success"]), reason="", scale=float(r["scale"]),
                              n_inliers=int(r["n_inliers"]))
        ok, _ = verdict.decide(res, nulls_of(r["null_inliers"]), s, cfg, rule["min_support"][s], rule["max_scale"])
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
            "registered": int(ok.sum()), "right": int(right.sum()), "missed_right": int((right & ~ok).sum()),
            "missed_right_rate": int((right & ~ok).sum()) / max(int(right.sum()), 1),
            "missed_right_ci": clopper_pearson(int((right & ~ok).sum()), int(right.sum()))}


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


TARGET_HEADER = ("| | poses | right: within (20 deg, 0.5 m) | FAILED among them (target <= 10 %) "
                 "| wrong: outside (20 deg, 0.5 m) | REGISTERED among them (target <= 5 %) "
                 "| within (5 deg, 0.1 m): FAILED among them |\n|---|---|---|---|---|---|---|")


def _share(k: int, n: int, ci) -> str:
    return f"{k} of {n}" + (f" ({_pct(k / n)} %, [{_pct(ci[0])}, {_pct(ci[1])}])" if n else "")


def target_lines(table, rule: dict | None = None) -> list[str]:
    """The acceptance table: per solver and depth (``true``, ``stub``), per solver and all, right poses
    (the paper's (20 deg, 0.5 m)) FAILED and wrong ones REGISTERED with their 95 % Clopper-Pearson
    intervals, and the poses within (5 deg, 0.1 m) FAILED."""
    lines = TARGET_HEADER.split("\n")
    groups = [(f"{name}, {depth} depth", table[(table["solver"] == s) & (table["depth"] == depth)])
              for s, name in (("kabsch", "Kabsch"), ("pnp", "PnP")) for depth in ("true", "stub")]
    groups += [(name, table[table["solver"] == s]) for s, name in (("kabsch", "Kabsch"), ("pnp", "PnP"))]
    for name, sub in groups + [("all", table)]:
        r = rates(sub, verdicts(sub, rule))
        lines.append(f"| {name} | {r['rows']} | {r['right']} | {_share(r['missed_right'], r['right'], r['missed_right_ci'])} "
                     f"| {r['wrong']} | {_share(r['FP'], r['wrong'], r['FP_ci'])} | {_share(r['FN'], r['good'], r['FN_ci'])} |")
    return lines


# Other statistics than the support (:func:`candidate_lines`), each of a row's inliers ``k``, matches
# ``n`` and null (:func:`freereg_lib.pipeline.verdict.null_of`); higher is more support.
def _col(table, name: str) -> np.ndarray:
    return table[name].to_numpy(dtype=float)


def _null(table) -> np.ndarray:
    from freereg_lib.pipeline import verdict

    cfg = _config()
    return np.array([verdict.null_of(nulls_of(c), s, cfg) for c, s in zip(table["null_inliers"], table["solver"])],
                    dtype=float)


def _null_solved_mean(table) -> np.ndarray:
    """The mean of the shuffles that found a pose (a failed shuffle, 0, is no count), at least the floor."""
    from freereg_lib.pipeline import verdict

    cfg = _config()
    floor = np.array([verdict.null_of([], s, cfg) for s in table["solver"]], dtype=float)
    solved = [[v for v in nulls_of(c) if v > 0] for c in table["null_inliers"]]
    return np.maximum(floor, [np.mean(v) if v else 0.0 for v in solved])


def _binomial(table) -> np.ndarray:
    """-log10 P(X >= k), X ~ Binomial(n, null / n): the pose's inliers against the null's inlier rate."""
    from scipy.stats import binom

    k, n = _col(table, "n_inliers"), np.maximum(_col(table, "n_matches"), 1)
    p0 = np.clip(_null(table) / n, 1e-9, 1 - 1e-9)
    return -np.log10(np.maximum(binom.sf(k - 1, n, p0), 1e-300))


STATISTICS = {
    "support k / null": supports,
    "support k / mean of the solved shuffles": lambda t: _col(t, "n_inliers") / _null_solved_mean(t),
    "inlier fraction k / n": lambda t: _col(t, "n_inliers") / np.maximum(_col(t, "n_matches"), 1),
    "inliers k": lambda t: _col(t, "n_inliers"),
    "binomial -log10 p": _binomial,
    "excess (k - null) / n": lambda t: (_col(t, "n_inliers") - _null(t)) / np.maximum(_col(t, "n_matches"), 1),
}
CRITERIA = ("no wrong pose", "least errors")


def _solved(table) -> np.ndarray:
    """Solved, with (Kabsch) a scale the verdict's bound lets through: the poses a least value decides."""
    from freereg_lib.pipeline import verdict

    scale = _col(table, "scale")
    with np.errstate(divide="ignore", invalid="ignore"):
        plausible = np.maximum(scale, 1 / scale) <= verdict.MAX_SCALE
    return table["success"].astype(bool).to_numpy() & (plausible | (table["solver"] != "kabsch").to_numpy())


def fit_statistic(table, stat: str, criterion: str = "no wrong pose") -> dict:
    """Per solver the least value of ``STATISTICS[stat]`` a REGISTERED pose needs, fitted on ``table``:
    ``"no wrong pose"``: just above every solved wrong pose (outside :data:`WRONG`) of ``table``, as
    :func:`fit_rule` without its grid; ``"least errors"``: the value with the least sum of the two
    rates, right poses FAILED and wrong poses REGISTERED."""
    v, ok, right = STATISTICS[stat](table), _solved(table), ~_wrong(table)
    out = {}
    for solver in SOLVERS:
        mine = (table["solver"] == solver).to_numpy()
        good, bad = mine & right, mine & ~right
        if criterion == "no wrong pose":
            out[solver] = float(np.nextafter(v[bad & ok].max(), np.inf)) if (bad & ok).any() else -np.inf
            continue

        def errors(c):
            reg = ok & (v >= c)
            return (good & ~reg).sum() / max(good.sum(), 1) + (bad & reg).sum() / max(bad.sum(), 1)

        out[solver] = float(min(np.unique(v[mine]), key=errors))
    return out


def statistic_verdicts(table, stat: str, least: dict) -> np.ndarray:
    """REGISTERED: solved, (Kabsch) of a plausible scale, and ``STATISTICS[stat]`` at least ``least[solver]``."""
    need = np.array([least[s] for s in table["solver"]], dtype=float)
    return _solved(table) & (STATISTICS[stat](table) >= need)


def _rates_table(rule_col: str, on_col: str, tables: dict):
    """A markdown table's header lines and ``line(name, on, least, ok_of)``, which appends a rule's row:
    its right poses FAILED and wrong ones REGISTERED on each of ``tables`` (``{name: rows}``), where
    ``ok_of(rows)`` is the rule's REGISTERED mask."""
    lines = [f"| {rule_col} | {on_col} | least (Kabsch; PnP) |"
             + "".join(f" {n}: right FAILED | {n}: wrong REGISTERED |" for n in tables),
             "|" + "---|" * (3 + 2 * len(tables))]

    def line(name, on, least, ok_of):
        cells = []
        for sub in tables.values():
            r = rates(sub, ok_of(sub))
            cells += [_share(r["missed_right"], r["right"], r["missed_right_ci"]),
                      _share(r["FP"], r["wrong"], r["FP_ci"])]
        lines.append(f"| {name} | {on} | {least} | " + " | ".join(cells) + " |")

    return lines, line


def candidate_lines(fit, tables: dict, extra: dict | None = None) -> list[str]:
    """The candidates table of docs/your_data.md: the command's rule, then each statistic of
    :data:`STATISTICS` fitted by each criterion of :data:`CRITERIA` on ``fit`` (and by the first on
    ``fit`` plus each of ``extra``, ``{name: rows}``), with the right poses FAILED and the wrong ones
    REGISTERED (the paper's (20 deg, 0.5 m); 95 % Clopper-Pearson) on each of ``tables`` (``{name: rows}``)."""
    import pandas as pd

    lines, line = _rates_table("statistic", "fitted on", tables)

    rule = command_rule()
    line("the command: support k / null, on a grid of 0.25", "fit",
         "; ".join(f"{rule['min_support'][s]:g}" for s in SOLVERS), lambda sub: verdicts(sub, rule))
    sets = {"fit": fit, **{f"fit + {n}": pd.concat([fit, t], ignore_index=True) for n, t in (extra or {}).items()}}
    for on, rows in sets.items():
        for criterion in CRITERIA if on == "fit" else CRITERIA[:1]:
            strict = criterion == "no wrong pose"  # shown as "> the strongest wrong pose"
            for stat in STATISTICS:
                least = fit_statistic(rows, stat, criterion)
                shown = "; ".join(f"> {np.nextafter(least[s], -np.inf):.3g}" if strict else f">= {least[s]:.3g}"
                                  for s in SOLVERS)
                line(f"{stat} ({criterion})", on, shown,
                     lambda sub, stat=stat, least=least: statistic_verdicts(sub, stat, least))
    return lines


# Two statistics combined (:func:`combined_lines`): REGISTERED when ``a >= x`` AND (or OR) ``b >= y``,
# for every pair of :data:`STATISTICS` and the number of matches; and a logistic regression.
PARTNERS = {**STATISTICS, "matches n": lambda t: _col(t, "n_matches")}
MODES = ("AND", "OR")


def fit_combined(table, a: str, b: str, mode: str) -> dict:
    """Per solver the least values ``(x, y)`` of ``PARTNERS[a]`` and ``PARTNERS[b]``, fitted on ``table``
    as :func:`fit_statistic` ``"no wrong pose"``: no solved wrong pose (outside :data:`WRONG`)
    REGISTERED and, of those, the fewest right poses FAILED. ``OR``: each just above its strongest
    wrong pose; ``AND``: for each ``x`` (on the grid just above the table's values) the least ``y``
    that passes no wrong pose, ties to the least ``x`` (one statistic alone when it does as well)."""
    va, vb, ok, right = PARTNERS[a](table), PARTNERS[b](table), _solved(table), ~_wrong(table)
    out = {}
    for solver in SOLVERS:
        mine = (table["solver"] == solver).to_numpy()
        good, bad = mine & right, mine & ~right & ok

        def above(v, rows):
            return float(np.nextafter(v[rows].max(), np.inf)) if rows.any() else -np.inf

        if mode == "OR":
            out[solver] = (above(va, bad), above(vb, bad))
            continue
        best = None
        for x in np.concatenate([[-np.inf], np.nextafter(np.unique(va[mine]), np.inf)]):
            y = above(vb, bad & (va >= x))
            failed = int((good & ~(ok & (va >= x) & (vb >= y))).sum())
            if best is None or failed < best[0]:
                best = (failed, float(x), y)
        out[solver] = best[1:]
    return out


def combined_verdicts(table, a: str, b: str, mode: str, least: dict) -> np.ndarray:
    """REGISTERED: solved, (Kabsch) of a plausible scale, and ``a >= x`` AND / OR ``b >= y`` (``least[solver]``)."""
    x, y = (np.array([least[s][i] for s in table["solver"]], dtype=float) for i in (0, 1))
    pa, pb = PARTNERS[a](table) >= x, PARTNERS[b](table) >= y
    return _solved(table) & ((pa & pb) if mode == "AND" else (pa | pb))


def combinations() -> list[tuple[str, str, str]]:
    """Every ``(a, b, mode)``: each pair of :data:`PARTNERS` in order, ``AND`` then ``OR``."""
    import itertools

    return [(a, b, mode) for a, b in itertools.combinations(PARTNERS, 2) for mode in MODES]


LOGISTIC_C = 1.0  # the L2 weight's inverse on the standardized features


def _log_features(table) -> np.ndarray:
    """log k, log n, log null: every ratio of :data:`STATISTICS` but the binomial is linear in these."""
    return np.column_stack([np.log(np.maximum(_col(table, "n_inliers"), 1)),
                            np.log(np.maximum(_col(table, "n_matches"), 1)), np.log(_null(table))])


def fit_logistic(table) -> dict:
    """Per solver a logistic regression of right (within :data:`WRONG`) on :func:`_log_features` of the
    solved poses of ``table`` (standardized, classes weighted equally, L2 with :data:`LOGISTIC_C`),
    and its cut on the linear score just above every solved wrong pose: ``{solver: (mean, std,
    weights, cut)}``. Deterministic (a convex loss, minimized from zero with its gradient)."""
    from scipy.optimize import minimize

    ok, right = _solved(table), ~_wrong(table)
    feats, out = _log_features(table), {}
    for solver in SOLVERS:
        rows = ok & (table["solver"] == solver).to_numpy()
        x, y = feats[rows], right[rows].astype(float)
        mean, std = x.mean(0), x.std(0) + 1e-12
        z = np.column_stack([(x - mean) / std, np.ones(len(x))])
        w = np.where(y > 0, len(y) / (2 * max(y.sum(), 1)), len(y) / (2 * max((1 - y).sum(), 1)))

        def loss(beta):
            s = z @ beta
            p = 1 / (1 + np.exp(-s))
            value = (w * (np.logaddexp(0, -s) * y + np.logaddexp(0, s) * (1 - y))).sum()
            return value + 0.5 / LOGISTIC_C * (beta[:-1] ** 2).sum(), z.T @ (w * (p - y)) + np.r_[beta[:-1] / LOGISTIC_C, 0]

        beta = minimize(loss, np.zeros(z.shape[1]), jac=True, method="L-BFGS-B", options={"gtol": 1e-10}).x
        score = z @ beta
        bad = (y == 0)
        out[solver] = (mean, std, beta, float(np.nextafter(score[bad].max(), np.inf)) if bad.any() else -np.inf)
    return out


def logistic_verdicts(table, model: dict) -> np.ndarray:
    """REGISTERED: solved, (Kabsch) of a plausible scale, and the :func:`fit_logistic` score at least its cut."""
    feats, ok = _log_features(table), np.zeros(len(table), dtype=bool)
    for solver, (mean, std, beta, cut) in model.items():
        rows = (table["solver"] == solver).to_numpy()
        ok[rows] = np.column_stack([(feats[rows] - mean) / std, np.ones(int(rows.sum()))]) @ beta >= cut
    return _solved(table) & ok


# Two statistics chosen on the TUM rows among the rules that pass no wrong pose of the ICL fit rows:
# an upper bound on what such a rule reaches there, not a rule (docs/your_data.md).
TUM_BOUND = {"kabsch": ("inlier fraction k / n", 0.2851, "inliers k", 29.0),
             "pnp": ("support k / null", 1.4, "inlier fraction k / n", 0.0967)}


def bound_verdicts(table, bound: dict = TUM_BOUND) -> np.ndarray:
    """REGISTERED: solved, (Kabsch) of a plausible scale, and per solver ``a >= x AND b >= y`` of ``bound``."""
    ok = np.zeros(len(table), dtype=bool)
    for solver, (a, x, b, y) in bound.items():
        rows = (table["solver"] == solver).to_numpy()
        ok |= rows & (PARTNERS[a](table) >= x) & (PARTNERS[b](table) >= y)
    return _solved(table) & ok


def _meets(r: dict) -> bool:
    return r["missed_right_rate"] <= TARGETS["right_FAILED"] and r["FP_rate"] <= TARGETS["wrong_REGISTERED"]


def combined_lines(fit, tables: dict, target: str | None = None) -> list[str]:
    """The combined rules' table of docs/your_data.md, counted as :func:`candidate_lines` on ``tables``
    (``{name: rows}``; the fit rows may be one of them): the rule of :func:`combinations` fitted on
    ``fit`` (:func:`fit_combined`) with the fewest right fit poses FAILED; the one with the fewest
    right poses of ``tables[target]`` FAILED among those passing at most 5 % of its wrong ones
    (chosen on ``target``; default the last table); the logistic regression (:func:`fit_logistic`);
    and :data:`TUM_BOUND`, labelled as chosen on TUM."""
    target = target or list(tables)[-1]
    lines, line = _rates_table("combined rule", "chosen on", tables)

    def shown(a, b, mode, least):  # a bound of -inf (one statistic alone does as well) is left out
        def one(x, y):
            parts = [f"{n} > {np.nextafter(v, -np.inf):.3g}" for n, v in ((a, x), (b, y)) if v != -np.inf]
            return f" {mode} ".join(parts) or "any solved pose"
        return "; ".join(one(*least[s]) for s in SOLVERS)

    fitted = [(c, fit_combined(fit, *c)) for c in combinations()]
    right = ~_wrong(fit)

    def fit_failed(item):
        return int((right & ~combined_verdicts(fit, *item[0], item[1])).sum())

    for on, pick in (("fit: fewest right FAILED", min(fitted, key=fit_failed)),
                     (f"{target}: fewest right FAILED, at most 5 % wrong REGISTERED",
                      min((i for i in fitted if rates(tables[target], combined_verdicts(tables[target], *i[0], i[1]))["FP_rate"]
                           <= TARGETS["wrong_REGISTERED"]),
                          key=lambda i: rates(tables[target], combined_verdicts(tables[target], *i[0], i[1]))["missed_right"]))):
        (a, b, mode), least = pick
        line(f"{a} {mode} {b}, fitted on the ICL fit rows", on, shown(a, b, mode, least),
             lambda sub, a=a, b=b, mode=mode, least=least: combined_verdicts(sub, a, b, mode, least))
    model = fit_logistic(fit)
    line("logistic regression on log k, log n, log null, fitted on the ICL fit rows", "fit: above every wrong pose",
         "; ".join(f"{s}: {', '.join(f'{round(v, 2) + 0.0:.2f}' for v in model[s][2])}, cut {round(model[s][3], 2) + 0.0:.2f}"
                   for s in SOLVERS),
         lambda sub: logistic_verdicts(sub, model))
    line("two statistics passing no wrong ICL fit pose, thresholds chosen on TUM (a bound, not a rule)", "TUM",
         "; ".join(f"{a} >= {x:g} AND {b} >= {y:g}" for a, x, b, y in TUM_BOUND.values()),
         bound_verdicts)
    return lines


def _set_name(path) -> str:
    """A rows file's name in the candidates table: ``verdict_icl_report_rows.csv`` -> ``ICL report``."""
    stem = Path(path).name.split(".")[0].removeprefix("verdict_").removesuffix("_rows")
    return {"icl_report": "ICL report", "icl_fit": "ICL fit", "tum": "TUM"}.get(stem, stem)


def describe(rule: dict) -> str:
    """A rule as one line: per solver its least support and (Kabsch) scale bound."""
    return "; ".join(f"{s}: support >= {rule['min_support'][s]:g} x the shuffled matches' inliers"
                     + (f", scale within [{1 / rule['max_scale']:.2f}, {rule['max_scale']:g}]" if s == "kabsch" else "")
                     for s in SOLVERS)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fit", required=True, help="the rows to fit the rule on (tools/verdict_holdout.py fit)")
    p.add_argument("--rows", required=True, help="the rows to count it on (tools/verdict_holdout.py report|sample)")
    p.add_argument("--targets", action="store_true", help="also the acceptance table per solver and depth")
    p.add_argument("--candidates", nargs="+", metavar="ROWS",
                   help="also the other statistics (STATISTICS), fitted on --fit, counted on each ROWS")
    p.add_argument("--fit-also", nargs="*", default=(), metavar="ROWS",
                   help="with --candidates: also fit each statistic on --fit plus these rows")
    a = p.parse_args(argv)
    fit, report = read_rows(a.fit), read_rows(a.rows)
    rule = fit_rule(fit)
    where = sorted({str(n).split("/")[0] + "/" for n in report["pair"]})  # the sample(s) of the rows
    shared = frames_of(fit) & frames_of(report) if where == ["icl/"] else set()
    print(f"fitted on {fit['pair'].nunique()} pairs ({len(fit)} poses) of frames {sorted(frames_of(fit))}: {describe(rule)}")
    print("the command's rule: " + ("the same" if rule == command_rule() else describe(command_rule())))
    print(f"counted on {report['pair'].nunique()} pairs ({len(report)} poses) of "
          + ", ".join(f"{w} frames {sorted(frames_of(report, w))}" for w in where)
          + (f"; frames in both: {sorted(shared)}" if shared else "; no frame in both"))
    print("\n".join(table_lines(report, rule)))
    if a.targets:
        print("\n".join(target_lines(report, rule)))
    if a.candidates:
        tables = {_set_name(c): read_rows(c) for c in a.candidates}
        print("\n".join(candidate_lines(fit, tables, {_set_name(c): read_rows(c) for c in a.fit_also})))
        print("\n".join(combined_lines(fit, {"ICL fit": fit, **tables})))


if __name__ == "__main__":
    main()
