"""Evaluation: correct correspondences, FMR, IR, IN, RR, RE, TE and RR over threshold ladders.

Definitions follow the paper and the official code (docs/fidelity.md):

* a match (image pixel, cloud point) is *evaluable* when the image's true depth at the
  pixel lies in ``depth_range``; it is *correct* when the pixel, lifted with that true
  depth and moved into the cloud frame with the true pose, lies within ``tau_c`` of the
  matched cloud point;
* per pair: IR = correct / evaluable, IN = correct; with fewer than 3 evaluable matches the
  official code scores IR 1, IN 1 (``few="official"``, the default; ``"zero"``: IR 0);
* over pairs: FMR = % of pairs with IR > 5 %, IR and IN are means (IR in %), RR = % of pairs
  with RE < tau_R and TE < tau_t.
* RE is the angle of ``R_gt^T R_est`` (from quaternions, as the official ``compute_R_diff``);
  TE is the distance between the true and estimated camera centres in the cloud frame,
  ``|| t(T_pc_cam_gt) - t(T_pc_cam_est) ||`` (the official ``compute_T_err`` on its
  ``gt = T_pc_cam``). A pair whose solver failed has no RE / TE and is not registered.
"""
from __future__ import annotations

import math

import numpy as np

from freereg_lib.geometry import cameras


