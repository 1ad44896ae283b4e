"""Pose solvers: Kabsch-RANSAC (Open3D 0.12's algorithm) on 3D-3D matches and PnP-RANSAC (OpenCV) on 2D-3D.

Both estimate ``T_cam_pc`` (point-cloud frame -> image camera) and return a
:class:`PoseResult`; too few or degenerate matches give ``success=False`` with a reason,
never an exception.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from freereg_lib.geometry import cameras


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


KABSCH_SCORINGS = ("official", "open3d")


def kabsch_ransac(
    pts_cam: np.ndarray,
    pts_pc: np.ndarray,
    inlier_m: float = 0.2,
    iterations: int = 50_000,
    ransac_n: int = 4,
    with_scale: bool = True,
    min_matches: int = 5,
    seed: int = 0,
    max_scale_ratio: float = 0.0,
    corres: np.ndarray | None = None,
    confidence: float = 1.0,
    scoring: str = "official",
) -> PoseResult:
    """Kabsch in RANSAC from image-side points ``pts_cam (N, 3)`` to cloud points ``pts_pc (M, 3)``.

    ``corres (K, 2) int`` pairs rows of ``pts_cam`` with rows of ``pts_pc`` (the matches);
    None means the two arrays are matched row by row. With ``with_scale`` the model is a
    similarity mapping the image side onto the cloud, which absorbs monocular depth's global
    scale error; the returned pose is its rigid part and ``scale`` the similarity's scale.
    ``inliers`` index ``corres``.

    ``scoring``:

    * ``"official"`` (the paper's): the algorithm of Open3D 0.12, the version the official
      code pins, of ``registration_ransac_based_on_correspondence`` (:func:`official_ransac`:
      ``ransac_n`` correspondences drawn uniformly with replacement, Umeyama's estimator,
      each hypothesis scored by the fraction of the matches within ``inlier_m``, ties to the
      lower inlier RMSE), then the official refinement (:func:`official_refinement`). Seeded
      NumPy, vectorised, byte-identical across processes.
    * ``"open3d"``: the same call under the installed Open3D (0.15 and later score each
      hypothesis by the nearest-neighbour fitness of the whole transformed image-side cloud
      against the target cloud, which with scaling rewards shrunken similarities), then the
      same refinement. Not the official behaviour; kept to measure the difference. It runs
      on one Open3D thread so that ``seed`` fixes the answer.

    ``max_scale_ratio > 0`` rejects minimal samples whose edge lengths differ by more than
    that ratio between the sides (Open3D's edge-length checker) and fails a final scale
    outside ``[1 / ratio, ratio]``; 0 (the official call) checks nothing. ``confidence < 1``
    stops early once that confidence of having drawn an all-inlier sample is reached (a
    speed-up; the official code never stops early).

    Departure, documented: when the refinement finds fewer than 4 inliers the official code
    returns the RANSAC similarity with its rotation block still scaled; here the pose is
    always the rigid part of the similarity. Its translation is the similarity's own in both,
    which is the right camera position: the scale acts about the image camera's centre.
    """
    if scoring not in KABSCH_SCORINGS:
        raise ValueError(f"unknown Kabsch-RANSAC scoring {scoring!r}; expected one of {KABSCH_SCORINGS}")
    if not 0.0 < confidence <= 1.0:
        raise ValueError(f"confidence must be in (0, 1], got {confidence}")
    pts_cam = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    pts_pc = np.asarray(pts_pc, dtype=np.float64).reshape(-1, 3)
    if corres is None:
        if len(pts_cam) != len(pts_pc):
            raise ValueError(f"pts_cam has {len(pts_cam)} rows but pts_pc has {len(pts_pc)}; "
                             "pass corres to pair rows of clouds of different sizes")
        corres = np.stack([np.arange(len(pts_cam))] * 2, axis=1)
    corres = np.asarray(corres, dtype=np.int64).reshape(-1, 2)
    if len(corres) and (corres.min() < 0 or corres[:, 0].max() >= len(pts_cam) or corres[:, 1].max() >= len(pts_pc)):
        raise ValueError(f"corres indexes rows outside pts_cam ({len(pts_cam)}) or pts_pc ({len(pts_pc)})")
    # Non-finite points (no monocular depth) leave both the clouds and the matches.
    fin_cam = np.all(np.isfinite(pts_cam), axis=1)
    fin_pc = np.all(np.isfinite(pts_pc), axis=1)
    usable = np.nonzero(fin_cam[corres[:, 0]] & fin_pc[corres[:, 1]])[0]
    need = max(min_matches, ransac_n, 3)
    if len(usable) < need:
        return _failed("kabsch", f"{len(usable)} usable matches (of {len(corres)}; usable: finite 3D points on both "
                                 f"sides), Kabsch-RANSAC needs at least {need}")
    src_m, tgt_m = pts_cam[corres[usable, 0]], pts_pc[corres[usable, 1]]
    if scoring == "official":
        M = official_ransac(src_m, tgt_m, inlier_m, iterations, ransac_n, with_scale, seed, max_scale_ratio,
                            confidence)
    else:
        new_cam = np.cumsum(fin_cam) - 1
        new_pc = np.cumsum(fin_pc) - 1
        pairs = np.stack([new_cam[corres[usable, 0]], new_pc[corres[usable, 1]]], axis=1)
        M = _open3d_ransac(pts_cam[fin_cam], pts_pc[fin_pc], pairs, inlier_m, iterations, ransac_n, with_scale,
                           seed, max_scale_ratio, confidence)
    M, inl = official_refinement(src_m, tgt_m, M, inlier_m, with_scale, rigid_rotation=False)
    if inl is None:
        resid = np.linalg.norm(src_m @ M[:3, :3].T + M[:3, 3] - tgt_m, axis=1)
        inl = np.nonzero(resid < inlier_m)[0]
    inliers = usable[inl]
    if not np.all(np.isfinite(M)) or np.linalg.det(M[:3, :3]) < 0:
        # The official refinement has no reflection guard; a reflection is no pose.
        return _failed("kabsch", f"the refined model is {'a reflection' if np.all(np.isfinite(M)) else 'not finite'} "
                                 f"({len(inliers)} inliers)")
    if len(inliers) < 3 or np.linalg.det(M[:3, :3]) <= 1e-12:
        return _failed("kabsch", f"RANSAC found a degenerate model ({len(inliers)} inliers)")
    T_pc_cam, scale = _split_similarity(M)
    if max_scale_ratio > 0 and not 1.0 / max_scale_ratio <= scale <= max_scale_ratio:
        return _failed("kabsch", f"the best model scales the image side by {scale:.2f}, beyond the allowed ratio "
                                 f"{max_scale_ratio:g}")
    return PoseResult(cameras.invert(T_pc_cam), True, "kabsch", "", inliers, scale)


def official_refine_stage(tgt_m: np.ndarray, src_m: np.ndarray, T: np.ndarray, weights: np.ndarray,
                          inlier_m: float, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray | None]:
    """One stage of the official refinement (``refiner.Refine_trans``): ``(s, T_new, overlap)``.

    The matches ``src_m (K, 3)`` -> ``tgt_m (K, 3)`` within ``inlier_m`` of ``T (4, 4)``
    (squared distance strictly below ``inlier_m**2``) are ``overlap (k,) int64``; with fewer
    than 4 the answer is ``(1.0, T, None)``. Otherwise a weighted Kabsch on them: centres
    weighted by ``weights / weights.sum()``; with ``with_scale`` the scale is the ratio of
    the standard deviations of the weighted, centred coordinates (all coordinates together,
    target over source), not Umeyama's; the rotation is ``U Vt`` of the SVD of
    ``tgt_c.T @ diag(w) @ (s src_c)`` with no reflection guard. ``T_new = [s R | c_t - s R c_s]``.
    """
    src_m = np.asarray(src_m, dtype=np.float64)
    tgt_m = np.asarray(tgt_m, dtype=np.float64)
    moved = src_m @ T[:3, :3].T + T[:3, 3]
    d2 = np.sum(np.square(tgt_m - moved), axis=-1)
    overlap = np.nonzero(d2 < inlier_m * inlier_m)[0]
    if len(overlap) < 4:
        return 1.0, np.array(T, dtype=np.float64, copy=True), None
    w = np.asarray(weights, dtype=np.float64)[overlap]
    w = w / w.sum()
    tgt, src = tgt_m[overlap], src_m[overlap]
    c_t, c_s = (tgt * w[:, None]).sum(axis=0), (src * w[:, None]).sum(axis=0)
    s = 1.0
    if with_scale:
        s = float(np.std((tgt - c_t) * w[:, None]) / np.std((src - c_s) * w[:, None]))
    src, c_s = src * s, c_s * s
    H = (tgt - c_t).T @ (w[:, None] * (src - c_s))
    U, _, Vt = np.linalg.svd(H)
    R = U @ Vt
    T_new = np.eye(4)
    T_new[:3, :3] = s * R
    T_new[:3, 3] = c_t - c_s @ R.T
    return s, T_new, overlap


def official_refinement(src_m: np.ndarray, tgt_m: np.ndarray, T0: np.ndarray, inlier_m: float, with_scale: bool,
                        rigid_rotation: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """The official refinement after RANSAC (``ransacor.run``): ``(T, inliers)``.

    Two stages of :func:`official_refine_stage` with unit weights, at ``2 * inlier_m`` then
    ``inlier_m``, starting from the RANSAC model ``T0 (4, 4)`` (image side -> cloud).
    ``inliers (k,) int64`` are the second stage's overlap (matches within ``inlier_m`` of the
    first stage's model), None when it had fewer than 4. With ``rigid_rotation`` (the
    official return) the rotation block is divided by the second stage's scale while the
    translation keeps the similarity's value; False returns the similarity itself.
    """
    ones = np.ones(len(src_m))
    _, T, _ = official_refine_stage(tgt_m, src_m, T0, ones, 2.0 * inlier_m, with_scale)
    s, T, inliers = official_refine_stage(tgt_m, src_m, T, ones, inlier_m, with_scale)
    if rigid_rotation:
        T = T.copy()
        T[:3, :3] = T[:3, :3] / (s if s > 0 else 1.0)
    return T, inliers


def official_ransac(src: np.ndarray, tgt: np.ndarray, inlier_m: float, iterations: int, ransac_n: int = 4,
                    with_scale: bool = True, seed: int = 0, max_scale_ratio: float = 0.0,
                    confidence: float = 1.0, batch: int = 256) -> np.ndarray:
    """Open3D 0.12's correspondence RANSAC on matched rows ``src (K, 3)`` -> ``tgt (K, 3)``.

    Each of ``iterations`` hypotheses is Umeyama's similarity (rigid without ``with_scale``)
    on ``ransac_n`` rows drawn uniformly with replacement from ``np.random.default_rng(seed)``.
    A hypothesis is better when more rows land strictly within ``inlier_m``, or as many with a
    lower inlier RMSE; one with no inlier never wins, so no inlier at all returns the
    identity, as Open3D does. ``confidence < 1`` stops early the way Open3D 0.12 does (the
    official call passes 1000: never). Hypotheses are scored ``batch`` at a time with one
    matrix product; the first best in draw order wins, so the answer does not depend on
    ``batch``. Returns the best ``(4, 4)`` model.
    """
    rng = np.random.default_rng(seed)
    K = len(src)
    best, best_count, best_rmse = np.eye(4), 0, 0.0
    done, stop = 0, int(iterations)
    iu = np.triu_indices(ransac_n, 1)
    src_t, tgt_t = np.ascontiguousarray(src.T), np.ascontiguousarray(tgt.T)
    max_d2 = inlier_m * inlier_m
    while done < stop:
        b = min(batch, stop - done)
        idx = rng.integers(0, K, size=(b, ransac_n))
        first = done
        done += b
        s_smp, t_smp = src[idx], tgt[idx]
        M = _umeyama(s_smp, t_smp, with_scale)
        ok = np.all(np.isfinite(M), axis=(1, 2))
        if max_scale_ratio > 0:
            ds = np.linalg.norm(s_smp[:, :, None] - s_smp[:, None, :], axis=-1)[:, iu[0], iu[1]]
            dt = np.linalg.norm(t_smp[:, :, None] - t_smp[:, None, :], axis=-1)[:, iu[0], iu[1]]
            sim = 1.0 / max_scale_ratio
            ok &= np.all((ds >= sim * dt) & (dt >= sim * ds), axis=1)
        rows = np.nonzero(ok)[0]
        if not len(rows):
            continue
        M = M[rows]
        # One GEMM for all hypotheses' rotations: (b * 3, 3) @ (3, K); an inner dimension of 3
        # is summed in one order whatever BLAS's threading, so the counts are reproducible.
        # Small batches updated in place stay in cache: the product is memory-bound.
        diff = (M[:, :3, :3].reshape(-1, 3) @ src_t).reshape(len(M), 3, K)
        diff += M[:, :3, 3:]
        diff -= tgt_t
        d2 = np.einsum("bik,bik->bk", diff, diff)
        inl = d2 < max_d2
        count = np.count_nonzero(inl, axis=1)
        top = int(count.max())
        if top == 0 or top < best_count:
            continue
        cand = np.nonzero(count == top)[0]
        rmse = np.sqrt(np.where(inl[cand], d2[cand], 0.0).sum(axis=1) / top)
        k = int(np.argmin(rmse))  # argmin keeps the first of equal RMSEs: draw order
        if top > best_count or rmse[k] < best_rmse:
            best, best_count, best_rmse = M[cand[k]], top, float(rmse[k])
            if confidence < 1.0:
                # Open3D 0.12 lowers its exit iteration when a hypothesis improves (per thread;
                # here in draw order), counted from the first iteration.
                fit = best_count / K
                with np.errstate(divide="ignore", invalid="ignore"):
                    exit_at = np.log(1.0 - confidence) / np.log(1.0 - fit ** ransac_n)
                if exit_at < stop:
                    stop = max(int(np.ceil(exit_at)), first + int(rows[cand[k]]) + 1)
    return best


def _open3d_ransac(src, tgt, pairs, inlier_m, iterations, ransac_n, with_scale, seed, max_scale_ratio,
                   confidence) -> np.ndarray:
    """The installed Open3D's correspondence RANSAC on one of its (TBB) threads; the 4 x 4 model
    (image side -> cloud). Open3D's parallel workers draw from one shared generator in a
    racy order, so one thread is what makes ``seed`` fix the answer."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    corres = o3d.utility.Vector2iVector(pairs.astype(np.int32))
    estimation = reg.TransformationEstimationPointToPoint(with_scaling=with_scale)
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(1.0 / max_scale_ratio)] if max_scale_ratio > 0 else []
    o3d.utility.random.seed(int(seed))
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        result = reg.registration_ransac_based_on_correspondence(
            source, target, corres, inlier_m, estimation, ransac_n, checkers,
            reg.RANSACConvergenceCriteria(int(iterations), float(confidence)),
        )
    finally:
        o3d.utility.set_max_threads(threads)
    return np.asarray(result.transformation).copy()


