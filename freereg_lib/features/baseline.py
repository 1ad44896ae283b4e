"""The position-only baseline of Table 1: matches from pixel positions alone.

Each image keypoint is matched to the depth-view keypoint at the same pixel (the image's grid
mapped onto the depth view when the two sizes differ) or, where that one has no depth, the
nearest one, mutually (a depth keypoint takes the image keypoint nearest to it): no feature,
diffusion or geometric, is computed. The same solvers (Kabsch-RANSAC on the monocular depth,
PnP-RANSAC) then run on those matches, and the same scores follow.

Why it belongs in the table: when the image and the cloud's depth camera look from nearly
the same pose (small motions: the first pairs of a sequence), "the same pixel" is already a
good match, and a method that does not beat it has shown nothing about its features. The
verdict lines (:func:`verdict_lines`) say so for every method.

In a benchmark it is one more method name, ``METHOD``, run by
:func:`freereg_lib.pipeline.variant_rows` with every solver of the run
(:func:`with_baseline`); its fusion weight ``w`` is NaN (no feature).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from freereg_lib.features.matching import Matches

METHOD = "Position-only"
W = math.nan  # the method's fusion weight in the rows: none, no feature is used


def position_matches(feats, image_size: tuple[int, int], depth_size: tuple[int, int]):
    """Mutual nearest neighbours in pixel position between the image keypoints
    (``feats.uv_image``) and the depth keypoints that have a depth (``feats.uv_depth``), the
    image's pixels mapped onto the depth view (``(u + 0.5) * W_d / W - 0.5``, the same for
    ``v``). Returns :class:`~freereg_lib.features.matching.Matches`."""

    uv_i = np.asarray(feats.uv_image, dtype=np.float64)
    uv_d = np.asarray(feats.uv_depth, dtype=np.float64)
    if len(uv_i) == 0 or len(uv_d) == 0:
        return Matches(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    (H, W), (Hd, Wd) = image_size, depth_size
    mapped = np.stack([(uv_i[:, 0] + 0.5) * Wd / W - 0.5, (uv_i[:, 1] + 0.5) * Hd / H - 0.5], axis=1)
    to_depth = cKDTree(uv_d).query(mapped)[1]
    to_image = cKDTree(mapped).query(uv_d)[1]
    ia = np.flatnonzero(to_image[to_depth] == np.arange(len(mapped)))
    return Matches(ia.astype(np.int64), to_depth[ia].astype(np.int64))


def with_baseline(variants) -> list[tuple[str, str]]:
    """``variants`` (method, solver) followed by the baseline with each of their solvers (in
    order, once each); unchanged when the baseline is already there."""
    variants = [tuple(v) for v in variants]
    solvers = list(dict.fromkeys(s for m, s in variants if m != METHOD))
    return variants + [(METHOD, s) for s in solvers if (METHOD, s) not in variants]


def verdict_lines(table, metrics_: tuple[str, ...] = ("RR", "IR")) -> list[str]:
    """One line per method and solver of a summary table (:func:`~freereg_lib.pipeline.summarize`)
    comparing it with the baseline of the same solver on ``metrics_``, saying plainly when it
    does **not** beat it (not strictly above on every one of them). Empty without baseline rows."""
    rows = {(r["method"], r["solver"]): r for r in table.to_dict("records")}
    lines = []
    for (mth, sol), r in rows.items():
        base = rows.get((METHOD, sol))
        if mth == METHOD or base is None:
            continue
        parts = [f"{m} {r[m]:.1f} vs {base[m]:.1f}" for m in metrics_]
        lost = [m for m in metrics_ if not (r[m] > base[m])]
        verdict = ("beats the position-only baseline" if not lost else
                   f"does NOT beat the position-only baseline ({', '.join(lost)} not above it)")
        lines.append(f"{mth} + {sol}: {'; '.join(parts)} (position-only): {verdict}")
    return lines
