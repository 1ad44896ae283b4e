"""Course assignments from the notebooks: student versions and an autograder.

The notebooks mark their exercises: a code cell tagged ``solution`` defines one or more
functions named ``student_<thing>``, and the cell tagged ``check`` after it compares them
with the library. From that:

* ``python -m freereg_lib.assignments make [--out assignments/student] [--key DIR]`` writes a
  student version of every notebook: each ``solution`` cell keeps its functions' signatures
  and docstrings and gets the body ``raise NotImplementedError("<hint>")``; ``check`` cells
  stay as they are (students run them to test themselves); outputs are stripped. The
  original notebooks are the answer key (``--key DIR`` also writes a stripped copy of them).
* ``python -m freereg_lib.assignments grade <notebook-or-folder> [...]`` reads each
  student's functions out of their notebook(s) (it runs only the ``solution`` cells, in a
  namespace that holds ``numpy as np``, the notebook's own imports and the ``freereg_lib``
  modules), runs them against the library on small seeded synthetic cases, each worth points,
  and prints a score table. A stub, a crash, a wrong answer or a time-out costs that case's
  points, never the run: the exit code is 0.

Each student (each path given to ``grade``) is graded in a process of its own with a hard
time limit (``--limit``), so a student whose code hangs, catches the time-out or calls
``os._exit`` costs only their own grade; results are printed, and written to ``--json``,
as each student finishes. The library's reference functions are guarded: a solution that
replaces one (monkeypatching) or just calls the reference of its exercise scores zero for
that exercise, with a message. Grading still runs the students' code: do it in a container
or a throw-away account, as with any autograder. The exercises and their cases are the ``EXERCISES``
registry below; ``assignments/README.md`` is the teacher's guide.
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import copy
import functools
import io
import json
import math
import pkgutil
import re
import os
import signal
import subprocess
import sys
import tempfile
import time
import threading
import tokenize
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
DEFAULT_OUT = ROOT / "assignments" / "student"
SOLUTION_TAG = "solution"
CHECK_TAG = "check"
METADATA_KEY = "freereg_assignment"
BANNER_ID = "assignment-banner"
CASE_TIMEOUT_S = 30.0
STUDENT_LIMIT_S = 600.0  # hard wall-clock limit of one student's grading process


# --------------------------------------------------------------------------------------
# The exercises and their graded cases.

@dataclass
class Case:
    """One graded test: ``run(f)`` calls the student's function and raises if it is wrong."""

    name: str
    points: float
    run: Callable[[Callable], None]


@dataclass
class Exercise:
    function: str   # the name the solution cell defines
    notebook: str   # the notebook's stem
    title: str
    teaches: str
    cases: list[Case] = field(default_factory=list)
    refs: tuple[str, ...] = ()  # "module.function" of the library's reference: calling it scores 0

    @property
    def max_points(self) -> float:
        return float(sum(c.points for c in self.cases))


EXERCISES: dict[str, Exercise] = {}


def _exercise(function: str, notebook: str, title: str, teaches: str, refs: tuple[str, ...] = ()) -> None:
    EXERCISES[function] = Exercise(function, notebook, title, teaches, refs=refs)


def _case(function: str, points: float, name: str):
    def register(run: Callable[[Callable], None]):
        EXERCISES[function].cases.append(Case(name, points, run))
        return run
    return register


def _copy(x: Any) -> Any:
    return x.copy() if isinstance(x, np.ndarray) else copy.deepcopy(x)


_student_timeout: list[float | None] = [None]  # seconds per call of a student's function, set by the grader
_current_refs: list[tuple[str, ...]] = [()]  # the exercise being graded: its reference functions


class ReferenceUsed(Exception):
    """The student's function called the library's reference of its own exercise."""


class ReferenceChanged(Exception):
    """The student's code replaced a library function (monkeypatching the reference)."""


def _ref_function(dotted: str):
    import importlib

    module, name = dotted.rsplit(".", 1)
    return getattr(importlib.import_module(f"freereg_lib.{module}"), name)


def _call(f: Callable, *args: Any) -> Any:
    """The student's function on copies of the arguments (so it cannot alter the reference's).

    Only this call is timed: the reference and its imports do not count against the student.
    While it runs, a profile hook watches for a call of the exercise's reference function;
    after it, the library and NumPy are checked for replaced functions (:class:`Guard`).
    """
    args = tuple(_copy(a) for a in args)
    codes = {}
    for dotted in _current_refs[0]:
        fn = _GUARD.original(dotted) if _GUARD else _ref_function(dotted)
        codes[fn.__code__] = dotted
    used: list[str] = []

    def watch(frame, event, arg):
        if event == "call" and frame.f_code in codes:
            used.append(codes[frame.f_code])

    previous = sys.getprofile()
    sys.setprofile(watch if codes else previous)
    try:
        with _time_limit(_student_timeout[0]):
            out = f(*args)
    finally:
        sys.setprofile(previous)
        if _GUARD:
            _GUARD.check()
    if used:
        raise ReferenceUsed(f"it calls the library's reference freereg_lib.{used[0]}; write the exercise "
                            "yourself (this exercise scores 0)")
    return out


class Guard:
    """Every function of the ``freereg_lib`` modules of the references, of NumPy (top level and ``testing``) and
    of ``math``, with its code object, as they were before any student code ran.

    :meth:`check` raises :class:`ReferenceChanged` naming what a student replaced (a module
    attribute or a function's ``__code__``), after putting the originals back.
    """

    def __init__(self):
        import importlib

        self.modules = [np, np.testing, np.linalg, math]
        # The modules of the references and what they call (not every module: torch is slow to import).
        names = sorted({r.split(".")[0] for e in EXERCISES.values() for r in e.refs} | {"cameras"})
        for name in names:
            self.modules.append(importlib.import_module(f"freereg_lib.{name}"))
        self.saved = {}
        for module in self.modules:
            for name, value in list(vars(module).items()):
                if callable(value) and not name.startswith("__"):
                    self.saved[(module.__name__, name)] = (module, value, getattr(value, "__code__", None))

    def original(self, dotted: str):
        module, name = dotted.rsplit(".", 1)
        return self.saved[(f"freereg_lib.{module}", name)][1]

    def check(self) -> None:
        changed = []
        for (mod_name, name), (module, value, code) in self.saved.items():
            now = vars(module).get(name)
            if now is not value:
                changed.append(f"{mod_name}.{name}")
                setattr(module, name, value)
            elif code is not None and getattr(value, "__code__", None) is not code:
                changed.append(f"{mod_name}.{name}.__code__")
                value.__code__ = code
        if changed:
            raise ReferenceChanged(f"the code replaced {', '.join(sorted(changed)[:3])} (monkeypatching the "
                                   "library or NumPy the grader checks against); this exercise scores 0")


