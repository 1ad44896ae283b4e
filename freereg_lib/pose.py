"""Pose solvers: Kabsch-RANSAC (Open3D) on 3D-3D matches and PnP-RANSAC (OpenCV) on 2D-3D.

Both estimate ``T_cam_pc`` (point-cloud frame -> image camera) and return a
:class:`PoseResult`; too few or degenerate matches give ``success=False`` with a reason,
never an exception.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import cameras


@dataclass
class PoseResult:
    """A solver's answer.

    ``T_cam_pc`` is the estimate (identity when ``success`` is False); ``reason`` says why
    a solve failed; ``inliers`` indexes the matches the final model explains; ``scale`` is
    the similarity scale Kabsch absorbed from monocular depth (1 for PnP).
    """

    T_cam_pc: np.ndarray
    success: bool
    solver: str
    reason: str = ""
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    scale: float = 1.0

    @property
    def n_inliers(self) -> int:
        return int(len(self.inliers))


def _failed(solver: str, reason: str) -> PoseResult:
    return PoseResult(np.eye(4), False, solver, reason)


def _finite_rows(*arrays: np.ndarray) -> np.ndarray:
    keep = np.ones(len(arrays[0]), dtype=bool)
    for a in arrays:
        keep &= np.all(np.isfinite(a), axis=1)
    return keep


def _split_similarity(M: np.ndarray) -> tuple[np.ndarray, float]:
    """A 4 x 4 similarity ``[sR | t]`` as a rigid ``[R | t]`` and the scale ``s``."""
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    T = M.copy()
    T[:3, :3] = M[:3, :3] / s
    # Re-orthonormalise: the product of the solver's R and s carries rounding.
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    return T, s


def kabsch_ransac(
    pts_cam: np.ndarray,
    pts_pc: np.ndarray,
    inlier_m: float = 0.2,
    iterations: int = 50_000,
    ransac_n: int = 4,
    with_scale: bool = True,
    min_matches: int = 5,
    seed: int = 0,
    max_scale_ratio: float = 2.0,
) -> PoseResult:
    """Kabsch in RANSAC on matched ``pts_cam (K, 3)`` (image side) and ``pts_pc (K, 3)``.

    Uses Open3D's ``registration_ransac_based_on_correspondence``. With ``with_scale`` the
    model is a similarity mapping the image side onto the cloud, which absorbs monocular
    depth's global scale error (as the official code does); the returned pose is its rigid
    part. The model is then refined on its inliers at 2x and 1x ``inlier_m``. The inlier
    distance is measured in the point-cloud frame.

    A similarity can cheat: shrinking the image side towards one spot explains many matches
    when ``inlier_m`` is large (outdoors, 4 m). Minimal samples whose edge lengths differ by
    more than ``max_scale_ratio`` between the sides are therefore rejected (Open3D's
    edge-length checker), and a final scale outside ``[1 / max_scale_ratio, max_scale_ratio]``
    is a failure.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    pts_cam = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    pts_pc = np.asarray(pts_pc, dtype=np.float64).reshape(-1, 3)
    if len(pts_cam) != len(pts_pc):
        raise ValueError(f"pts_cam has {len(pts_cam)} rows but pts_pc has {len(pts_pc)}")
    rows = np.nonzero(_finite_rows(pts_cam, pts_pc))[0]
    need = max(min_matches, ransac_n, 3)
    if len(rows) < need:
        return _failed("kabsch", f"{len(rows)} usable matches (of {len(pts_cam)}; usable: finite 3D points on both "
                                 f"sides), Kabsch-RANSAC needs at least {need}")
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts_cam[rows]))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts_pc[rows]))
    idx = np.arange(len(rows), dtype=np.int32)
    corres = o3d.utility.Vector2iVector(np.stack([idx, idx], axis=1))
    estimation = reg.TransformationEstimationPointToPoint(with_scaling=with_scale)
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(1.0 / max_scale_ratio)]
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_correspondence(
        src, tgt, corres, inlier_m, estimation, ransac_n, checkers,
        reg.RANSACConvergenceCriteria(iterations, 0.9999),
    )
    M = np.asarray(result.transformation)
    src_np, tgt_np = pts_cam[rows], pts_pc[rows]
    for factor in (2.0, 1.0):
        resid = np.linalg.norm(src_np @ M[:3, :3].T + M[:3, 3] - tgt_np, axis=1)
        inl = np.nonzero(resid < factor * inlier_m)[0]
        if len(inl) < 3:
            break
        sel = o3d.utility.Vector2iVector(np.stack([inl, inl], axis=1).astype(np.int32))
        M = np.asarray(estimation.compute_transformation(src, tgt, sel))
    resid = np.linalg.norm(src_np @ M[:3, :3].T + M[:3, 3] - tgt_np, axis=1)
    inliers = rows[resid < inlier_m]
    if len(inliers) < 3 or not np.all(np.isfinite(M)) or np.linalg.det(M[:3, :3]) <= 1e-12:
        return _failed("kabsch", f"RANSAC found a degenerate model ({len(inliers)} inliers)")
    T_pc_cam, scale = _split_similarity(M)
    if not 1.0 / max_scale_ratio <= scale <= max_scale_ratio:
        return _failed("kabsch", f"the best model scales the image side by {scale:.2f}, beyond the allowed ratio {max_scale_ratio:g}")
    return PoseResult(cameras.invert(T_pc_cam), True, "kabsch", "", inliers, scale)


