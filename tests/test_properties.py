"""Property-based tests (hypothesis): over random rigid poses and random synthetic scenes the
solvers recover the pose from clean ground-truth matches, poses and pairs pass validation,
and the dataset metrics stay within [0, 100].

Examples are derandomized (the same ones on every run) and few, so the file runs in seconds.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from freereg_lib.data import synthetic
from freereg_lib.geometry import cameras, keypoints, metrics, pose

FAST = settings(max_examples=12, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])

unit = st.floats(-1.0, 1.0, allow_nan=False)
axes = st.tuples(unit, unit, unit).filter(lambda a: np.linalg.norm(a) > 1e-3)
angles = st.floats(-math.pi, math.pi, allow_nan=False)
translations = st.tuples(*[st.floats(-20.0, 20.0, allow_nan=False)] * 3)


@st.composite
def rigid_poses(draw) -> np.ndarray:
    return cameras.make_pose(cameras.rotation_about(np.array(draw(axes)), draw(angles)), np.array(draw(translations)))


@functools.lru_cache(maxsize=None)
def _scene(kind: str, seed: int):
    size = (120, 160) if kind == "indoor" else (64, 208)
    return synthetic.make_pair(kind, seed=seed, image_size=size)


@given(T=rigid_poses())
@FAST
def test_rigid_poses_pass_and_scaled_or_reflected_ones_do_not(T):
    np.testing.assert_array_equal(cameras.check_pose(T, "T"), T)
    assert cameras.is_rigid(cameras.invert(T))
    for bad in (T @ np.diag([1.0, 1.0, -1.0, 1.0]), T @ np.diag([1.3, 1.3, 1.3, 1.0])):
        with pytest.raises(ValueError, match="T is not a rigid transform"):
            cameras.check_pose(bad, "T")


@given(kind=st.sampled_from(["indoor", "outdoor"]), seed=st.integers(0, 40), T_new_pc=rigid_poses(),
       with_scale=st.booleans())
@FAST
def test_solvers_recover_the_pose_from_true_matches(kind, seed, T_new_pc, with_scale):
    """Move the scene's cloud frame by a random rigid pose; Kabsch and PnP on the true
    correspondences of a keypoint grid give the moved ground truth back."""
    pair = _scene(kind, seed)
    T_cam_new = pair.T_cam_pc @ cameras.invert(T_new_pc)
    moved = pair.__class__(**{**pair.__dict__, "points": cameras.transform(T_new_pc, pair.points),
                              "T_pc_sensor": T_new_pc @ pair.T_pc_sensor, "T_cam_pc": T_cam_new})
    moved.validate()  # a rigidly moved pair is still a valid pair
    uv = keypoints.grid_keypoints(pair.image_size, (8, 10))
    pts_cam, pts_new, keep = metrics.true_correspondences(uv, pair.depth_gt, pair.K_image, T_cam_new)
    assert len(keep) >= 12
    np.testing.assert_allclose(cameras.transform(T_cam_new, pts_new), pts_cam, atol=1e-9)

    kab = pose.kabsch_ransac(pts_cam, pts_new, inlier_m=0.01, iterations=200, with_scale=with_scale)
    pnp = pose.pnp_ransac(np.rint(uv[keep]), pts_new, pair.K_image, reproj_px=1.0, iterations=200)
    for res in (kab, pnp):
        assert res.success, res.reason
        re, te = metrics.pose_errors(res.T_cam_pc, T_cam_new)
        assert re < 1e-3 and te < 1e-3, (res.solver, re, te)
        assert cameras.is_rigid(res.T_cam_pc)
    assert kab.n_inliers == len(keep) and abs(kab.scale - 1.0) < 1e-6


maybe_nan = lambda hi: st.one_of(st.just(math.nan), st.floats(0.0, hi, allow_nan=False))  # noqa: E731


@st.composite
def result_rows(draw) -> list[dict]:
    n = draw(st.integers(0, 25))
    return [{"pair": f"p{k}", "IR": draw(st.floats(0.0, 1.0)), "IN": draw(st.integers(0, 2000)),
             "RE": draw(maybe_nan(180.0)), "TE": draw(maybe_nan(100.0))} for k in range(n)]


@given(rows=result_rows(), rot=st.floats(0.1, 45.0), trans=st.floats(0.01, 10.0), fmr=st.floats(0.0, 0.5))
@settings(max_examples=60, deadline=None, derandomize=True, database=None)
def test_aggregate_stays_within_0_and_100(rows, rot, trans, fmr):
    ladder = ((5.0, 0.1), (rot, trans))
    agg = metrics.aggregate(rows, rot, trans, fmr, ladder)
    assert agg["n_pairs"] == len(rows)
    if not rows:
        assert all(math.isnan(agg[k]) for k in ("FMR", "IR", "RR")) and agg["n_failed"] == 0
        return
    for key in ("FMR", "IR", "RR", "RR@5deg/0.1m", f"RR@{rot:g}deg/{trans:g}m"):
        assert 0.0 <= agg[key] <= 100.0, (key, agg[key])
    assert agg[f"RR@{rot:g}deg/{trans:g}m"] == agg["RR"]
    registered = sum(metrics.registered(r["RE"], r["TE"], rot, trans) for r in rows)
    assert agg["RR"] == pytest.approx(100.0 * registered / len(rows))
    assert 0 <= agg["n_failed"] <= len(rows) and registered <= len(rows) - agg["n_failed"]
    assert agg["IN"] >= 0 and (math.isnan(agg["RE"]) or 0.0 <= agg["RE"] <= 180.0)