_GUARD: Guard | None = None


def _assert_close(got: Any, want: np.ndarray, what: str, atol: float = 1e-9, rtol: float = 0.0) -> None:
    got = np.asarray(got, dtype=np.float64)
    want = np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, f"{what}: shape {got.shape}, expected {want.shape}"
    bad = ~np.isclose(got, want, atol=atol, rtol=rtol, equal_nan=True)
    if bad.any():
        at = tuple(int(i) for i in np.argwhere(bad)[0])
        raise AssertionError(f"{what}: {int(bad.sum())} of {bad.size} values differ, "
                             f"e.g. at {at}: {got[at]:.6g} instead of {want[at]:.6g}")


def _random_pose(rng: np.random.Generator, angle: float | None = None, t_scale: float = 1.0) -> np.ndarray:
    from . import cameras

    angle = rng.uniform(-np.pi, np.pi) if angle is None else angle
    return cameras.make_pose(cameras.rotation_about(rng.normal(size=3), angle), t_scale * rng.normal(size=3))


@functools.lru_cache(maxsize=1)
def _room_pair():
    """A small synthetic indoor pair (60 x 80 pixels; well under a second)."""
    from . import synthetic

    return synthetic.make_pair("indoor", seed=7, image_size=(60, 80))


# Exercise: render a point cloud into a depth map (00).
_exercise(
    "student_project_to_depth", "00_preliminaries", "Render a point cloud into a depth map",
    "rigid transforms, the pinhole model, pixel rounding and z-buffering (the nearest point wins); "
    "this is how FreeReg turns the cloud into a depth image for ControlNet",
    refs=("projection.project_to_depth",),
)


def _ref_depth(points, K, T, size):
    from . import projection

    return projection.project_to_depth(points, K, T, size)[0]


@_case("student_project_to_depth", 3, "the synthetic room seen by its depth camera")
def _(f):
    from . import cameras

    p = _room_pair()
    args = (p.points, p.K_depth, cameras.invert(p.T_pc_sensor), p.depth_size)
    _assert_close(_call(f, *args), _ref_depth(*args), "depth map")


@_case("student_project_to_depth", 3, "a random cloud from a random pose, non-square image")
def _(f):
    from . import cameras

    rng = np.random.default_rng(11)
    T = _random_pose(rng, t_scale=0.5)
    cam = np.c_[rng.uniform(-3, 3, (800, 2)), rng.uniform(-1, 6, 800)]  # some behind, some outside
    points = cameras.transform(cameras.invert(T), cam)
    args = (points, cameras.intrinsics(30.0, 32.0, 19.5, 14.5), T, (30, 40))
    _assert_close(_call(f, *args), _ref_depth(*args), "depth map")


@_case("student_project_to_depth", 2, "the nearest point wins on a shared pixel, in any order")
def _(f):
    from . import cameras

    rng = np.random.default_rng(12)
    K = cameras.intrinsics(10.0, 10.0, 4.0, 3.0)
    rays = np.c_[rng.uniform(-0.3, 0.3, (40, 2)), np.ones(40)]
    points = np.concatenate([rays * d for d in (3.0, 1.5, 2.5, 0.8, 4.0)])  # five depths per ray
    points = points[rng.permutation(len(points))]
    args = (points, K, np.eye(4), (7, 9))
    _assert_close(_call(f, *args), _ref_depth(*args), "depth map")


@_case("student_project_to_depth", 2, "points behind the sensor or off the image leave zeros")
def _(f):
    from . import cameras

    K = cameras.intrinsics(10.0, 10.0, 2.0, 2.0)
    toy = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.1, 0.0, 1.0],
                    [0.5, 0.5, -2.0], [5.0, 0.0, 1.0], [0.0, -5.0, 1.0]])
    args = (toy, K, np.eye(4), (5, 5))
    _assert_close(_call(f, *args), _ref_depth(*args), "depth map")
    behind = np.array([[0.0, 0.0, -1.0], [0.1, 0.1, -3.0]])
    _assert_close(_call(f, behind, K, np.eye(4), (5, 5)), np.zeros((5, 5)), "all points behind the sensor")


# Exercise: the inlier ratio (00).
_exercise(
    "student_inlier_ratio", "00_preliminaries", "The inlier ratio (IR) of one pair",
    "how a pixel-to-point match is judged correct: true depth, back-projection, the inverse pose, "
    "the tau_c threshold, and which matches can be evaluated at all",
    refs=("metrics.correct_matches", "metrics.inlier_stats"),
)


def _ref_ir(*args) -> float:
    from . import metrics

    return metrics.inlier_stats(*metrics.correct_matches(*args))[0]


def _room_matches(rng: np.random.Generator, n: int, noise: float = 0.02):
    """Pixels of the room pair and their true cloud points (plus noise), as matches."""
    from . import cameras

    p = _room_pair()
    H, W = p.depth_gt.shape
    v, u = np.nonzero(np.isfinite(p.depth_gt) & (p.depth_gt > 0.01) & (p.depth_gt < 10.0))
    pick = rng.choice(len(u), size=n, replace=False)
    uv = np.c_[u[pick], v[pick]] + rng.uniform(-0.45, 0.45, (n, 2))  # the nearest pixel stays the same
    uv = np.clip(uv, 0, [W - 1, H - 1])
    z = p.depth_gt[v[pick], u[pick]]
    pts = cameras.transform(cameras.invert(p.T_cam_pc), cameras.lift(uv, z, p.K_image))
    return p, uv, pts + rng.normal(scale=noise, size=pts.shape)


def _check_ir(f, args) -> None:
    got, want = _call(f, *args), _ref_ir(*args)
    assert np.isscalar(got) or np.ndim(got) == 0, f"expected one number, got {type(got).__name__} {np.shape(got)}"
    assert math.isclose(float(got), want, rel_tol=1e-9, abs_tol=1e-9), f"IR {float(got):.6g}, expected {want:.6g}"


@_case("student_inlier_ratio", 2, "true matches of the synthetic room")
def _(f):
    p, uv, pts = _room_matches(np.random.default_rng(21), 120)
    _check_ir(f, (uv, pts, p.depth_gt, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0)))


@_case("student_inlier_ratio", 3, "a third of the matches wrong")
def _(f):
    rng = np.random.default_rng(22)
    p, uv, pts = _room_matches(rng, 150)
    wrong = rng.choice(len(pts), size=50, replace=False)
    pts[wrong] = pts[rng.permutation(wrong)] + rng.normal(scale=0.5, size=(50, 3))
    _check_ir(f, (uv, pts, p.depth_gt, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0)))