def _pnp_methods() -> dict[str, int]:
    """``pnp_ransac``'s ``method`` names and the ``cv2.solvePnPRansac`` ``flags`` they pass.

    The USAC entries need OpenCV's USAC framework (OpenCV >= 4.5); an OpenCV without it
    lacks those names rather than failing at import.
    """
    import cv2

    methods = {"iterative": cv2.SOLVEPNP_ITERATIVE, "ap3p": cv2.SOLVEPNP_AP3P,
               "epnp": cv2.SOLVEPNP_EPNP, "sqpnp": cv2.SOLVEPNP_SQPNP}
    for name, attr in (("usac", "USAC_DEFAULT"), ("usac_accurate", "USAC_ACCURATE")):
        if hasattr(cv2, attr):
            methods[name] = getattr(cv2, attr)
    return methods


PNP_METHODS = _pnp_methods()


def pnp_ransac(
    uv: np.ndarray,
    pts_pc: np.ndarray,
    K: np.ndarray,
    reproj_px: float = 10.0,
    iterations: int = 50_000,
    min_matches: int = 8,
    confidence: float = 0.999,
    method: str = "iterative",
    workers: int = 1,
) -> PoseResult:
    """OpenCV ``solvePnPRansac`` on image pixels ``uv (K, 2)`` and cloud points ``pts_pc (K, 3)``.

    ``method`` picks the ``flags`` passed to OpenCV (``PNP_METHODS``):

    * ``"iterative"`` (the default: OpenCV's default and the official code's, i.e. the
      paper's solver), ``"epnp"``, ``"sqpnp"``: classic RANSAC on 5-point EPnP samples,
      the final model refined on its inliers with the named solver;
    * ``"ap3p"``: classic RANSAC on 4-point AP3P samples;
    * ``"usac"`` (``cv2.USAC_DEFAULT``) and ``"usac_accurate"`` (``cv2.USAC_ACCURATE``):
      OpenCV's USAC framework, the CPU speed-up.

    Why USAC: with this method's coarse matches (a median 11 % within 10 px) classic
    RANSAC's adaptive stop needs more than 50k 5-point samples, so ``"iterative"`` runs the
    whole cap at ~50 us a sample (seconds per call on a CPU). USAC draws 3-point P3P
    samples (hundreds to thousands suffice), rejects bad hypotheses early (SPRT), scores
    with MSAC and locally optimises each new best model (``"usac_accurate"``: graph-cut).
    It gets the same cap, threshold and confidence (OpenCV's ``usac/ransac_solvers.cpp``,
    ``setParameters``; checked on OpenCV 5.0.0 by varying each) and is deterministic. On 20
    synthetic pairs it is ~100x faster at the same recall with coarser poses; figures in
    ``benchmarks/README.md`` (``benchmarks/bench_pnp.py``).

    ``workers > 1`` splits the ``iterations`` over that many threads (:func:`_best_of_workers`):
    the same solver and as many hypotheses, other random samples, ~``workers`` x faster on as
    many free cores (``workers = 1``: exactly one OpenCV call).

    Too few usable matches, an OpenCV error or no model with 4 inliers give
    ``success=False`` with a reason, never an exception; an unknown ``method`` raises
    ``ValueError``. (USAC itself raises below 3 points and "succeeds" on exactly 3, so the
    ``min_matches`` guard answers first for every method.)
    """
    import cv2

    flags = PNP_METHODS.get(method)
    if flags is None:
        raise ValueError(f"unknown PnP method {method!r}; expected one of {sorted(PNP_METHODS)}")

    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    pts_pc = np.asarray(pts_pc, dtype=np.float64).reshape(-1, 3)
    if len(uv) != len(pts_pc):
        raise ValueError(f"uv has {len(uv)} rows but pts_pc has {len(pts_pc)}")
    rows = np.nonzero(_finite_rows(uv, pts_pc))[0]
    need = max(min_matches, 4)
    if len(rows) < need:
        return _failed("pnp", f"{len(rows)} usable matches (of {len(uv)}; usable: a finite pixel and 3D point), "
                              f"PnP-RANSAC needs at least {need}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    K = np.asarray(K, dtype=np.float64)

    def run(order: np.ndarray, iters: int):
        """One OpenCV RANSAC over the usable matches in ``order``: (ok, rvec, tvec, inliers as rows)."""
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            pts_pc[order], uv[order], K, None,
            iterationsCount=iters, reprojectionError=reproj_px, confidence=confidence, flags=flags,
        )
        return ok, rvec, tvec, None if inl is None else order[inl.reshape(-1)]

    try:
        if workers == 1:
            ok, rvec, tvec, inl = run(rows, iterations)
        else:
            ok, rvec, tvec, inl = _best_of_workers(run, rows, iterations, int(workers))
    except cv2.error as exc:
        return _failed("pnp", f"OpenCV refused the problem: {str(exc).strip().splitlines()[-1]}")
    if not ok or inl is None or len(inl) < 4:
        return _failed("pnp", "PnP-RANSAC found no model with at least 4 inliers")
    R, _ = cv2.Rodrigues(rvec)
    T = cameras.make_pose(R, tvec.reshape(3))
    return PoseResult(T, True, "pnp", "", inl, 1.0)


def _best_of_workers(run, rows: np.ndarray, iterations: int, workers: int):
    """``workers`` RANSAC runs of ``ceil(iterations / workers)`` samples each, in threads
    (OpenCV releases the GIL), and the model with the most inliers.

    OpenCV seeds its sampler the same way on every call, so each worker sees the matches in
    its own seeded order (worker 0: the original one) and draws other samples: together
    they rank as many hypotheses by consensus as one run of ``iterations`` would. Ties go
    to the lowest worker, so the answer is deterministic.
    """
    from concurrent.futures import ThreadPoolExecutor

    orders = [rows] + [rows[np.random.default_rng(w).permutation(len(rows))] for w in range(1, workers)]
    per_worker = -(-iterations // workers)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(lambda order: run(order, per_worker), orders))
    found = [r for r in results if r[0] and r[3] is not None]
    if not found:
        return results[0]
    return max(found, key=lambda r: len(r[3]))
