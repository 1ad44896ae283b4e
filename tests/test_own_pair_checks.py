"""``Pair.validate`` names the faults a pair's own data can tell (``geometry_fault``), each of which
passed silently before: a depth in units off by 1.2, 1.5, 4 or 5 (0.2 x), a transposed rotation with
the same translation, another pair's pose or depth, and a mirrored depth map; good pairs pass.

A quarter-size ICL pair keeps it cheap (the same numbers on either side of the thresholds as full
size, as ``tests/test_bad_input_round4.py`` measured)."""
from __future__ import annotations

import dataclasses

import pytest

from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.pair import geometry_fault
from freereg_lib.report import pair_files as PF


@pytest.fixture(scope="module")
def icl():
    return ICLSample()


@pytest.fixture(scope="module")
def pair(icl):
    return PF.downscale_pair(icl.pair(50, 90), 0.25)


def _transposed(p):
    T = p.T_cam_pc.copy()
    T[:3, :3] = T[:3, :3].T
    return dataclasses.replace(p, T_cam_pc=T)


@pytest.mark.parametrize("name, make, says", [
    ("depth x0.2", lambda p, s: dataclasses.replace(p, depth_gt=p.depth_gt * 0.2), "depth_gt is 0.2 x the truth (x4.9"),
    ("depth x1.2", lambda p, s: dataclasses.replace(p, depth_gt=p.depth_gt * 1.2), "depth_gt is 1.2 x the truth"),
    ("depth x1.5", lambda p, s: dataclasses.replace(p, depth_gt=p.depth_gt * 1.5), "depth_gt is 1.5 x the truth"),
    ("depth x4", lambda p, s: dataclasses.replace(p, depth_gt=p.depth_gt * 4), "depth_gt is 4 x the truth"),
    ("transposed", lambda p, s: _transposed(p), "rotation looks transposed"),
    ("other pose", lambda p, s: dataclasses.replace(p, T_cam_pc=s.pair(150, 190).T_cam_pc), "another view's"),
    ("other depth", lambda p, s: dataclasses.replace(p, depth_gt=PF.downscale_pair(s.pair(0, 10), 0.25).depth_gt),
     "another view's"),
    ("mirrored depth", lambda p, s: dataclasses.replace(p, depth_gt=p.depth_gt[:, ::-1].copy()), "mirrored depth"),
])
def test_validate_names_what_passed_silently(pair, icl, name, make, says):
    bad = make(pair, icl)
    with pytest.raises(ValueError) as info:
        bad.validate()
    msg = str(info.value)
    assert msg.startswith("pair icl/00050-00090: depth_gt lifted with T_cam_pc does not land on the point cloud: ")
    assert says in msg and "\n" not in msg, (name, msg)


@pytest.mark.parametrize("i, j", [(0, 10), (10, 50), (80, 120), (0, 100), (110, 210), (170, 200)])
def test_validate_passes_good_pairs_far_apart_too(icl, i, j):
    # Pairs 100 frames apart land only half of their pixels on the cloud: the new checks (looked
    # into below 50 %) must not refuse them.
    assert geometry_fault(PF.downscale_pair(icl.pair(i, j), 0.25)) == ""
