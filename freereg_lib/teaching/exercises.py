"""The exercises, their graded cases and the library reference each answer is compared with.

A case is a list of calls of the student's function: :attr:`Case.calls` draws their arguments
from the run's generator (:class:`Draw`: a new seed every grading run unless the teacher fixes
one), so no answer can be prepared in advance. The student's process only ever
sees these arguments and returns its answers as data; the grader computes
:attr:`Exercise.reference` on the same arguments in its own process and compares with
:attr:`Exercise.check`. This module runs no student code.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from freereg_lib import features
from freereg_lib.config import config_for
from freereg_lib.data import synthetic
from freereg_lib.features import matching
from freereg_lib.geometry import cameras, metrics, pose, projection


@dataclass
class Case:
    """One graded test: the argument tuples of its calls, drawn by :class:`Draw`."""

    name: str
    points: float
    calls: Callable[["Draw"], list[tuple]]


@dataclass
class Exercise:
    function: str   # the name the solution cell defines
    notebook: str   # the notebook's stem
    title: str
    teaches: str
    reference: Callable[..., Any]        # the right answer, from the library
    check: Callable[[Any, Any], None]    # check(got, want): raises AssertionError when wrong
    cases: list[Case] = field(default_factory=list)

    @property
    def max_points(self) -> float:
        return float(sum(c.points for c in self.cases))


EXERCISES: dict[str, Exercise] = {}


class Draw:
    """The run's draws for one case: a generator of its own and the run's room."""

    def __init__(self, seed: int, index: int):
        self.seed = int(seed)
        self.rng = np.random.default_rng([self.seed, index])

    def room(self):
        return _room_pair(self.seed % (2**31 - 1))


def _exercise(function: str, notebook: str, title: str, teaches: str, reference: Callable,
              check: Callable) -> None:
    EXERCISES[function] = Exercise(function, notebook, title, teaches, reference, check)


def _case(function: str, points: float, name: str):
    def register(calls: Callable[[Draw], list[tuple]]):
        EXERCISES[function].cases.append(Case(name, points, calls))
        return calls
    return register


def _assert_close(got: Any, want: Any, what: str, atol: float = 1e-9, rtol: float = 0.0) -> None:
    try:
        got = np.asarray(got, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise AssertionError(f"{what}: not numbers ({e})") from None
    want = np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, f"{what}: shape {got.shape}, expected {want.shape}"
    bad = ~np.isclose(got, want, atol=atol, rtol=rtol, equal_nan=True)
    if bad.any():
        at = tuple(int(i) for i in np.argwhere(bad)[0])
        raise AssertionError(f"{what}: {int(bad.sum())} of {bad.size} values differ, "
                             f"e.g. at {at}: {got[at]:.6g} instead of {want[at]:.6g}")


def _random_pose(rng: np.random.Generator, angle: float | None = None, t_scale: float = 1.0) -> np.ndarray:
    angle = rng.uniform(-np.pi, np.pi) if angle is None else angle
    return cameras.make_pose(cameras.rotation_about(rng.normal(size=3), angle), t_scale * rng.normal(size=3))


@functools.lru_cache(maxsize=2)
def _room_pair(seed: int):
    """A small synthetic indoor pair (60 x 80 pixels; well under a second)."""
    return synthetic.make_pair("indoor", seed=seed, image_size=(60, 80))


# --------------------------------------------------------------------------------------
# Render a point cloud into a depth map (00).

def _ref_depth(points, K, T, size):
    return projection.project_to_depth(points, K, T, size)[0]


_exercise(
    "student_project_to_depth", "00_preliminaries", "Render a point cloud into a depth map",
    "rigid transforms, the pinhole model, pixel rounding and z-buffering (the nearest point wins); "
    "this is how FreeReg turns the cloud into a depth image for ControlNet",
    _ref_depth, lambda got, want: _assert_close(got, want, "depth map"))


@_case("student_project_to_depth", 3, "the synthetic room seen by its depth camera")
def _(d: Draw):
    p = d.room()
    return [(p.points, p.K_depth, cameras.invert(p.T_pc_sensor), p.depth_size)]


@_case("student_project_to_depth", 3, "a random cloud from a random pose, non-square image")
def _(d: Draw):
    T = _random_pose(d.rng, t_scale=0.5)
    cam = np.c_[d.rng.uniform(-3, 3, (800, 2)), d.rng.uniform(-1, 6, 800)]  # some behind, some outside
    return [(cameras.transform(cameras.invert(T), cam), cameras.intrinsics(30.0, 32.0, 19.5, 14.5), T, (30, 40))]


@_case("student_project_to_depth", 2, "the nearest point wins on a shared pixel, in any order")
def _(d: Draw):
    rays = np.c_[d.rng.uniform(-0.3, 0.3, (40, 2)), np.ones(40)]
    points = np.concatenate([rays * z for z in (3.0, 1.5, 2.5, 0.8, 4.0)])  # five depths per ray
    return [(points[d.rng.permutation(len(points))], cameras.intrinsics(10.0, 10.0, 4.0, 3.0), np.eye(4), (7, 9))]


@_case("student_project_to_depth", 2, "points behind the sensor or off the image leave zeros")
def _(d: Draw):
    K = cameras.intrinsics(10.0, 10.0, 2.0, 2.0)
    toy = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.1, 0.0, 1.0],
                    [0.5, 0.5, -2.0], [5.0, 0.0, 1.0], [0.0, -5.0, 1.0]])
    behind = np.array([[0.0, 0.0, -1.0], [0.1, 0.1, -3.0]])
    return [(toy, K, np.eye(4), (5, 5)), (behind, K, np.eye(4), (5, 5))]


# --------------------------------------------------------------------------------------
# The inlier ratio (00).

def _ref_ir(*args) -> float:
    """The exercise's IR: the fraction of evaluable matches that are correct, 0 with fewer than 3
    evaluable (``few="zero"``; the library also offers the official tool's convention)."""
    return metrics.inlier_stats(*metrics.correct_matches(*args), few="zero")[0]


def _check_ir(got, want) -> None:
    assert np.ndim(got) == 0 and not isinstance(got, (tuple, list, dict, str)), \
        f"expected one number, got {type(got).__name__} of shape {np.shape(got)}"
    got = float(got)
    assert math.isclose(got, want, rel_tol=1e-9, abs_tol=1e-9), f"IR {got:.6g}, expected {want:.6g}"


_exercise(
    "student_inlier_ratio", "00_preliminaries", "The inlier ratio (IR) of one pair",
    "how a pixel-to-point match is judged correct: true depth, back-projection, the inverse pose, "
    "the tau_c threshold, and which matches can be evaluated at all",
    _ref_ir, _check_ir)


def _room_matches(d: Draw, n: int, noise: float = 0.02):
    """Pixels of the room pair and their true cloud points (plus noise), as matches."""
    p, rng = d.room(), d.rng
    H, W = p.depth_gt.shape
    v, u = np.nonzero(np.isfinite(p.depth_gt) & (p.depth_gt > 0.01) & (p.depth_gt < 10.0))
    pick = rng.choice(len(u), size=n, replace=False)
    uv = np.c_[u[pick], v[pick]] + rng.uniform(-0.45, 0.45, (n, 2))  # the nearest pixel stays the same
    uv = np.clip(uv, 0, [W - 1, H - 1])
    z = p.depth_gt[v[pick], u[pick]]
    pts = cameras.transform(cameras.invert(p.T_cam_pc), cameras.lift(uv, z, p.K_image))
    return p, uv, pts + rng.normal(scale=noise, size=pts.shape)


@_case("student_inlier_ratio", 2, "true matches of the synthetic room")
def _(d: Draw):
    p, uv, pts = _room_matches(d, 120)
    return [(uv, pts, p.depth_gt, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0))]