def _umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> np.ndarray:
    """Least-squares similarity (or rigid) ``(B, 4, 4)`` taking ``src (B, n, 3)`` onto ``dst (B, n, 3)``.

    Umeyama (1991) as Eigen's ``umeyama`` computes it, the estimator of Open3D's
    point-to-point estimation (reflections guarded). Degenerate samples (coincident points)
    give non-finite models.
    """
    mu_s, mu_d = src.mean(axis=1, keepdims=True), dst.mean(axis=1, keepdims=True)
    xs, xd = src - mu_s, dst - mu_d
    sigma = np.einsum("bni,bnj->bij", xd, xs) / src.shape[1]
    U, D, Vt = np.linalg.svd(sigma)
    S = np.ones((len(src), 3))
    S[:, 2] = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)
    R = np.einsum("bij,bj,bjk->bik", U, S, Vt)
    if with_scale:
        var_s = np.einsum("bni,bni->b", xs, xs) / src.shape[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("bi,bi->b", D, S) / var_s
    else:
        s = np.ones(len(src))
    M = np.zeros((len(src), 4, 4))
    M[:, :3, :3] = s[:, None, None] * R
    M[:, :3, 3] = mu_d[:, 0] - np.einsum("bij,bj->bi", M[:, :3, :3], mu_s[:, 0])
    M[:, 3, 3] = 1.0
    return M


def _pnp_methods() -> dict[str, int]:
    """``pnp_ransac``'s ``method`` names and the ``cv2.solvePnPRansac`` ``flags`` they pass.

    The USAC entries need OpenCV's USAC framework (OpenCV >= 4.5); an OpenCV without it
    lacks those names rather than failing at import.
    """

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

    ``workers > 1`` splits the ``iterations`` over that many threads (``_best_of_workers``):
    the same solver and as many hypotheses, other random samples, ~``workers`` x faster on as
    many free cores (``workers = 1``: exactly one OpenCV call).

    Too few usable matches, an OpenCV error or no model with 4 inliers give
    ``success=False`` with a reason, never an exception; an unknown ``method`` raises
    ``ValueError``. (USAC itself raises below 3 points and "succeeds" on exactly 3, so the
    ``min_matches`` guard answers first for every method.)
    """

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

    orders = [rows] + [rows[np.random.default_rng(w).permutation(len(rows))] for w in range(1, workers)]
    per_worker = -(-iterations // workers)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(lambda order: run(order, per_worker), orders))
    found = [r for r in results if r[0] and r[3] is not None]
    if not found:
        return results[0]
    return max(found, key=lambda r: len(r[3]))
