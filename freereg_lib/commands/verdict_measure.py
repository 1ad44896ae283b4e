"""How often is ``freereg register``'s verdict wrong? Measured on real frames.

The command says ``REGISTERED`` or ``FAILED`` without ground truth (:func:`freereg_lib.pipeline.register._verdict`:
enough RANSAC inliers, enough of the matches, a plausible Kabsch scale). This runs the command's
chain on pairs of the shipped ICL living-room sample exactly as ``freereg register IMAGE CLOUD
--depth-pose identity --image-depth DEPTH --backend stub`` runs it (the cloud in its sensor's
frame: the sensor is given; the ``demo`` config the command uses; FreeReg-G with FPFH, the stub's
monocular depth made from the true depth; both solvers), records each pose's inliers, matches,
scale and its true errors, and counts

* false negatives: ``FAILED`` for a pose within (5 deg, 0.1 m) of the truth (there must be none);
* false positives: ``REGISTERED`` for a pose outside the paper's (20 deg, 0.5 m).

::

    python -m freereg_lib.commands.verdict_measure [--pairs 40] [--max-gap 80] [--iters 50000] [--out rows.csv]

The pairs are spread evenly (:func:`freereg_lib.data.sources.spread`) over the sample's frame pairs
with gaps of 10 to ``max_gap`` frames (larger gaps: harder pairs, so both verdicts occur).
"""
from __future__ import annotations

import argparse

import numpy as np

GOOD = (5.0, 0.1)       # a pose this close must never be called FAILED
WRONG = (20.0, 0.5)     # a pose outside the paper's RR thresholds must not be called REGISTERED


def pick(n_items: int, n_pairs: int, held_out: bool = False) -> list[int]:
    """The spread selection of ``n_pairs`` (:func:`~freereg_lib.data.sources.spread`), or with
    ``held_out`` as many pairs spread over the ones that selection left out."""
    from freereg_lib.data.sources import spread

    chosen = spread(n_items, n_pairs)
    if not held_out:
        return chosen
    rest = sorted(set(range(n_items)) - set(chosen))
    return [rest[k] for k in spread(len(rest), n_pairs)]


def rows(n_pairs: int = 40, max_gap: int = 80, iters: int = 50_000, solvers=("kabsch", "pnp"),
         depths=("stub", "true"), held_out: bool = False, demo: str | None = None,
         progress: bool = True) -> list[dict]:
    """One row per (pair, depth, solver) with what the verdict reads and the true errors.

    ``depth``: the image side's depth, the stub's monocular depth (``"stub"``: the true depth with
    a global scale error and a smooth distortion, what the command runs) or the true depth
    itself (``"true"``: a perfect monocular depth model, standing in for a good real backend).
    ``held_out``: the pairs the selection of ``n_pairs`` leaves out (:func:`pick`), to check a rule
    fitted on the first. ``demo``: the official demo folder, added as one more pair."""
    import dataclasses

    from freereg_lib.commands.cli import choose_setting
    from freereg_lib.commands.real_frames import run
    from freereg_lib.config import config_for
    from freereg_lib.data.datasets.icl import ICLSample
    from freereg_lib.commands.user_inputs import load_demo

    sample = ICLSample()
    listed = sample.pair_list(max_gap=max_gap)
    pairs = [load_demo(demo)] if demo else []
    # As the command reads it: a cloud file (no sensor depth map) in its sensor's frame.
    pairs += [dataclasses.replace(sample.pair(*listed[k]), sensor_depth=None)
              for k in pick(len(listed), n_pairs, held_out)]
    gaps = {p.name: p.meta.get("frame_cloud", 0) - p.meta.get("frame_image", 0) for p in pairs}
    # The setting the command chooses for each pair (cli.choose_setting), as it would run it.
    by_setting: dict[str, list] = {}
    for p in pairs:
        by_setting.setdefault(choose_setting("auto", p, False, False, p is pairs[0] and bool(demo))[0], []).append(p)
    keep = ("depth", "solver", "success", "n_matches", "n_inliers", "scale", "RE", "TE", "seconds")
    out = []
    for setting, group in by_setting.items():
        cfg = config_for(setting, ransac_iters=iters)
        out += [{"pair": r["pair"], "gap": gaps[r["pair"]], "setting": setting, **{k: r[k] for k in keep}}
                for r in run(depths=depths, solvers=solvers, cfg=cfg, progress=progress, pairs=group)]
    return out