@_case("student_inlier_ratio", 3, "a third of the matches wrong")
def _(d: Draw):
    p, uv, pts = _room_matches(d, 150)
    wrong = d.rng.choice(len(pts), size=50, replace=False)
    pts[wrong] = pts[d.rng.permutation(wrong)] + d.rng.normal(scale=0.5, size=(50, 3))
    return [(uv, pts, p.depth_gt, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0))]


@_case("student_inlier_ratio", 2, "matches without a valid depth or with a NaN point are not evaluable")
def _(d: Draw):
    p, uv, pts = _room_matches(d, 100)
    depth = p.depth_gt.copy()
    pix = np.rint(uv).astype(int)
    depth[pix[:10, 1], pix[:10, 0]] = 0.0       # no measurement
    depth[pix[10:20, 1], pix[10:20, 0]] = 25.0  # beyond the depth range
    depth[pix[20:25, 1], pix[20:25, 0]] = np.nan
    pts[25:30] = np.nan
    pts[30:60] += d.rng.normal(scale=1.0, size=(30, 3))  # and some wrong matches
    return [(uv, pts, depth, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0))]


@_case("student_inlier_ratio", 1, "fewer than 3 evaluable matches give 0, three are enough")
def _(d: Draw):
    p, uv, pts = _room_matches(d, 5, noise=0.0)
    calls = []
    for n_evaluable in (2, 3):
        some = pts.copy()
        some[n_evaluable:] = np.nan
        calls.append((uv, some, p.depth_gt, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0)))
    return calls