@_case("student_inlier_ratio", 2, "matches without a valid depth or with a NaN point are not evaluable")
def _(f):
    rng = np.random.default_rng(23)
    p, uv, pts = _room_matches(rng, 100)
    depth = p.depth_gt.copy()
    pix = np.rint(uv).astype(int)
    depth[pix[:10, 1], pix[:10, 0]] = 0.0       # no measurement
    depth[pix[10:20, 1], pix[10:20, 0]] = 25.0  # beyond the depth range
    depth[pix[20:25, 1], pix[20:25, 0]] = np.nan
    pts[25:30] = np.nan
    pts[30:60] += rng.normal(scale=1.0, size=(30, 3))  # and some wrong matches
    _check_ir(f, (uv, pts, depth, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0)))


@_case("student_inlier_ratio", 1, "fewer than 3 evaluable matches give 0, three are enough")
def _(f):
    p, uv, pts = _room_matches(np.random.default_rng(24), 5, noise=0.0)
    for n_evaluable in (2, 3):
        some = pts.copy()
        some[n_evaluable:] = np.nan
        _check_ir(f, (uv, some, p.depth_gt, p.K_image, p.T_cam_pc, 0.3, (0.01, 10.0)))


@_case("student_inlier_ratio", 2, "another tau_c and depth range are honoured")
def _(f):
    p, uv, pts = _room_matches(np.random.default_rng(25), 150, noise=0.04)
    _check_ir(f, (uv, pts, p.depth_gt, p.K_image, p.T_cam_pc, 0.06, (0.5, 2.5)))


# Exercise: Kabsch (02).
_exercise(
    "student_kabsch", "02_geometric_features", "The Kabsch algorithm",
    "the closed-form least-squares rigid fit of two matched point sets (centring, SVD of the "
    "cross-covariance, the reflection fix); the solver inside FreeReg's Kabsch-RANSAC",
    refs=("pose.kabsch_ransac", "pose._umeyama"),
)


def _check_pose(f, src, dst, want, atol=1e-6) -> None:
    got = np.asarray(_call(f, src, dst), dtype=np.float64)
    assert got.shape == (4, 4), f"expected a 4 x 4 transform, got shape {got.shape}"
    _assert_close(got[3], [0, 0, 0, 1], "last row of the transform")
    _assert_close(got, want, "transform", atol=atol)


@_case("student_kabsch", 3, "a known pose on random points")
def _(f):
    from . import cameras

    rng = np.random.default_rng(31)
    T = _random_pose(rng)
    src = rng.normal(size=(60, 3))
    _check_pose(f, src, cameras.transform(T, src), T)


@_case("student_kabsch", 3, "a planar point set (needs the reflection fix)")
def _(f):
    from . import cameras

    rng = np.random.default_rng(32)
    T = _random_pose(rng, angle=2.0)
    src = np.c_[rng.normal(size=(50, 2)), np.zeros(50)]
    _check_pose(f, src, cameras.transform(T, src), T)


@_case("student_kabsch", 2, "noisy matches: the least-squares fit")
def _(f):
    from . import cameras, pose

    rng = np.random.default_rng(33)
    T = _random_pose(rng)
    src = rng.normal(size=(80, 3)) * [2.0, 1.0, 0.5]
    dst = cameras.transform(T, src) + rng.normal(scale=0.05, size=(80, 3))
    # With a huge inlier distance every match is an inlier and the refit is plain Kabsch.
    ref = pose.kabsch_ransac(src, dst, inlier_m=1e3, iterations=50, with_scale=False, seed=0)
    assert ref.success, ref
    _check_pose(f, src, dst, cameras.invert(ref.T_cam_pc))


@_case("student_kabsch", 2, "a near half-turn, a far translation, four points")
def _(f):
    from . import cameras

    rng = np.random.default_rng(34)
    T = cameras.make_pose(cameras.rotation_about(rng.normal(size=3), 3.1), [120.0, -45.0, 30.0])
    src = rng.normal(size=(4, 3))
    _check_pose(f, src, cameras.transform(T, src), T)


# Exercise: mutual nearest neighbours (03).
_exercise(
    "student_mutual_nn", "03_fusion", "Mutual nearest neighbours",
    "descriptor matching: all pairwise distances with one matrix product, nearest neighbours "
    "both ways, and the mutual check that turns features into pixel-to-point matches",
    refs=("matching.mutual_nn",),
)


def _check_mnn(f, fa, fb) -> None:
    from . import matching

    got = _call(f, fa, fb)
    assert isinstance(got, (tuple, list)) and len(got) == 2, "expected a pair (idx_a, idx_b)"
    ia, ib = (np.asarray(g).reshape(-1) for g in got)
    ra, rb = matching.mutual_nn(fa, fb)
    assert len(ia) == len(ib), f"idx_a has {len(ia)} entries but idx_b {len(ib)}"
    assert len(ia) == len(ra), f"{len(ia)} mutual pairs, expected {len(ra)}"
    assert np.array_equal(ia, ra), "idx_a differs from the reference (is it sorted?)"
    assert np.array_equal(ib, rb), "idx_b differs from the reference"


@_case("student_mutual_nn", 4, "random descriptors, 200 x 16 against 150 x 16")
def _(f):
    rng = np.random.default_rng(41)
    _check_mnn(f, rng.standard_normal((200, 16)), rng.standard_normal((150, 16)))


@_case("student_mutual_nn", 3, "a shuffled, slightly noisy copy: every row matches")
def _(f):
    rng = np.random.default_rng(42)
    fa = rng.standard_normal((120, 8))
    fb = fa[rng.permutation(120)] + rng.normal(scale=0.01, size=(120, 8))
    _check_mnn(f, fa, fb)


@_case("student_mutual_nn", 3, "few rows against many, three channels")
def _(f):
    rng = np.random.default_rng(43)
    _check_mnn(f, rng.uniform(size=(30, 3)), rng.uniform(size=(90, 3)))


# Exercise: the fusion (03).
_exercise(
    "student_fuse", "03_fusion", "Fusing diffusion and geometric features",
    "FreeReg's feature fusion: per-row L2 normalisation, the weight w between the two modalities, "
    "and why the fused width stays the same at w = 0 and w = 1",
    refs=("features.fuse",),
)


def _check_fuse(f, f_d, f_g, w) -> None:
    from . import features

    _assert_close(_call(f, f_d, f_g, w), features.fuse(f_d, f_g, w), f"fused features (w = {w})",
                  atol=1e-6, rtol=1e-4)


@_case("student_fuse", 3, "w = 0.5 on features of different widths")
def _(f):
    rng = np.random.default_rng(51)
    _check_fuse(f, rng.normal(size=(40, 12)) * 5.0, rng.normal(size=(40, 32)) * 0.1, 0.5)


