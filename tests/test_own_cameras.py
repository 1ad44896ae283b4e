"""Your own camera through ``freereg register``: pixels that are not square, intrinsics out of order.

Non-square pixels: a real 640 x 480 ICL frame squeezed to 320 x 480 (fx and cx halved, as
``cameras.scale_intrinsics`` gives) is a correct image of another camera. The command now
resamples it to square pixels (:func:`freereg_lib.commands.inputs_check.square_pixels`), since
the learned models read an image as a square-pixel photo (ZoeDepth keeps the aspect it is
given: the micro ZoeDepth's depth error triples on a squeezed room), and registers it within the
bound the original meets. Measured when written (stub with
the true depth, FreeReg-G, Kabsch, 2,000 iterations, full-size frames 0 / 40): sensor-frame
cloud RE 1.0 deg original, 1.6 deg squeezed (2.2 deg before the resampling); merged world-frame
cloud RE 0.8 / 2.2 deg.

Intrinsics out of order: ``--K fx fy cy cx`` is named as a swap (it was blamed on
``--depth-size``, or on a wide image called "outside the image"), ``--K cx cy fx fy`` as the
principal point given first, a swapped ``--depth-K`` beside the image's own size as ``--depth-K``.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from freereg_lib.commands import cli
from freereg_lib.commands import inputs_check as IC
from freereg_lib.commands import user_inputs as UI
from freereg_lib.config import config_for
from freereg_lib.data import synthetic
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.geometry import cameras
from freereg_lib.models import get_backend
from freereg_lib.pipeline.register import InputError
from freereg_lib.report import pair_files as PF
from freereg_lib.report import plots

I, J = 0, 40          # image frame, cloud frame
BOUND = (5.0, 0.2)    # deg, m: the original meets it with room (RE 1.0 / 0.8 deg)


@pytest.fixture(scope="module")
def icl():
    return ICLSample()


def _case(root: Path, icl: ICLSample, kind: str, width_factor: float) -> dict:
    """Frame ``I``'s image (its width scaled by ``width_factor``) and true depth; the cloud of
    frame ``J`` in its sensor's frame (``sensor``) or frames ``J - 20, J, J + 20`` merged in the
    world frame (``world``, no sensor pose)."""
    root.mkdir(parents=True, exist_ok=True)
    K = icl.K
    if kind == "sensor":
        points, _ = cameras.backproject(icl.depth(J), K)
        T_pc_cam = cameras.invert(icl.pose(J)) @ icl.pose(I)
    else:
        frames = [f for f in (J - 20, J, J + 20) if f in icl.frames]
        points = np.concatenate([cameras.transform(icl.pose(f), cameras.backproject(icl.depth(f), K)[0])
                                 for f in frames])[:: 3 * len(frames)]
        T_pc_cam = icl.pose(I)
    image, depth = icl.rgb(I), icl.depth(I)
    H, W = depth.shape
    w = round(W * width_factor)
    image = cv2.resize(image, (w, H), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(depth, (w, H), interpolation=cv2.INTER_NEAREST)
    K_img = cameras.scale_intrinsics(K, w / W, 1.0)
    cv2.imwrite(str(root / "image.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(root / "depth.png"), np.round(depth * 1000).astype(np.uint16))
    PF.write_ply(root / "cloud.ply", points)
    np.savetxt(root / "gt_T_pc_cam.txt", T_pc_cam)
    return {"root": root, "K": K_img, "sensor": kind == "sensor"}


def _argv(case: dict, out: Path, K=None) -> list[str]:
    K = case["K"] if K is None else K
    return (["register", str(case["root"] / "image.png"), str(case["root"] / "cloud.ply"), "--K",
             *(f"{v:.6f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])), "--image-depth",
             str(case["root"] / "depth.png"), "--gt-T-pc-cam", str(case["root"] / "gt_T_pc_cam.txt"),
             "--backend", "stub", "--stub-true-depth", "--ransac-iters", "2000", "--views", "4", "--out", str(out)]
            + (["--depth-pose", "identity"] if case["sensor"] else []))


# --------------------------------------------------------------------------------------
# Pixels that are not square.

def test_a_squeezed_image_is_resampled_to_square_pixels(icl, tmp_path):
    case = _case(tmp_path / "sq", icl, "sensor", 0.5)
    assert case["K"][0, 0] == pytest.approx(icl.K[0, 0] / 2)
    pair = UI.load_inputs(case["root"] / "image.png", case["root"] / "cloud.ply", case["K"], depth_pose=np.eye(4),
                          image_depth=case["root"] / "depth.png")
    assert pair.image_size == (480, 640) and pair.depth_gt.shape == (480, 640)
    np.testing.assert_allclose(pair.K_image, icl.K, atol=1e-9)  # the original camera, to the pixel
    np.testing.assert_allclose(pair.K_depth, icl.K, atol=1e-9)
    assert tuple(pair.depth_size) == (480, 640)  # the depth camera was the image's: resampled with it
    assert any("pixels are not square" in n and "320 x 480 to 640 x 480" in n for n in pair.meta["notes"])
    # The resampled image is the original frame again, up to the detail the squeeze lost.
    diff = np.abs(pair.image.astype(float) - icl.rgb(I).astype(float)).mean()
    assert diff < 6, diff
    valid = (pair.depth_gt > 0) & (icl.depth(I) > 0)
    assert np.median(np.abs(pair.depth_gt[valid] - icl.depth(I)[valid])) < 0.01


def test_square_pixels_keep_the_image_and_a_wild_aspect_is_refused(icl):
    image, K, depth = icl.rgb(I), icl.K, icl.depth(I)
    same = IC.square_pixels(image, K, depth)
    assert same[0] is image and same[2] is depth and same[3] == ""
    tall = cameras.scale_intrinsics(K, 1.0, 0.5)  # fy halved: rows are upsampled
    img2, K2, d2, note = IC.square_pixels(image[::2], tall, depth[::2])
    assert img2.shape[:2] == (480, 640) and d2.shape == (480, 640) and K2[0, 0] == pytest.approx(K2[1, 1])
    assert "240 to 640 x 480" in note
    with pytest.raises(InputError, match=r"^--K: fx = 525 and fy = 105 px differ 5 times; expected about equal"):
        IC.square_pixels(image, cameras.intrinsics(525, 105, 319.5, 239.5), depth)


@pytest.mark.parametrize("seed", [1, 5])
def test_a_learned_depth_model_reads_a_squeezed_image_badly_and_the_resampled_one_well(seed):
    # Why the command resamples: ZoeDepth's processor keeps the aspect ratio it is given, so it sees a
    # room squeezed to half its width. The micro ZoeDepth (same processor, learned weights, CPU) on
    # synthetic rooms 0-5 when written: median AbsRel 0.083 original, 0.283 squeezed, 0.085 resampled.
    backend = get_backend("micro", config_for("demo"), device="cpu")
    pair = synthetic.make_pair("indoor", seed=seed)
    H, W = pair.image_size
    image = cv2.resize(pair.image, (W // 2, H), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(pair.depth_gt, (W // 2, H), interpolation=cv2.INTER_NEAREST)
    back, _, _, _ = IC.square_pixels(image, cameras.scale_intrinsics(pair.K_image, 0.5, 1.0), None)

    def absrel(pred, gt):
        valid = gt > 0
        return float(np.median(np.abs(pred[valid] - gt[valid]) / gt[valid]))

    original = absrel(backend.mono_depth(pair.image), pair.depth_gt)
    squeezed = absrel(backend.mono_depth(image), depth)
    resampled = absrel(backend.mono_depth(back), pair.depth_gt)
    assert squeezed > 3 * original and resampled < 1.3 * original + 0.01, (original, squeezed, resampled)


@pytest.mark.parametrize("kind", ["sensor", "world"])
def test_the_squeezed_frame_registers_within_the_originals_bound(icl, tmp_path, capsys, monkeypatch, kind):
    # The command still draws its figures, but does not render them to PNG: rendering and
    # compacting them was ~40 % of each run's CPU, and the saved figures are test_register's.
    drawn = []
    monkeypatch.setattr(plots, "save", lambda fig, name, folder: drawn.append(name) or Path(folder) / f"{name}.png")
    errors = {}
    for factor in (1.0, 0.5):
        case = _case(tmp_path / f"{kind}_{factor}", icl, kind, factor)
        out = tmp_path / f"out_{factor}"
        assert cli.main(_argv(case, out)) == 0, capsys.readouterr().err
        text = capsys.readouterr().out
        if factor != 1.0:
            assert "resampled from 320 x 480 to square pixels" in text and "pixels are not square" in text
        doc = json.loads((out / "registration.json").read_text())
        errors[factor] = doc["ground_truth"]
        assert doc["registered"] and doc["ground_truth"]["registered_gt"], (factor, doc["ground_truth"])
    for factor, e in errors.items():
        assert e["RE"] < BOUND[0] and e["TE"] < BOUND[1], (factor, errors)
    assert drawn == ["matches", "overlay"] * 2


# --------------------------------------------------------------------------------------
# Intrinsics out of order.

@pytest.fixture(scope="module")
def small(tmp_path_factory, icl):
    """Quarter-size frame 10 against frame 40's cloud: 160 x 120, fx = fy = 131.25, (cx, cy) = (79.5, 59.5)."""
    pair = PF.downscale_pair(icl.pair(10, 40), 0.25)
    return PF.write_user_files(pair, tmp_path_factory.mktemp("own_cameras")), pair.K_image