def verdicts(table, min_inliers=None, min_ratio=None, max_scale=None) -> np.ndarray:
    """The command's verdict for each row of ``table`` (a DataFrame of :func:`rows`), computed
    by :func:`freereg_lib.pipeline.register._verdict` itself; thresholds default to the command's."""
    from types import SimpleNamespace

    from freereg_lib.pipeline import register as R

    out = []
    for r in table.to_dict("records"):
        res = SimpleNamespace(success=bool(r["success"]), reason="", scale=float(r["scale"]),
                              n_inliers=int(r["n_inliers"]))
        ok, _ = R._verdict(res, {"matches": int(r["n_matches"]), "note": ""}, r["solver"],
                           *R.verdict_thresholds(r["solver"], min_inliers, min_ratio, max_scale))
        out.append(ok)
    return np.asarray(out, dtype=bool)


def rates(table, ok: np.ndarray) -> dict:
    """False negatives (FAILED within ``GOOD``) and false positives (REGISTERED outside ``WRONG``)."""
    re, te = table["RE"].to_numpy(), table["TE"].to_numpy()
    with np.errstate(invalid="ignore"):
        good = (re < GOOD[0]) & (te < GOOD[1])
        right = (re < WRONG[0]) & (te < WRONG[1])
    wrong = ~right
    return {"rows": len(table), "good": int(good.sum()), "wrong": int(wrong.sum()),
            "FN": int((good & ~ok).sum()), "FN_rate": float((good & ~ok).sum() / max(good.sum(), 1)),
            "FP": int((wrong & ok).sum()), "FP_rate": float((wrong & ok).sum() / max(wrong.sum(), 1)),
            "registered": int(ok.sum()), "missed_right": int((right & ~ok).sum())}


def main(argv=None) -> None:
    import pandas as pd

    from freereg_lib.pipeline.register import verdict_thresholds

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--max-gap", type=int, default=80)
    p.add_argument("--iters", type=int, default=50_000)
    p.add_argument("--held-out", action="store_true", help="the pairs the selection of --pairs leaves out")
    p.add_argument("--demo", help="the official demo folder: one more pair")
    p.add_argument("--out", help="write the rows as CSV")
    p.add_argument("--rows", help="read rows written before instead of running")
    a = p.parse_args(argv)
    table = pd.read_csv(a.rows) if a.rows else pd.DataFrame(rows(a.pairs, a.max_gap, a.iters, held_out=a.held_out, demo=a.demo))
    if a.out:
        table.to_csv(a.out, index=False)
    rule = "; ".join(f"{s}: >= {n} inliers, >= {q:.0%} of the matches" + (f", scale within {m:g}x" if s == "kabsch" else "")
                     for s in ("kabsch", "pnp") for n, q, m in [verdict_thresholds(s)])
    print(f"{table['pair'].nunique()} pairs x {table['depth'].nunique()} depths x {table['solver'].nunique()} "
          f"solvers; the rule: {rule}")
    groups = [("all", table), *table.groupby(["depth", "solver"])]
    for solver, sub in groups:
        solver = solver if isinstance(solver, str) else " + ".join(solver)
        r = rates(sub, verdicts(sub))
        print(f"  {solver:12s}: {r['rows']} poses, {r['good']} within {GOOD[0]:g} deg / {GOOD[1]:g} m, {r['wrong']} "
              f"outside {WRONG[0]:g} deg / {WRONG[1]:g} m; FAILED within: {r['FN']} ({r['FN_rate']:.0%}), "
              f"REGISTERED outside: {r['FP']} ({r['FP_rate']:.0%}); right but FAILED: {r['missed_right']}")


if __name__ == "__main__":
    main()