@_case("student_fuse", 2, "the ends w = 0 and w = 1 keep the full width")
def _(f):
    rng = np.random.default_rng(52)
    f_d, f_g = rng.normal(size=(25, 6)), rng.normal(size=(25, 10))
    for w in (0.0, 1.0):
        _check_fuse(f, f_d, f_g, w)


@_case("student_fuse", 2, "zero rows stay zero")
def _(f):
    rng = np.random.default_rng(53)
    f_d, f_g = rng.normal(size=(10, 4)), rng.normal(size=(10, 5))
    f_g[[1, 4, 7]] = 0.0
    f_d[4] = 0.0
    _check_fuse(f, f_d, f_g, 0.5)


@_case("student_fuse", 3, "several weights on float32 features")
def _(f):
    rng = np.random.default_rng(54)
    f_d = rng.normal(size=(30, 16)).astype(np.float32)
    f_g = rng.uniform(size=(30, 33)).astype(np.float32)
    for w in (0.3, 0.7, 0.9):
        _check_fuse(f, f_d, f_g, w)


# Exercise: registration recall over a ladder (04).
_exercise(
    "student_registration_recall", "04_benchmark", "Registration recall over a threshold ladder",
    "how RR is counted: both thresholds strict, and a pair without a pose (NaN errors) "
    "is a failure that still counts in the total",
    refs=("metrics.aggregate", "metrics.registered"),
)


def _check_rr(f, re, te, ladder) -> None:
    from . import metrics

    re_a, te_a = np.asarray(re, dtype=np.float64), np.asarray(te, dtype=np.float64)
    rows = [{"IR": 0.0, "IN": 0, "RE": a, "TE": b} for a, b in zip(re_a, te_a)]
    agg = metrics.aggregate(rows, ladder=tuple(ladder))
    want = [agg[f"RR@{deg:g}deg/{m:g}m"] for deg, m in ladder]
    got = _call(f, re, te, ladder)
    _assert_close(np.asarray(got, dtype=np.float64).reshape(-1), want, "RR per rung (%)")


@_case("student_registration_recall", 4, "the paper's indoor ladder, some pairs without a pose")
def _(f):
    from .config import config_for

    cfg = config_for("synthetic_indoor")
    rng = np.random.default_rng(61)
    re, te = rng.exponential(8.0, 40), rng.exponential(0.3, 40)
    re[[3, 17, 30]] = np.nan
    te[[3, 17, 30]] = np.nan
    _check_rr(f, re, te, [*cfg.rr_ladder, (cfg.rr_rot_deg, cfg.rr_trans_m)])


@_case("student_registration_recall", 2, "failed pairs count in the total")
def _(f):
    nan = np.nan
    _check_rr(f, np.array([1.0, nan, 2.0, nan]), np.array([0.1, nan, 0.05, nan]), [(5.0, 0.2), (20.0, 1.0)])
    _check_rr(f, np.full(5, np.nan), np.full(5, np.nan), [(5.0, 0.2)])


@_case("student_registration_recall", 2, "both thresholds are strict")
def _(f):
    re = np.array([5.0, 4.9, 5.0, 1.0, 0.0])
    te = np.array([0.1, 0.2, 0.2, 0.19999, 0.3])
    _check_rr(f, re, te, [(5.0, 0.2), (5.0, 0.3), (10.0, 1.0)])


@_case("student_registration_recall", 2, "pandas Series and plain lists as input")
def _(f):
    import pandas as pd

    rng = np.random.default_rng(62)
    re, te = rng.exponential(10.0, 12), rng.exponential(0.5, 12)
    re[5] = te[5] = np.nan
    _check_rr(f, pd.Series(re, index=np.arange(100, 112)), pd.Series(te, index=np.arange(100, 112)),
              [(10.0, 0.5), (20.0, 1.0)])
    _check_rr(f, list(re), list(te), [(3.0, 0.1)])


# --------------------------------------------------------------------------------------
# Reading notebooks.

def _read(path: str | Path):
    import nbformat

    return nbformat.read(str(path), as_version=4)


def _tags(cell) -> list[str]:
    return list(cell.get("metadata", {}).get("tags", []))


def _is_solution(cell) -> bool:
    return cell.cell_type == "code" and SOLUTION_TAG in _tags(cell)


def _python(source: str) -> str:
    """A cell's source as plain Python (IPython magics become calls) where IPython is around."""
    try:
        from IPython.core.inputtransformer2 import TransformerManager
    except ImportError:  # pragma: no cover - IPython comes with the notebook extras
        return source
    try:
        return TransformerManager().transform_cell(source)
    except Exception:
        return source