def correct_matches(
    uv_image: np.ndarray,
    pts_pc: np.ndarray,
    depth_gt: np.ndarray,
    K_image: np.ndarray,
    T_cam_pc_gt: np.ndarray,
    tau_c: float = 0.3,
    depth_range: tuple[float, float] = (0.01, 10.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Which matches are correct.

    ``uv_image (K, 2)`` image pixels, ``pts_pc (K, 3)`` their matched cloud points,
    ``depth_gt (H, W)`` the image's true depth. Returns ``correct (K,) bool`` and
    ``evaluable (K,) bool``; ``correct`` implies ``evaluable``.
    """
    dist, evaluable, _ = match_distances(uv_image, pts_pc, depth_gt, K_image, T_cam_pc_gt, depth_range)
    correct = evaluable & (dist < tau_c)
    return correct, evaluable


def match_distances(uv_image, pts_pc, depth_gt, K_image, T_cam_pc_gt, depth_range=(0.01, 10.0)):
    """``(dist (K,), evaluable (K,) bool, lifted (K, 3))``: each image pixel lifted with its
    true depth and moved into the cloud frame (``lifted``), and its distance to the matched
    cloud point (NaN where not evaluable: true depth outside ``depth_range``, strict, or no
    finite cloud point)."""
    uv_image = np.asarray(uv_image, dtype=np.float64).reshape(-1, 2)
    pts_pc = np.asarray(pts_pc, dtype=np.float64).reshape(-1, 3)
    if len(uv_image) == 0:
        return np.zeros(0), np.zeros(0, bool), np.zeros((0, 3))
    z = cameras.nearest_sample(np.asarray(depth_gt, dtype=np.float64), uv_image)
    evaluable = np.isfinite(z) & (z > depth_range[0]) & (z < depth_range[1])
    evaluable &= np.all(np.isfinite(pts_pc), axis=1)
    # np.linalg.inv, not the rigid inverse: a ground truth read from a file with few digits is
    # orthonormal only to them, and the official code applies its gt as it is.
    T_pc_cam = np.linalg.inv(np.asarray(T_cam_pc_gt, dtype=np.float64))
    lifted = cameras.transform(T_pc_cam, cameras.lift(uv_image, np.where(evaluable, z, 0), K_image))
    dist = np.where(evaluable, np.linalg.norm(lifted - np.where(np.isfinite(pts_pc), pts_pc, 0.0), axis=1), np.nan)
    return dist, evaluable, lifted


def lift_truth(uv: np.ndarray, depth_gt: np.ndarray, K: np.ndarray, depth_range=(0.01, 10.0)) -> np.ndarray:
    """Pixels ``uv (K, 2)`` lifted with the true depth ``depth_gt`` into their camera frame,
    ``(K, 3)``, NaN rows where the depth is outside ``depth_range`` (strict): the official
    ``eval_mask`` of one side."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = cameras.nearest_sample(np.asarray(depth_gt, dtype=np.float64), uv) if len(uv) else np.zeros(0)
    ok = np.isfinite(z) & (z > depth_range[0]) & (z < depth_range[1])
    out = np.full((len(uv), 3), np.nan)
    if ok.any():
        out[ok] = cameras.lift(uv[ok], z[ok], K)
    return out


FEW_EVALUABLE = 3  # the official ir_cal: fewer evaluable matches than this give IR 1, IN 1


def inlier_stats(correct: np.ndarray, evaluable: np.ndarray, few: str = "official") -> tuple[float, int]:
    """Per-pair IR (fraction in [0, 1]) and IN.

    With fewer than 3 evaluable matches the official ``ir_cal`` returns the distances ``[0]``,
    so such a pair scores IR 1 and IN 1 (``few="official"``, the default, ``cfg.eval_few_matches``);
    ``few="zero"`` scores IR 0 and IN the correct count instead. Rows report
    ``n_evaluable`` so that such a pair can be seen.
    """
    n_eval = int(np.count_nonzero(evaluable))
    n_correct = int(np.count_nonzero(correct))
    if n_eval >= FEW_EVALUABLE:
        return n_correct / n_eval, n_correct
    if few == "official":
        return 1.0, 1
    if few == "zero":
        return 0.0, n_correct
    raise ValueError(f"few must be 'official' or 'zero', got {few!r}")


def pose_errors(T_cam_pc_est: np.ndarray, T_cam_pc_gt: np.ndarray) -> tuple[float, float]:
    """RE in degrees and TE in metres between two ``T_cam_pc`` poses (see module docstring)."""
    T_est = cameras.invert(np.asarray(T_cam_pc_est, dtype=np.float64))
    T_gt = cameras.invert(np.asarray(T_cam_pc_gt, dtype=np.float64))
    return transform_errors(T_est, T_gt)


def transform_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """The official ``compute_T_err(T_gt, T)`` on two transforms of one convention: RE from the
    quaternions of the rotation blocks, TE = ``|| t_gt - t ||`` of the translation columns."""
    T_est = np.asarray(T_est, dtype=np.float64)
    T_gt = np.asarray(T_gt, dtype=np.float64)
    re = cameras.rotation_error_deg(T_est[:3, :3], T_gt[:3, :3])
    te = float(np.linalg.norm(T_gt[:3, 3] - T_est[:3, 3]))
    return re, te


def registered(re: float, te: float, rot_deg: float, trans_m: float) -> bool:
    """RR test for one pair; NaN errors (a failed solve) are never registered."""
    return bool(np.isfinite(re) and np.isfinite(te) and re < rot_deg and te < trans_m)


def aggregate(
    rows: list[dict],
    rot_deg: float = 20.0,
    trans_m: float = 0.5,
    fmr_ratio: float = 0.05,
    ladder: tuple[tuple[float, float], ...] = (),
) -> dict:
    """Dataset-level metrics from per-pair rows with keys ``IR`` (fraction), ``IN``, ``RE``, ``TE``.

    Returns percentages ``FMR``, ``IR``, ``RR`` and ``RR@<deg>deg/<m>m`` for each ladder rung,
    the mean ``IN``, the mean and median ``RE`` / ``TE`` over pairs that have an estimate
    (``RE``, ``TE``, ``RE_median``, ``TE_median``) and over the registered pairs
    (``RE_reg``, ``TE_reg``, ``RE_reg_median``, ``TE_reg_median``), ``n_few_evaluable`` (rows
    with ``n_evaluable`` in 0..2: their truth covers too few matches to score) and ``n_pairs`` /
    ``n_failed`` (pairs without an estimate). The official tables average RE / TE over
    *all* pairs, a failed pair counting with the random pose the official code returns; a
    failed solve here has no pose, so that average cannot be formed. An empty list gives NaNs. A row
    whose ``IR`` is not a fraction in [0, 1] (a percentage, say) raises ``ValueError``.
    """
    n = len(rows)
    out: dict = {"n_pairs": n}
    if n == 0:
        for key in ("FMR", "IR", "IN", "RR", "RE", "TE", "RE_median", "TE_median",
                    "RE_reg", "TE_reg", "RE_reg_median", "TE_reg_median"):
            out[key] = math.nan
        out["n_failed"] = 0
        for deg, m in ladder:
            out[f"RR@{deg:g}deg/{m:g}m"] = math.nan
        return out
    ir = np.array([r["IR"] for r in rows], dtype=np.float64)
    bad = ~((ir >= 0.0) & (ir <= 1.0))
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"IR must be a fraction in [0, 1] in every row; row {k} (pair {rows[k].get('pair', '?')!r}) "
                         f"has IR = {float(ir[k])!r} (a percentage? divide it by 100)")
    inn = np.array([r["IN"] for r in rows], dtype=np.float64)
    re = np.array([r.get("RE", math.nan) for r in rows], dtype=np.float64)
    te = np.array([r.get("TE", math.nan) for r in rows], dtype=np.float64)
    has = np.isfinite(re) & np.isfinite(te)
    out["FMR"] = 100.0 * float(np.mean(ir > fmr_ratio))
    out["IR"] = 100.0 * float(np.mean(ir))
    out["IN"] = float(np.mean(inn))
    out["RR"] = 100.0 * float(np.mean([registered(a, b, rot_deg, trans_m) for a, b in zip(re, te)]))
    out["RE"] = float(np.mean(re[has])) if has.any() else math.nan
    out["TE"] = float(np.mean(te[has])) if has.any() else math.nan
    out["RE_median"] = float(np.median(re[has])) if has.any() else math.nan
    out["TE_median"] = float(np.median(te[has])) if has.any() else math.nan
    reg = np.array([registered(a, b, rot_deg, trans_m) for a, b in zip(re, te)], dtype=bool)
    out["RE_reg"] = float(np.mean(re[reg])) if reg.any() else math.nan
    out["TE_reg"] = float(np.mean(te[reg])) if reg.any() else math.nan
    out["RE_reg_median"] = float(np.median(re[reg])) if reg.any() else math.nan
    out["TE_reg_median"] = float(np.median(te[reg])) if reg.any() else math.nan
    out["n_failed"] = int(n - has.sum())
    if any("n_evaluable" in r for r in rows):
        # Pairs whose truth covers fewer than 3 matches (scored IR 1, IN 1 by the official rule).
        ne = np.array([r.get("n_evaluable", -1) for r in rows], dtype=np.float64)
        out["n_few_evaluable"] = int(np.count_nonzero((ne >= 0) & (ne < FEW_EVALUABLE)))
    for deg, m in ladder:
        out[f"RR@{deg:g}deg/{m:g}m"] = 100.0 * float(
            np.mean([registered(a, b, deg, m) for a, b in zip(re, te)])
        )
    return out


def true_correspondences(
    uv_image: np.ndarray, depth_gt: np.ndarray, K_image: np.ndarray, T_cam_pc_gt: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth 3D partners of image pixels, for tests and worked examples.

    Lifts ``uv_image (K, 2)`` with the true depth; returns camera points ``(K', 3)``, the
    same points in the cloud frame ``(K', 3)``, and the kept rows ``(K',)`` (valid depth).
    """
    z = cameras.nearest_sample(np.asarray(depth_gt, dtype=np.float64), uv_image)
    keep = np.nonzero(np.isfinite(z) & (z > 0))[0]
    uv_px = np.rint(np.asarray(uv_image, dtype=np.float64)[keep])
    pts_cam = cameras.lift(uv_px, z[keep], K_image)
    return pts_cam, cameras.transform(cameras.invert(T_cam_pc_gt), pts_cam), keep
