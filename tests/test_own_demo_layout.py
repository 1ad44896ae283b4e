"""The official demo's case, built from the shipped ICL frames: ``freereg register --demo`` and the
demo's loose files (with and without the sensor pose) register with the stub backend.

The official demo (``FreeReg/data/demo``, no licence, so not shipped) is a ScanNet frame: a
17k-point cloud in its sensor's frame (about 6 % of its sensor's pixels), a camera about 1.3 m
from the scene, and the stub's monocular depth there is off by a scale of 1.27 (its fixed
0.27 m error on a near scene). The case here has the same make: half-size ICL frame ``J``'s
depth in its sensor's frame, every 16th point kept, the whole scene shrunk by :data:`SHRINK`
(cloud, depths and translations) so that the stub's scale error is the demo's size, in the demo
layout (``source_rgb.png``, ``target_pc.ply``, ``intrinsics.json``, ``just_for_eval/``). Measured
on the official demo itself (docs/your_data.md): ``--demo`` RE 4.2 deg / TE 0.16 m, the loose
files 3.6 deg / 0.15 m without the sensor pose and 4.2 deg / 0.16 m with it, all REGISTERED.
This case, when written (2,000 iterations): all three REGISTERED at RE 6.4 deg, TE 0.12 m (shrunk
scene), 34 inliers = 2.62 x the shuffled matches' 13 (the rule asks 2.5 x), scale 1.23; the former
rule called it FAILED (34 < 48 inliers), and the former fill sent loose sparse clouds to 3dmatch.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from freereg_lib.commands import cli
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.geometry import cameras
from freereg_lib.report import pair_files as PF

I, J = 190, 200
SHRINK = 0.75   # the scene shrunk: the stub's 0.27 m error becomes a scale error near the demo's
THIN = 16       # every 16th point of the sensor's depth: ~6 % of its pixels, as the demo's cloud
ITERS = 2000


def build(root: Path) -> dict:
    """The demo-layout case in ``root``; returns its image intrinsics and ``T_cam_pc``."""
    icl = ICLSample()
    (root / "just_for_eval").mkdir(parents=True, exist_ok=True)
    h, w = 480, 640
    K = cameras.scale_intrinsics(icl.K, w / 640, h / 480)
    small = lambda d: cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST) * SHRINK  # noqa: E731
    image = cv2.resize(icl.rgb(I), (w, h), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(root / "source_rgb.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(root / "just_for_eval" / "source_rgb.gtd.png"), np.round(small(icl.depth(I)) * 1000).astype(np.uint16))
    points, _ = cameras.backproject(small(icl.depth(J)), K)
    PF.write_ply(root / "target_pc.ply", points[::THIN])
    T_pc_cam = cameras.invert(icl.pose(J)) @ icl.pose(I)
    T_pc_cam[:3, 3] *= SHRINK
    np.savetxt(root / "just_for_eval" / "rgb2pc.gt.pose.txt", T_pc_cam)
    Kl = K.tolist()
    (root / "intrinsics.json").write_text(json.dumps({"rgb_intrinsic": Kl, "dpt_intrinsic": Kl, "rgb_size": [w, h],
                                                      "dpt_size": [w, h], "dpt_scale": 1000.0}))
    return {"K": K, "T_cam_pc": cameras.invert(T_pc_cam)}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo_layout")
    return root, build(root)


def _loose(root: Path, K: np.ndarray, sensor: bool) -> list[str]:
    argv = ["register", str(root / "source_rgb.png"), str(root / "target_pc.ply"), "--K",
            *(f"{v:.6f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])),
            "--image-depth", str(root / "just_for_eval" / "source_rgb.gtd.png"),
            "--gt-T-pc-cam", str(root / "just_for_eval" / "rgb2pc.gt.pose.txt"), "--views", "4"]
    return argv + (["--depth-pose", "identity"] if sensor else [])


@pytest.mark.parametrize("how", ["demo", "loose-with-sensor-pose", "loose-without"])
def test_the_demo_layout_registers_with_the_stub(case, how, tmp_path, capsys):
    root, truth = case
    argv = (["register", "--demo", str(root)] if how == "demo" else _loose(root, truth["K"], how != "loose-without"))
    argv += ["--backend", "stub", "--ransac-iters", str(ITERS), "--out", str(tmp_path / "out")]
    assert cli.main(argv) == 0, capsys.readouterr().err
    text = capsys.readouterr().out
    assert re.search(r"^setting: demo: ", text, re.M), text  # the sparse cloud is densified, as the demo's
    doc = json.loads((tmp_path / "out" / "registration.json").read_text())
    gt = doc["ground_truth"]
    assert gt["RE"] < 20 and gt["TE"] < 0.5 * SHRINK, (how, gt)
    assert doc["registered"], text[-600:]
    scale = float(re.search(r"scale (\d+\.\d+)\s*$", text.strip().splitlines()[-1]).group(1))
    assert max(scale, 1 / scale) > 1.2, scale  # the demo's regime: a scale the old 1.25 bound sat next to


@pytest.mark.parametrize("step, low, high", [(1, 0.95, 1.0), (3, 0.09, 0.13), (7, 0.015, 0.03), (20, 0.0, 0.02)])
def test_the_fill_reads_points_a_few_pixels_apart_as_sparse(step, low, high):
    # A wall 2 m in front of a 640 x 480 camera, one point every `step` pixels: it fills about
    # 1 / step ** 2 of its footprint. A 7 x 7 closing gave each point farther than 7 px from the
    # others a footprint of its own pixel: 20 px apart read as 100 % filled, which sent the
    # official demo's 17k points (17 % "filled") to the 3dmatch setting.
    K = cameras.intrinsics(500.0, 500.0, 319.5, 239.5)
    v, u = np.mgrid[0:480:step, 0:640:step]
    pts = cameras.lift(np.stack([u.ravel(), v.ravel()], axis=1).astype(float), np.full(u.size, 2.0), K)
    fill = cli.projected_fill(pts, K, (480, 640), np.eye(4))
    assert low <= fill <= high, (step, fill)