def _defined_functions(source: str) -> list[str]:
    try:
        tree = ast.parse(_python(source))
    except SyntaxError:
        return []
    return [n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _notebook_stem(nb, path: Path | None) -> str | None:
    """Which project notebook ``nb`` is: its assignment metadata, else its file name."""
    meta = nb.get("metadata", {}).get(METADATA_KEY, {})
    if meta.get("notebook"):
        return meta["notebook"]
    if path is None:
        return None
    stems = sorted({e.notebook for e in EXERCISES.values()} | {p.stem for p in NOTEBOOKS.glob("*.ipynb")})
    for stem in stems:
        if path.stem.startswith(stem):
            return stem
    prefix = re.match(r"(\d\d)_", path.stem)
    matches = [s for s in stems if prefix and s.startswith(prefix.group(0))]
    return matches[0] if len(matches) == 1 else None


# --------------------------------------------------------------------------------------
# Student versions.

_HINT_COMMENT = re.compile(r"#\s*HINT\s*:?\s*(.*)", re.IGNORECASE)
_MARKDOWN_HINT = re.compile(r"\bHint:\s*(.+?)(?:\)\s*)?(?:\n\s*\n|$)", re.DOTALL)


def _clean(text: str) -> str:
    return " ".join(text.split())


def markdown_hint(nb, index: int) -> str | None:
    """The "Hint: ..." sentence of the markdown cell(s) just above cell ``index``, if any."""
    for cell in reversed(nb.cells[:index]):
        if cell.cell_type != "markdown":
            break
        m = _MARKDOWN_HINT.search(cell.source)
        if m:
            return _clean(m.group(1))
    return None


def _signature_end(lines: list[str], start: int, stop: int) -> tuple[int, int]:
    """(0-based line, column) of the colon that ends the ``def`` line(s) in ``lines[start:stop]``."""
    text = "\n".join(lines[start:stop]) + "\n"
    depth, seen_def = 0, False
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.NAME and tok.string == "def":
            seen_def = True
        elif tok.type == tokenize.OP:
            if tok.string in "([{":
                depth += 1
            elif tok.string in ")]}":
                depth -= 1
            elif tok.string == ":" and seen_def and depth == 0:
                return start + tok.start[0] - 1, tok.start[1]
    raise ValueError("could not find the end of the def line")


def _hint_comments(lines: list[str], start: int, stop: int) -> list[str]:
    text = "\n".join(lines[start:stop]) + "\n"
    found = []
    try:
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            if tok.type == tokenize.COMMENT:
                m = _HINT_COMMENT.match(tok.string)
                if m and m.group(1).strip():
                    found.append(m.group(1).strip())
    except (tokenize.TokenError, IndentationError):
        pass
    return found


def _function_stub(node: ast.FunctionDef, lines: list[str], chunk_start: int, md_hint: str | None) -> list[str]:
    first = min([node.lineno, *(d.lineno for d in node.decorator_list)]) - 1
    end = node.end_lineno
    colon_line, colon_col = _signature_end(lines, first, end)
    body0 = node.body[0]
    one_liner = body0.lineno - 1 == colon_line
    if one_liner:
        head = lines[first:colon_line] + [lines[colon_line][: colon_col + 1]]
        indent = " " * (node.col_offset + 4)
    else:
        head = lines[first : colon_line + 1]
        indent = " " * body0.col_offset
    out = list(head)
    doc = ast.get_docstring(node, clean=True)
    has_doc = isinstance(body0, ast.Expr) and isinstance(body0.value, ast.Constant) and isinstance(body0.value.value, str)
    if has_doc and not one_liner:
        out += lines[body0.lineno - 1 : body0.end_lineno]
    elif has_doc:
        out.append(f'{indent}"""{doc}"""')
    hints = _hint_comments(lines, chunk_start, end)
    if hints:
        hint = " ".join(hints)
    elif md_hint:
        hint = md_hint
    elif doc:
        hint = doc.strip().splitlines()[0]
    else:
        hint = None
    message = (f"{node.name} is your exercise. Hint: {hint}" if hint else
               f"{node.name} is your exercise: write it as the text above asks, then run the check cell below.")
    out.append(f"{indent}# Your code here: replace the line below with your implementation.")
    out.append(f"{indent}raise NotImplementedError({json.dumps(message, ensure_ascii=False)})")
    return out


def stub_source(source: str, md_hint: str | None = None) -> str:
    """A solution cell with every top-level function reduced to signature, docstring and a stub.

    Imports are kept; every other statement, comment and nested function is solution code and
    goes. The stub raises ``NotImplementedError`` with a hint: a ``# HINT: ...`` comment of the
    function (or just above it) if there is one, else the exercise text's "Hint: ..." sentence
    (``md_hint``), else the docstring's first line, else a generic pointer to the text and the
    check cell. (The docstring comes after the exercise's hint because the stub keeps it anyway.)
    """
    tree = ast.parse(source)
    lines = source.splitlines()
    out: list[list[str]] = []
    chunk_start = 0
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out.append(_function_stub(node, lines, chunk_start, md_hint))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(lines[node.lineno - 1 : node.end_lineno])
        chunk_start = node.end_lineno
    return "\n\n\n".join("\n".join(chunk) for chunk in out)


def _banner(stem: str, functions: list[str]):
    import nbformat

    if functions:
        todo = "\n".join(f"- `{name}`" for name in functions)
        text = (f"**Student version** of `{stem}`.\n\n"
                f"Your exercises in this notebook (code cells tagged `{SOLUTION_TAG}`):\n\n{todo}\n\n"
                "Replace each `raise NotImplementedError(...)` with your code, keep the function names and "
                f"signatures, and run the cell tagged `{CHECK_TAG}` just below to test yourself. Your functions "
                "are graded on their own, with only their arguments, `numpy as np`, this notebook's imports and "
                "the `freereg_lib` modules to hand; do not use the notebook's variables (`pair`, `cfg`, ...) "
                "inside them.")
    else:
        text = f"**Student version** of `{stem}`. This notebook has no exercise: read and run it."
    cell = nbformat.v4.new_markdown_cell(text)
    cell["id"] = BANNER_ID
    return cell


def _relocate_outputs(source: str, stem: str) -> str:
    """Point ``out_dir`` / ``figures_dir`` of a parameters cell (annotated or not) into the student folder."""
    targets = {"out_dir": f"runs/{stem}", "figures_dir": "figures"}
    return re.sub(r'^(\s*)(out_dir|figures_dir)(\s*(?::[^=\n]*)?=\s*)(?:"[^"\n]*"|\'[^\'\n]*\')(.*)$',
                  lambda m: f'{m.group(1)}{m.group(2)}{m.group(3)}"{targets[m.group(2)]}"{m.group(4)}',
                  source, flags=re.MULTILINE)


def _strip(nb) -> None:
    for cell in nb.cells:
        cell.get("metadata", {}).pop("papermill", None)
        cell.get("metadata", {}).pop("execution", None)
        if cell.cell_type == "code":
            cell["outputs"] = []
            cell["execution_count"] = None
    nb.metadata.pop("papermill", None)


def student_notebook(nb, stem: str):
    """The student version of notebook ``nb`` (a copy; ``nb`` is left alone)."""
    out = copy.deepcopy(nb)
    _strip(out)
    functions = []
    for i, cell in enumerate(out.cells):
        if _is_solution(cell):
            functions += _defined_functions(cell.source)
            try:
                cell.source = stub_source(cell.source, markdown_hint(out, i))
            except SyntaxError as e:
                raise ValueError(f"{stem}: solution cell {i} is not valid Python ({e})") from e
        elif cell.cell_type == "code" and "parameters" in _tags(cell):
            cell.source = _relocate_outputs(cell.source, stem)
    banner = _banner(stem, functions)
    if out.nbformat_minor < 5:
        banner.pop("id", None)
    out.cells.insert(0, banner)
    out.metadata[METADATA_KEY] = {"notebook": stem, "exercises": functions,
                                  "generated_by": "python -m freereg_lib.assignments make"}
    return out


def make(out: str | Path = DEFAULT_OUT, notebooks: str | Path = NOTEBOOKS,
         key: str | Path | None = None) -> list[Path]:
    """Write the student version of every notebook of ``notebooks`` into ``out``.

    With ``key``, a copy of the originals (outputs stripped) goes there as the answer key.
    Returns the student notebooks written.
    """
    import nbformat

    out, notebooks = Path(out), Path(notebooks)
    sources = sorted(notebooks.glob("*.ipynb"))
    if not sources:
        raise FileNotFoundError(f"no notebook in {notebooks}")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for path in sources:
        nb = _read(path)
        student = student_notebook(nb, path.stem)
        nbformat.validate(student)
        nbformat.write(student, str(out / path.name))
        written.append(out / path.name)
        if key is not None:
            Path(key).mkdir(parents=True, exist_ok=True)
            answer = copy.deepcopy(nb)
            _strip(answer)
            nbformat.write(answer, str(Path(key) / path.name))
    return written


def fill(student, key):
    """The student notebook with the key's solution cells put back (a copy).

    Cells are matched by the functions they define, else by their order.
    """
    out = copy.deepcopy(student)
    key_cells = [c for c in key.cells if _is_solution(c)]
    by_names = {tuple(_defined_functions(c.source)): c.source for c in key_cells}
    mine = [c for c in out.cells if _is_solution(c)]
    for k, cell in enumerate(mine):
        names = tuple(_defined_functions(cell.source))
        if names in by_names:
            cell.source = by_names[names]
        elif k < len(key_cells):
            cell.source = key_cells[k].source
    return out


class exercise_check:  # noqa: N801 - used as a statement: ``with exercise_check("student_fuse"):``
    """The body of a ``check`` cell: an unsolved exercise reports itself instead of stopping Run All.

    ``with exercise_check("student_fuse"): <the checks>`` runs the checks. When one of the named
    functions is still the student version's stub (it raises ``NotImplementedError`` naming
    itself), the rest of the block is skipped and one line says so: which exercise, its hint, and
    that the notebook goes on with the library's reference (no later cell calls the student's
    function). A wrong answer (an ``AssertionError``) or any other error still stops the notebook,
    as a failed check should.
    """

    def __init__(self, *functions: str) -> None:
        unknown = [f for f in functions if f not in EXERCISES]
        if unknown or not functions:
            raise ValueError(f"exercise_check: unknown exercise(s) {unknown}; known: {', '.join(EXERCISES)}")
        self.functions = functions
        self.skipped: str | None = None  # the exercise whose stub stopped the check, if any

    def __enter__(self) -> "exercise_check":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None or not issubclass(exc_type, NotImplementedError):
            return False
        name = next((f for f in self.functions if f in str(exc)), None)
        if name is None:
            return False
        refs = ", ".join(f"freereg_lib.{r}" for r in EXERCISES[name].refs[:1]) or "the library"
        self.skipped = name
        print(f"EXERCISE NOT DONE: {name} still raises NotImplementedError, so this check is skipped. "
              f"The rest of the notebook does not use {name}: it runs on the library's reference, {refs}.\n"
              f"  {exc}")
        return True


# --------------------------------------------------------------------------------------
# Grading.

class _Namespace(dict):
    """Globals for the students' code: a name the notebook imports is imported on first use.

    Functions defined here look their globals up through ``__missing__`` (a dict subclass as
    globals disables CPython's fast path), so ``pd`` or ``cameras`` cost nothing unless used.
    """

    def __init__(self, lazy: dict[str, str]):
        super().__init__(__name__="__student__", __builtins__=__builtins__, np=np)
        self._lazy = lazy

    def __missing__(self, name: str):
        statement = self._lazy.pop(name, None)
        if statement is None:
            raise KeyError(name)
        scratch: dict = {}
        exec(statement, scratch)
        value = scratch[name]
        self[name] = value
        return value


def _parsed_cells(nb):
    """The syntax tree of every code cell outside the solution cells that parses."""
    for cell in nb.cells:
        if cell.cell_type != "code" or _is_solution(cell):
            continue
        try:
            yield ast.parse(_python(cell.source))
        except SyntaxError:
            continue


def _import_statements(nb) -> dict[str, str]:
    """Every name the notebook's import statements bind (outside solution cells), and the statement."""
    lazy: dict[str, str] = {}
    import freereg_lib

    for mod in pkgutil.iter_modules(freereg_lib.__path__):
        if mod.name != "assignments":
            lazy[mod.name] = f"from freereg_lib import {mod.name}"
    for tree in _parsed_cells(nb):
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    name = a.asname or a.name.split(".")[0]
                    lazy[name] = f"import {a.name}" + (f" as {a.asname}" if a.asname else "")
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                for a in node.names:
                    if a.name != "*":
                        lazy[a.asname or a.name] = (f"from {node.module} import {a.name}"
                                                    + (f" as {a.asname}" if a.asname else ""))
    return lazy


@contextlib.contextmanager
def _time_limit(seconds: float | None):
    usable = (seconds and seconds > 0 and hasattr(signal, "setitimer")
              and threading.current_thread() is threading.main_thread())
    if not usable:
        yield
        return

    def expired(signum, frame):
        raise TimeoutError(f"no answer within {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@contextlib.contextmanager
def _quiet():
    """Keep the students' prints and warnings out of the score table."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
            warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def _describe(e: BaseException) -> str:
    text = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
    text = _clean(text)
    return text if len(text) <= 200 else text[:197] + "..."


def load_functions(path: str | Path, timeout: float = CASE_TIMEOUT_S) -> tuple[dict[str, Callable], dict[str, str]]:
    """The exercise functions a student notebook defines, and why any could not be read.

    Runs every cell tagged ``solution`` (each on its own, so one broken cell spoils only its
    own functions) in a fresh namespace with ``numpy as np``, the notebook's imports and the
    ``freereg_lib`` modules. A function the student defined in an untagged cell is taken from
    there (only its ``def``). Nothing else of the notebook runs.
    """
    nb = _read(path)
    ns = _Namespace(_import_statements(nb))
    problems: dict[str, str] = {}
    for i, cell in enumerate(nb.cells):
        if not _is_solution(cell):
            continue
        try:
            code = compile(_python(cell.source), f"<{Path(path).name} cell {i}>", "exec")
            try:
                with _quiet(), _time_limit(timeout):
                    exec(code, ns)
            finally:
                if _GUARD:
                    _GUARD.check()
        except BaseException as e:  # noqa: BLE001 - any failure of the student's cell is a result
            if isinstance(e, KeyboardInterrupt):
                raise
            names = _defined_functions(cell.source) or re.findall(r"^def\s+(\w+)", cell.source, re.MULTILINE)
            for name in names or [f"cell {i}"]:
                problems[name] = (str(e) if isinstance(e, ReferenceChanged)
                                  else f"its solution cell failed: {_describe(e)}")
                if isinstance(e, ReferenceChanged):
                    ns.pop(name, None)
    found = {name: ns[name] for name in EXERCISES if callable(dict.get(ns, name))}
    missing = set(EXERCISES) - set(found)
    # A function defined outside its solution cell (an untagged cell) still counts.
    trees = list(_parsed_cells(nb)) if missing else []
    for name in missing:
        for tree in trees:
            defs = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name == name]
            if defs:
                try:
                    with _quiet(), _time_limit(timeout):
                        exec(compile(ast.Module(body=defs[-1:], type_ignores=[]), f"<{Path(path).name}>", "exec"), ns)
                    found[name] = ns[name]
                    problems.pop(name, None)
                except Exception as e:  # noqa: BLE001
                    problems[name] = f"its definition failed: {_describe(e)}"
    return found, problems


def grade_function(exercise: Exercise, f: Callable | None, problem: str | None = None,
                   timeout: float = CASE_TIMEOUT_S) -> dict:
    """Score one exercise's function case by case; never raises."""
    result = {"exercise": exercise.function, "notebook": exercise.notebook, "title": exercise.title,
              "score": 0.0, "max": exercise.max_points, "status": "missing", "cases": []}
    if f is None:
        result["message"] = problem or "not found"
        for case in exercise.cases:
            result["cases"].append({"name": case.name, "points": 0.0, "max": case.points, "ok": False,
                                    "message": "not graded"})
        return result
    not_implemented = 0
    cheat = ""
    for case in exercise.cases:
        ok, message = False, ""
        _student_timeout[0] = timeout
        _current_refs[0] = exercise.refs
        try:
            with _quiet():
                case.run(f)
            ok = True
        except NotImplementedError as e:
            not_implemented += 1
            message = _describe(e)
        except (ReferenceUsed, ReferenceChanged) as e:
            cheat = cheat or str(e)
            message = str(e)
        except BaseException as e:  # noqa: BLE001 - the student's crash is a result
            if isinstance(e, KeyboardInterrupt):
                raise
            message = _describe(e)
        finally:
            _student_timeout[0] = None
            _current_refs[0] = ()
        result["cases"].append({"name": case.name, "points": case.points if ok else 0.0, "max": case.points,
                                "ok": ok, "message": message})
    if cheat:  # one case is enough: the whole exercise scores zero
        for c in result["cases"]:
            c["points"], c["ok"] = 0.0, False
            c["message"] = c["message"] or cheat
        result.update(score=0.0, status="refused", message=cheat)
        return result
    result["score"] = float(sum(c["points"] for c in result["cases"]))
    if not_implemented == len(exercise.cases):
        result["status"], result["message"] = "not implemented", "raises NotImplementedError"
    elif result["score"] == result["max"]:
        result["status"], result["message"] = "ok", ""
    else:
        result["status"] = "partial" if result["score"] > 0 else "failed"
        result["message"] = next(c["message"] for c in result["cases"] if not c["ok"]) or "wrong answer"
    return result


def _notebooks_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.ipynb")
                  if ".ipynb_checkpoints" not in p.parts and not p.name.endswith(".executed.ipynb"))


def grade(path: str | Path, timeout: float = CASE_TIMEOUT_S, verbose: bool = False,
          print_table: bool = True, limit: float = STUDENT_LIMIT_S) -> dict:
    """Grade a student notebook, or a folder holding one student's notebooks, in a process of
    its own killed after ``limit`` seconds (see :func:`grade_here` for what is graded).

    When that process ends without a result (killed at the limit, ``os._exit``, a crash), the
    exercises it had finished keep their scores and the others score 0 with the reason.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such notebook or folder")
    with tempfile.TemporaryDirectory(prefix="freereg_grade_") as tmp:
        progress = Path(tmp) / "progress.jsonl"
        cmd = [sys.executable, "-m", "freereg_lib.assignments", "grade-one", str(path),
               "--timeout", str(timeout), "--progress", str(progress)]
        start = time.time()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True, cwd=str(ROOT))
        try:
            code = proc.wait(timeout=limit)
            ended = f"its grading process ended (exit code {code}) before finishing this exercise"
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the student's threads and children too
            proc.wait()
            ended = (f"its grading process was stopped at the hard limit of {limit:g} s "
                     "(code that never returns, or catches the time-out)")
        with contextlib.suppress(OSError):
            os.killpg(proc.pid, signal.SIGKILL)  # anything the student left running
        lines = []
        if progress.is_file():
            for line in progress.read_text().splitlines():
                with contextlib.suppress(ValueError):
                    lines.append(json.loads(line))
    final = next((x["result"] for x in lines if "result" in x), None)
    if final is None:
        wanted = next((x["wanted"] for x in lines if "wanted" in x), None)
        if wanted is None:  # stopped before it got that far: read it here (no student code runs)
            wanted = list(EXERCISES) if path.is_dir() else _wanted_in(path)
        done = {x["exercise"]["exercise"]: x["exercise"] for x in lines if "exercise" in x}
        exercises = []
        for name in wanted:
            if name in done:
                exercises.append(done[name])
                continue
            ex = grade_function(EXERCISES[name], None, ended)
            ex["status"] = "stopped"
            exercises.append(ex)
        skipped = next((x["skipped"] for x in lines if "skipped" in x), [])
        final = _result(path, exercises, skipped)
        final["stopped"] = ended
        final["seconds"] = round(time.time() - start, 1)
    if print_table:
        print(format_table(final, verbose))
    return final


def _wanted_in(path: Path) -> list[str]:
    """The exercises a single notebook is graded on (as :func:`grade_here`), read statically."""
    try:
        nb = _read(path)
    except Exception:  # noqa: BLE001
        return []
    stem = _notebook_stem(nb, path)
    own = [n for n, ex in EXERCISES.items() if ex.notebook == stem]
    defined = {n for c in nb.cells if c.cell_type == "code" for n in _defined_functions(c.source)}
    return own + [n for n in EXERCISES if n in defined and n not in own]


def _result(path: Path, exercises: list[dict], skipped: list[str]) -> dict:
    score = float(sum(e["score"] for e in exercises))
    top = float(sum(e["max"] for e in exercises))
    return {"path": str(path), "score": score, "max": top, "percent": 100.0 * score / top if top else 0.0,
            "exercises": exercises, "skipped": skipped}


def grade_here(path: str | Path, timeout: float = CASE_TIMEOUT_S, verbose: bool = False,
               print_table: bool = True, progress: str | Path | None = None) -> dict:
    """Grade a student notebook, or a folder holding one student's notebooks, in this process.

    A folder is graded on every exercise (one missing from it scores 0); a single notebook on
    the exercises of the project notebook it is a version of (found from its metadata or file
    name), or failing that on the exercise functions it defines. Prints a table unless
    ``print_table`` is false, and returns ``{"path", "score", "max", "percent", "exercises": [...]}``
    with one entry per exercise (``score``, ``max``, ``status``, ``message`` and ``cases``).
    With ``progress``, one JSON line per step goes to that file as it happens (the wanted
    exercises, each graded exercise, the result), for :func:`grade` to read.
    """
    global _GUARD
    if _GUARD is None:
        _GUARD = Guard()  # before any student code runs
    path = Path(path)
    if path.is_dir():
        files = _notebooks_in(path)
        wanted = list(EXERCISES)
    elif path.is_file():
        files = [path]
        wanted = None
    else:
        raise FileNotFoundError(f"{path}: no such notebook or folder")

    found: dict[str, tuple[Callable | None, str | None]] = {}
    skipped = []
    for nb_path in files:
        try:
            nb = _read(nb_path)
        except Exception as e:  # noqa: BLE001 - an unreadable file is a result too
            skipped.append(f"{nb_path.name}: not a readable notebook ({_describe(e)})")
            continue
        stem = _notebook_stem(nb, nb_path)
        own = [n for n, ex in EXERCISES.items() if ex.notebook == stem]
        defined = {n for c in nb.cells if c.cell_type == "code" for n in _defined_functions(c.source)}
        relevant = own + [n for n in EXERCISES if n in defined and n not in own]
        if wanted is None:
            wanted = relevant
        if not relevant:
            continue
        functions, problems = load_functions(nb_path, timeout)
        for name in relevant:  # the first notebook that defines a function gives it
            f = functions.get(name)
            if f is not None and (name not in found or found[name][0] is None):
                found[name] = (f, None)
            elif name not in found:
                found[name] = (None, problems.get(name) or f"not defined in {nb_path.name}")

    log = open(progress, "a") if progress else None

    def note(item: dict) -> None:
        if log:
            log.write(json.dumps(item) + "\n")
            log.flush()
            os.fsync(log.fileno())

    note({"wanted": list(wanted or []), "skipped": skipped})
    exercises = []
    for name in wanted or []:
        f, problem = found.get(name, (None, f"no notebook for {EXERCISES[name].notebook}"))
        exercises.append(grade_function(EXERCISES[name], f, problem, timeout))
        note({"exercise": exercises[-1]})
    result = _result(path, exercises, skipped)
    note({"result": result})
    if log:
        log.close()
    if print_table:
        print(format_table(result, verbose))
    return result


def _points(x: float) -> str:
    return f"{x:g}"


def format_table(result: dict, verbose: bool = False) -> str:
    """The score table of one ``grade`` result, as plain text."""
    rows = [("notebook", "exercise", "score", "status")]
    notes = {}
    for e in result["exercises"]:
        rows.append((e["notebook"], e["exercise"], f"{_points(e['score'])}/{_points(e['max'])}", e["status"]))
        lines = []
        if e["status"] == "missing":
            lines.append(e.get("message", ""))
        elif e["status"] in ("stopped", "refused"):
            lines.append(e.get("message", ""))
        elif e["status"] != "not implemented":
            for c in e["cases"]:
                if verbose or not c["ok"]:
                    mark = "ok  " if c["ok"] else "FAIL"
                    text = f"{mark} {_points(c['points'])}/{_points(c['max'])}  {c['name']}"
                    lines.append(text + (f": {c['message']}" if c["message"] else ""))
        notes[len(rows) - 1] = lines
    rows.append(("total", "", f"{_points(result['score'])}/{_points(result['max'])}", f"{result['percent']:.1f} %"))
    if result.get("stopped") and not result["exercises"]:
        notes[len(rows) - 1] = [result["stopped"]]
    widths = [max(len(r[k]) for r in rows) for k in range(4)]
    out = [f"Autograder: {result['path']}"]
    for i, row in enumerate(rows):
        if i == len(rows) - 1:
            out.append("  ".join("-" * w for w in widths))
        out.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
        if i == 0:
            out.append("  ".join("-" * w for w in widths))
        for line in notes.get(i, []):
            out.append(" " * 4 + line)
    if not result["exercises"]:
        out.append("(no exercise found)")
    for line in result.get("skipped", []):
        out.append(f"skipped {line}")
    return "\n".join(out)


# --------------------------------------------------------------------------------------
# Command line.

def exercise_table() -> str:
    """The exercises as a Markdown table (notebook, function, points, what it teaches)."""
    lines = ["| notebook | function | points | teaches |", "|---|---|---|---|"]
    for e in EXERCISES.values():
        lines.append(f"| {e.notebook} | `{e.function}` | {_points(e.max_points)} | {e.teaches} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m freereg_lib.assignments", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_make = sub.add_parser("make", help="write the student versions of the notebooks")
    p_make.add_argument("--out", default=str(DEFAULT_OUT), help="folder for the student notebooks "
                        "(default: assignments/student of the project)")
    p_make.add_argument("--notebooks", default=str(NOTEBOOKS), help="the full notebooks (default: notebooks/)")
    p_make.add_argument("--key", default=None, help="also write the answer key (stripped originals) here")
    p_grade = sub.add_parser("grade", help="grade student notebooks and print the scores")
    p_grade.add_argument("paths", nargs="+", help="a student notebook, or a folder of one student's notebooks")
    p_grade.add_argument("--timeout", type=float, default=CASE_TIMEOUT_S, help="seconds allowed per call of a student's function")
    p_grade.add_argument("--json", default=None, help="also write the results to this JSON file")
    p_grade.add_argument("-v", "--verbose", action="store_true", help="list every case, not just the failed ones")
    p_grade.add_argument("--limit", type=float, default=STUDENT_LIMIT_S,
                         help="hard limit in seconds for one student's grading process (default 600)")
    p_one = sub.add_parser("grade-one", help=argparse.SUPPRESS)  # the per-student process of `grade`
    p_one.add_argument("path")
    p_one.add_argument("--timeout", type=float, default=CASE_TIMEOUT_S)
    p_one.add_argument("--progress", required=True)
    sub.add_parser("list", help="list the exercises")
    args = parser.parse_args(argv)

    if args.command == "make":
        written = make(args.out, args.notebooks, args.key)
        for path in written:
            nb = _read(path)
            names = nb.metadata.get(METADATA_KEY, {}).get("exercises", [])
            print(f"{path}: {', '.join(names) if names else 'no exercise'}")
        if args.key:
            print(f"answer key: {args.key}")
        return 0
    if args.command == "list":
        print(exercise_table())
        return 0
    if args.command == "grade-one":
        grade_here(args.path, args.timeout, print_table=False, progress=args.progress)
        return 0

    results = []
    for i, path in enumerate(args.paths):
        if i:
            print()
        try:
            results.append(grade(path, args.timeout, args.verbose, limit=args.limit))
        except FileNotFoundError as e:
            print(f"Autograder: {e}")
            results.append({"path": str(path), "score": 0.0, "max": 0.0, "percent": 0.0,
                            "exercises": [], "error": str(e)})
        sys.stdout.flush()
        if args.json:  # written as each student finishes: a later crash loses nothing
            _write_json(Path(args.json), results if len(args.paths) > 1 else results[0])
    if len(results) > 1:
        print("\nSummary")
        width = max(len(r["path"]) for r in results)
        for r in results:
            print(f"{r['path'].ljust(width)}  {_points(r['score'])}/{_points(r['max'])}  ({r['percent']:.1f} %)")
    return 0


def _write_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(path)


if __name__ == "__main__":
    sys.exit(main())