def _error(argv: list[str], capsys) -> str:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def _files(paths, image=None, depth=None) -> list[str]:
    return ["register", str(image or paths["image"]), str(paths["cloud"]), "--image-depth",
            str(depth or paths["image_depth"]), "--backend", "stub", "--ransac-iters", "10", "--views", "1"]


def test_the_brief_example_names_k_not_depth_size(tmp_path, capsys):
    # A 640 x 480 image given --K 585 585 240 320 (fx fy cy cx).
    img = tmp_path / "image.png"
    cv2.imwrite(str(img), np.zeros((480, 640, 3), np.uint8))
    PF.write_ply(tmp_path / "cloud.ply", np.random.default_rng(0).uniform(-1, 1, (500, 3)) + [0, 0, 3])
    err = _error(["register", str(img), str(tmp_path / "cloud.ply"), "--K", "585", "585", "240", "320", "--backend",
                  "stub", "--out", str(tmp_path / "o")], capsys)
    assert "--K: cx, cy look swapped" in err and "--K 585 585 320 240" in err and "depth" not in err


def test_swapped_cx_cy_on_a_wide_image_are_named_not_called_outside(small, tmp_path, capsys):
    paths, K = small
    wide, wide_d = tmp_path / "wide.png", tmp_path / "wide_d.png"
    cv2.imwrite(str(wide), cv2.imread(str(paths["image"]))[30:90])  # 160 x 60: cy of the swap is 79.5 > 60
    cv2.imwrite(str(wide_d), cv2.imread(str(paths["image_depth"]), cv2.IMREAD_UNCHANGED)[30:90])
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2] - 30
    err = _error(_files(paths, wide, wide_d) + ["--K", *map(str, (fx, fy, cy, cx)), "--out", str(tmp_path / "o")],
                 capsys)
    assert "--K: cx, cy look swapped" in err and f"--K {fx:g} {fy:g} {cx:g} {cy:g}" in err and "outside" not in err


def test_the_principal_point_given_first_is_named(small, tmp_path, capsys):
    paths, K = small
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    err = _error(_files(paths) + ["--K", *map(str, (cx, cy, fx, fy)), "--out", str(tmp_path / "o")], capsys)
    assert "--K: the principal point looks given first" in err and f"--K {fx:g} {fy:g} {cx:g} {cy:g}" in err


def test_a_swapped_depth_k_beside_the_images_size_is_named(small, tmp_path, capsys):
    paths, K = small
    fx, fy, cx, cy = (f"{v:g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    base = _files(paths) + ["--K", fx, fy, cx, cy, "--depth-pose", "identity", "--out", str(tmp_path / "o")]
    err = _error(base + ["--depth-K", fx, fy, cy, cx, "--depth-size", "160", "120"], capsys)
    assert err.startswith("freereg register: error: --depth-K: cx, cy look swapped") and f"{fx} {fy} {cx} {cy}" in err
    # A size given H W beside a right --depth-K is still named as the size, with the other reading.
    err = _error(base + ["--depth-K", fx, fy, cx, cy, "--depth-size", "120", "160"], capsys)
    assert "--depth-size is W H (width first); you gave H W?" in err and "--depth-size 160 120 fits it" in err
