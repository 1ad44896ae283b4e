"""``freereg register``'s REGISTERED / FAILED without ground truth: the pose's support against a per-run null.

The chosen pose's RANSAC inliers are compared with what the same solver reaches on the same matches
with their depth side shuffled (``NULL_SHUFFLES`` runs of at most ``NULL_MAX_ITERS``
iterations; the null is their most inliers, at least the solver's minimum of matches). REGISTERED:
a pose, (Kabsch) a scale within ``[1 / MAX_SCALE, MAX_SCALE]`` (a sanity bound) and inliers / null
at least ``MIN_SUPPORT`` (fitted by ``freereg_lib.commands.verdict_measure.fit_rule``;
docs/your_data.md has its rates).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from freereg_lib.pipeline import steps

MIN_SUPPORT = {"kabsch": 2.5, "pnp": 2.75}
MAX_SCALE = 1.5
NULL_SHUFFLES = {"kabsch": 4, "pnp": 2}
NULL_MAX_ITERS = 10_000


def null_inliers(pair, feats, m, cfg, solver: str, shuffles: int | None = None) -> list[int]:
    """The solver's inliers on ``m`` with its depth side shuffled, one count per shuffle (0: no
    pose); seeded by ``cfg.seed``, so a rerun agrees."""
    cheap = dataclasses.replace(cfg, ransac_iters=min(int(cfg.ransac_iters), NULL_MAX_ITERS))
    rng = np.random.default_rng([int(cfg.seed), len(m), 62])
    out = []
    for _ in range(NULL_SHUFFLES[solver] if shuffles is None else int(shuffles)) if len(m) else ():
        res = steps.solve(pair, feats, dataclasses.replace(m, idx_depth=np.asarray(m.idx_depth)[rng.permutation(len(m))]),
                          cheap, solver)
        out.append(int(res.n_inliers) if res.success else 0)
    return out


def null_of(nulls, solver: str, cfg) -> int:
    """The null a pose is compared with: the most inliers of the shuffles, at least the solver's minimum of matches."""
    return max([int(cfg.min_matches_kabsch if solver == "kabsch" else cfg.min_matches_pnp), *map(int, nulls)])


def decide(res, nulls, solver: str, cfg, min_support: float | None = None, max_scale: float | None = None,
           note: str = "") -> tuple[bool, str]:
    """``(registered, why)`` for the solver's ``res`` and the shuffles' inliers ``nulls``; ``why``
    prints the quantities compared."""
    need = MIN_SUPPORT[solver] if min_support is None else float(min_support)
    bound = MAX_SCALE if max_scale is None else float(max_scale)
    if res is None:
        return False, f"no pose ({note})"
    if not res.success:
        return False, f"the solver found no pose ({res.reason})"
    if solver == "kabsch" and not 1 / bound <= res.scale <= bound:
        return False, (f"the similarity's scale {res.scale:.2f} is outside [{1 / bound:.2g}, {bound:g}] "
                       "(it shrank or blew up the image side onto wrong matches)")
    null = null_of(nulls, solver, cfg)
    got = int(res.n_inliers) / null
    compared = (f"{res.n_inliers} inliers = {got:.2f} x the {null} the same solver reaches on the matches shuffled "
                f"(chance; {len(nulls)} shuffles: {', '.join(str(v) for v in nulls) or '-'})")
    if got < need:
        return False, f"{compared}, below {need:g} x"
    return True, f"{compared}, at least {need:g} x (a plausibility check, not a proof without ground truth)"
