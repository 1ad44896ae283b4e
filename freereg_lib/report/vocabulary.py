"""The one verdict vocabulary: how a claim of the paper is judged on a run's or a committed split's pairs.

Every verdict line the notebooks print is made here, so that the same words mean the same evidence
everywhere:

* ``holds``: the difference is in the paper's direction and significant at 5 % on at least
  :data:`MIN_PAIRS` pairs;
* ``same direction, not significant``;
* ``opposite direction, significant`` / ``opposite direction, not significant``;
* ``no difference``: the two values are equal on pairs that carry a comparison;
* ``cannot be told (<reason>)``: the data cannot carry a comparison (fewer than :data:`MIN_PAIRS`
  pairs, both values 0, no p-value).

A verdict line names the claim, the verdict, the two values with their intervals, the difference,
p, the number of pairs and the setting, in that order:

    from freereg_lib.report.vocabulary import Value, verdict_line
    verdict_line("fused IR above FreeReg-G", Value("FreeReg", 20.3, (17.4, 23.2)), Value("FreeReg-G", 4.3, (3.7, 4.9)),
                 diff=16.0, p=5e-5, n=100, setting="micro, FPFH voxel 0.1 m, test split")
"""
from __future__ import annotations

from dataclasses import dataclass

MIN_PAIRS = 30
ALPHA = 0.05
VERDICTS = ("holds", "same direction, not significant", "opposite direction, significant",
            "opposite direction, not significant", "no difference", "cannot be told")


@dataclass(frozen=True)
class Value:
    """One side of a comparison: its name, value (% or a count) and 95 % interval when known."""

    name: str
    value: float
    ci: tuple[float, float] | None = None

    def __str__(self) -> str:
        ci = "" if self.ci is None else f" [{self.ci[0]:.1f}, {self.ci[1]:.1f}]"
        return f"{self.name} {self.value:.1f}{ci}"


def verdict(diff: float, p: float | None, n: int, expected_sign: int = 1, both_zero: bool = False) -> str:
    """The verdict word for a difference ``diff`` (claimed side minus the other) whose paper sign is
    ``expected_sign`` (+1: the claimed side is above), with paired p-value ``p`` over ``n`` pairs."""
    if n < MIN_PAIRS:
        return f"cannot be told ({n} pair{'s' if n != 1 else ''}, fewer than {MIN_PAIRS})"
    if both_zero:
        return "cannot be told (both values are 0)"
    if p is None:
        return "cannot be told (no paired test)"
    if diff == 0:
        return "no difference"
    significant = p < ALPHA
    if (diff > 0) == (expected_sign > 0):
        return "holds" if significant else "same direction, not significant"
    return f"opposite direction, {'significant' if significant else 'not significant'}"


def p_text(p: float | None, permutations: int | None = None) -> str:
    """``p = 0.0370``, or ``p < 0.0001`` at the smallest p a permutation test can give."""
    if p is None:
        return "no p"
    floor = 1.0 / (permutations + 1) if permutations else 0.0
    return f"p < {max(floor * 1.0001, 1e-4):.4f}" if p <= max(floor, 1e-4) + 1e-12 else f"p = {p:.4f}"


def verdict_line(claim: str, a: Value, b: Value, diff: float, p: float | None, n: int, setting: str,
                 expected_sign: int = 1, unit: str = "points") -> str:
    """One line: ``<claim>: <verdict>: <a> vs <b>, <diff> <unit>, <p>; n = <n> pairs, <setting>``."""
    both_zero = a.value == 0 and b.value == 0
    word = verdict(diff, p, n, expected_sign, both_zero)
    return f"{claim}: {word}: {a} vs {b}, {diff:+.1f} {unit}, {p_text(p)}; n = {n} pairs, {setting}"


def glimpse_line(claim: str, a: Value, b: Value, n: int, setting: str) -> str:
    """A live run's comparison on fewer than :data:`MIN_PAIRS` pairs: the values, and no verdict."""
    return (f"{claim}: {verdict(a.value - b.value, None, n)}: {a} vs {b}; n = {n} live pair(s), {setting} "
            "(a glimpse)")


def paired_line(claim: str, name_a: str, a, name_b: str, b, setting: str, expected_sign: int = 1,
                scale: float = 100.0, unit: str = "points") -> str:
    """A verdict line from two per-pair lists of the same pairs (rates in [0, 1] shown in % with
    ``scale = 100``, counts with ``scale = 1``): means with 95 % bootstrap intervals, the paired
    permutation test, and the verdict; fewer than :data:`MIN_PAIRS` pairs get no verdict."""
    import numpy as np

    from freereg_lib.training.evaluate import bootstrap_ci, paired_permutation_p

    x = scale * np.asarray(a, dtype=np.float64)
    y = scale * np.asarray(b, dtype=np.float64)
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    n = len(x)
    va = Value(name_a, float(x.mean()) if n else float("nan"), bootstrap_ci(x) if n > 1 else None)
    vb = Value(name_b, float(y.mean()) if n else float("nan"), bootstrap_ci(y) if n > 1 else None)
    p = paired_permutation_p(x, y) if n >= MIN_PAIRS else None
    return verdict_line(claim, va, vb, float(np.mean(x - y)) if n else 0.0, p, n, setting, expected_sign, unit)