@_case("student_inlier_ratio", 2, "another tau_c and depth range are honoured")
def _(d: Draw):
    p, uv, pts = _room_matches(d, 150, noise=0.04)
    return [(uv, pts, p.depth_gt, p.K_image, p.T_cam_pc, 0.06, (0.5, 2.5))]


# --------------------------------------------------------------------------------------
# Kabsch (02).

def _ref_kabsch(src, dst) -> np.ndarray:
    return pose._umeyama(np.asarray(src, float)[None], np.asarray(dst, float)[None], False)[0]


def _check_pose(got, want) -> None:
    got = np.asarray(got, dtype=np.float64)
    assert got.shape == (4, 4), f"expected a 4 x 4 transform, got shape {got.shape}"
    _assert_close(got[3], np.asarray(want)[3], "last row of the transform")  # [0, 0, 0, 1]
    _assert_close(got, want, "transform", atol=1e-6)


_exercise(
    "student_kabsch", "02_geometric_features", "The Kabsch algorithm",
    "the closed-form least-squares rigid fit of two matched point sets (centring, SVD of the "
    "cross-covariance, the reflection fix); the solver inside FreeReg's Kabsch-RANSAC",
    _ref_kabsch, _check_pose)


@_case("student_kabsch", 3, "a known pose on random points")
def _(d: Draw):
    src = d.rng.normal(size=(60, 3))
    return [(src, cameras.transform(_random_pose(d.rng), src))]


@_case("student_kabsch", 3, "planar point sets (need the reflection fix)")
def _(d: Draw):
    calls, reflected = [], 0  # without the fix about half come out reflected: keep drawing until three do
    while len(calls) < 6 or reflected < 3:
        src = np.c_[d.rng.normal(size=(50, 2)), np.zeros(50)]
        dst = cameras.transform(_random_pose(d.rng, angle=2.0), src)
        U, _, Vt = np.linalg.svd((src - src.mean(0)).T @ (dst - dst.mean(0)))
        if np.linalg.det(Vt.T @ U.T) < 0 or len(calls) < 6 - (3 - reflected):
            calls.append((src, dst))
            reflected += np.linalg.det(Vt.T @ U.T) < 0
    return calls


@_case("student_kabsch", 2, "noisy matches: the least-squares fit")
def _(d: Draw):
    src = d.rng.normal(size=(80, 3)) * [2.0, 1.0, 0.5]
    return [(src, cameras.transform(_random_pose(d.rng), src) + d.rng.normal(scale=0.05, size=(80, 3)))]


@_case("student_kabsch", 2, "a near half-turn, a far translation, four points")
def _(d: Draw):
    T = cameras.make_pose(cameras.rotation_about(d.rng.normal(size=3), 3.1), [120.0, -45.0, 30.0])
    src = d.rng.normal(size=(4, 3))
    return [(src, cameras.transform(T, src))]


# --------------------------------------------------------------------------------------
# Mutual nearest neighbours (03).

def _ref_mnn(fa, fb):
    return matching.mutual_nn(fa, fb)


def _check_mnn(got, want) -> None:
    assert isinstance(got, (tuple, list)) and len(got) == 2, "expected a pair (idx_a, idx_b)"
    ia, ib = (np.asarray(g).reshape(-1) for g in got)
    ra, rb = want
    assert len(ia) == len(ib), f"idx_a has {len(ia)} entries but idx_b {len(ib)}"
    assert len(ia) == len(ra), f"{len(ia)} mutual pairs, expected {len(ra)}"
    assert np.array_equal(ia, ra), "idx_a differs from the reference (is it sorted?)"
    assert np.array_equal(ib, rb), "idx_b differs from the reference"


_exercise(
    "student_mutual_nn", "03_fusion", "Mutual nearest neighbours",
    "descriptor matching: all pairwise distances with one matrix product, nearest neighbours "
    "both ways, and the mutual check that turns features into pixel-to-point matches",
    _ref_mnn, _check_mnn)


@_case("student_mutual_nn", 4, "random descriptors, 200 x 16 against 150 x 16")
def _(d: Draw):
    return [(d.rng.standard_normal((200, 16)), d.rng.standard_normal((150, 16)))]


@_case("student_mutual_nn", 3, "a shuffled, slightly noisy copy: every row matches")
def _(d: Draw):
    fa = d.rng.standard_normal((120, 8))
    return [(fa, fa[d.rng.permutation(120)] + d.rng.normal(scale=0.01, size=(120, 8)))]


@_case("student_mutual_nn", 3, "few rows against many, three channels")
def _(d: Draw):
    return [(d.rng.uniform(size=(30, 3)), d.rng.uniform(size=(90, 3)))]


# --------------------------------------------------------------------------------------
# The fusion (03).

def _ref_fuse(f_d, f_g, w):
    return features.fuse(f_d, f_g, w)


_exercise(
    "student_fuse", "03_fusion", "Fusing diffusion and geometric features",
    "FreeReg's feature fusion: per-row L2 normalisation, the weight w between the two modalities, "
    "and why the fused width stays the same at w = 0 and w = 1",
    _ref_fuse, lambda got, want: _assert_close(got, want, "fused features", atol=1e-6, rtol=1e-4))


@_case("student_fuse", 3, "w = 0.5 on features of different widths")
def _(d: Draw):
    return [(d.rng.normal(size=(40, 12)) * 5.0, d.rng.normal(size=(40, 32)) * 0.1, 0.5)]


@_case("student_fuse", 2, "the ends w = 0 and w = 1 keep the full width")
def _(d: Draw):
    f_d, f_g = d.rng.normal(size=(25, 6)), d.rng.normal(size=(25, 10))
    return [(f_d, f_g, 0.0), (f_d, f_g, 1.0)]


@_case("student_fuse", 2, "zero rows stay zero")
def _(d: Draw):
    f_d, f_g = d.rng.normal(size=(10, 4)), d.rng.normal(size=(10, 5))
    f_g[[1, 4, 7]] = 0.0
    f_d[4] = 0.0
    return [(f_d, f_g, 0.5)]


@_case("student_fuse", 3, "several weights on float32 features")
def _(d: Draw):
    f_d = d.rng.normal(size=(30, 16)).astype(np.float32)
    f_g = d.rng.uniform(size=(30, 33)).astype(np.float32)
    return [(f_d, f_g, w) for w in (0.3, 0.7, 0.9)]


# --------------------------------------------------------------------------------------
# Registration recall over a ladder (04).

def _ref_rr(re, te, ladder) -> list[float]:
    re_a, te_a = np.asarray(re, dtype=np.float64), np.asarray(te, dtype=np.float64)
    rows = [{"IR": 0.0, "IN": 0, "RE": a, "TE": b} for a, b in zip(re_a, te_a)]
    agg = metrics.aggregate(rows, ladder=tuple(tuple(r) for r in ladder))
    return [agg[f"RR@{deg:g}deg/{m:g}m"] for deg, m in ladder]


_exercise(
    "student_registration_recall", "04_benchmark", "Registration recall over a threshold ladder",
    "how RR is counted: both thresholds strict, and a pair without a pose (NaN errors) "
    "is a failure that still counts in the total",
    _ref_rr, lambda got, want: _assert_close(np.asarray(got, dtype=np.float64).reshape(-1), want,
                                             "RR per rung (%)"))


@_case("student_registration_recall", 4, "the paper's indoor ladder, some pairs without a pose")
def _(d: Draw):
    cfg = config_for("synthetic_indoor")
    re, te = d.rng.exponential(8.0, 40), d.rng.exponential(0.3, 40)
    gone = d.rng.choice(40, size=3, replace=False)
    re[gone] = te[gone] = np.nan
    return [(re, te, [*map(tuple, cfg.rr_ladder), (cfg.rr_rot_deg, cfg.rr_trans_m)])]


@_case("student_registration_recall", 2, "failed pairs count in the total")
def _(d: Draw):
    nan = np.nan
    return [(np.array([1.0, nan, 2.0, nan]), np.array([0.1, nan, 0.05, nan]), [(5.0, 0.2), (20.0, 1.0)]),
            (np.full(5, np.nan), np.full(5, np.nan), [(5.0, 0.2)])]


@_case("student_registration_recall", 2, "both thresholds are strict")
def _(d: Draw):
    re = np.array([5.0, 4.9, 5.0, 1.0, 0.0])
    te = np.array([0.1, 0.2, 0.2, 0.19999, 0.3])
    return [(re, te, [(5.0, 0.2), (5.0, 0.3), (10.0, 1.0)])]


@_case("student_registration_recall", 2, "plain lists, integer errors and a strided view as input")
def _(d: Draw):
    re, te = d.rng.exponential(10.0, 24), d.rng.exponential(0.5, 24)
    re[5] = te[5] = np.nan
    return [(re[::2], te[::2], [(10.0, 0.5), (20.0, 1.0)]),
            ([float(x) for x in re], [float(x) for x in te], [(3.0, 0.1)]),
            (np.rint(re[6:12]).astype(np.int64), te[6:12], [(10, 1)])]


# --------------------------------------------------------------------------------------
# For the notebooks and the guide.

def points(x: float) -> str:
    return f"{x:g}"


def exercise_table() -> str:
    """The exercises as a Markdown table (notebook, function, points, what it teaches)."""
    lines = ["| notebook | function | points | teaches |", "|---|---|---|---|"]
    for e in EXERCISES.values():
        lines.append(f"| {e.notebook} | `{e.function}` | {points(e.max_points)} | {e.teaches} |")
    return "\n".join(lines)
