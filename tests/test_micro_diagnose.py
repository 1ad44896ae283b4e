"""The FreeReg-D decomposition (freereg_lib.training.diagnose): the depth-camera image the renderer
adds, the feature pass on a true image, and its first variant reproducing the pipeline's number;
and the images the ControlNet generates from a depth map (notebook 01's Fig. 2-I)."""
from __future__ import annotations

import numpy as np
import pytest

from freereg_lib.config import FreeRegConfig
from freereg_lib.data import synthetic

SIZE = (60, 80)


def test_depth_camera_image_leaves_the_pair_as_it_was():
    plain = synthetic.make_pair("indoor", seed=3, image_size=SIZE)
    extra = synthetic.make_pair("indoor", seed=3, image_size=SIZE, depth_camera_image=True)
    for field in ("image", "points", "T_pc_sensor", "T_cam_pc", "depth_gt", "point_ids"):
        np.testing.assert_array_equal(getattr(plain, field), getattr(extra, field))
    img = extra.meta["depth_camera_image"]
    assert img.shape == SIZE + (3,) and img.dtype == np.uint8
    # The other camera's view, not the image camera's again.
    assert not np.array_equal(img, extra.image)
    assert "depth_camera_image" not in plain.meta


def test_appearance_seed_recolours_the_same_room_seen_from_the_same_poses():
    plain = synthetic.make_pair("indoor", seed=3, image_size=SIZE, depth_camera_image=True)
    a = synthetic.make_pair("indoor", seed=3, image_size=SIZE, depth_camera_image=True, appearance_seed=1)
    for field in ("points", "T_pc_sensor", "T_cam_pc", "depth_gt", "image_ids", "point_ids", "depth_frame_gt"):
        np.testing.assert_array_equal(getattr(a, field), getattr(plain, field))
    assert not np.array_equal(a.image, plain.image)
    seen = plain.image_ids >= 0
    assert np.abs(a.image[seen].astype(int) - plain.image[seen]).mean() > 5
    np.testing.assert_array_equal(
        synthetic.make_pair("indoor", seed=3, image_size=SIZE, appearance_seed=1).image, a.image)
    b = synthetic.make_pair("indoor", seed=3, image_size=SIZE, appearance_seed=2)
    assert not np.array_equal(b.image, a.image)
    with pytest.raises(ValueError, match="appearance_seed: only an indoor"):
        synthetic.make_pair("outdoor", seed=3, image_size=(32, 104), appearance_seed=1)


@pytest.fixture(scope="module")
def tiny():
    pytest.importorskip("diffusers")
    import torch

    from freereg_lib.models import get_backend

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    # 5 DDIM steps instead of 20 (4 guided steps before the feature pass instead of 17): these
    # tests compare variants made with the same steps, and sampling is most of their time.
    yield get_backend("tiny", FreeRegConfig(ddim_steps=5), device="cpu", resize_hw=(64, 128))
    torch.set_num_threads(n)


def test_the_true_image_pass_is_the_unet_pass_plus_what_the_controlnet_adds(tiny):
    import torch

    D = tiny.diffusion
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (48, 96, 3), dtype=np.uint8)]
    depths = [rng.uniform(0.5, 4.0, (48, 96))]
    plain = D.rgb_batch(images, (0, 4, 6), noise_tag="x")[0]
    guided = D.depth_pass_on_images(images, depths, (0, 4, 6), noise_tag="x")[0]
    assert any(not np.allclose(plain[k], guided[k]) for k in plain)  # the tiny ControlNet is awake
    saved = {k: v.clone() for k, v in D.controlnet.state_dict().items()}
    try:
        with torch.no_grad():  # ControlNet's zero convolutions back at zero: it adds nothing
            for m in [*D.controlnet.controlnet_down_blocks, D.controlnet.controlnet_mid_block]:
                m.weight.zero_()
                m.bias.zero_()
        silent = D.depth_pass_on_images(images, depths, (0, 4, 6), noise_tag="x")[0]
    finally:
        D.controlnet.load_state_dict(saved)
    for k in plain:
        np.testing.assert_array_equal(silent[k], plain[k])
    # Another noise tag is another forward-noise draw.
    other = D.rgb_batch(images, (0,), noise_tag="y")[0]
    assert not np.allclose(other[0], plain[0])


def test_generate_draws_repeatable_images_that_depend_on_the_seed(tiny):
    D = tiny.diffusion
    depth = np.random.default_rng(1).uniform(0.5, 4.0, (48, 96))
    a, b = D.generate(depth, seeds=(0, 1))
    assert a.shape == (64, 128, 3) and a.dtype == np.uint8  # the diffusion input size
    assert not np.array_equal(a, b)
    np.testing.assert_array_equal(D.generate(depth, seeds=(0,))[0], a)
    other = np.random.default_rng(2).uniform(0.5, 4.0, (48, 96))
    assert not np.array_equal(D.generate(other, seeds=(0,))[0], a)  # the hint steers the sampling


def test_depth_side_maps_names_a_pair_without_its_depth_camera_image(tiny):
    from freereg_lib import pipeline
    from freereg_lib.training import diagnose

    pair = synthetic.make_pair("indoor", seed=3, image_size=SIZE)
    view = pipeline.depth_view(pair, FreeRegConfig())
    with pytest.raises(ValueError, match="with_depth_camera_image"):
        diagnose.depth_side_maps(pair, view, view, tiny, (0, 4, 6))
    plain_extra = synthetic.make_pair("indoor", seed=3, image_size=SIZE, depth_camera_image=True)
    with pytest.raises(ValueError, match="re-coloured"):  # the true image alone is not enough
        diagnose.depth_side_maps(plain_extra, view, view, tiny, (0, 4, 6))


def test_the_frame_hint_variant_changes_only_the_hint(tiny):
    from freereg_lib import pipeline
    from freereg_lib.training import diagnose

    cfg = FreeRegConfig()
    # At full size (480 x 640) the 60,000 points fill a fifth of the depth camera's pixels.
    pair = diagnose.render_with_depth_camera_images("indoor", 3)
    view = pipeline.depth_view(pair, cfg)
    frame = diagnose.frame_view(pair, cfg)
    assert (frame.raw > 0).mean() > (view.raw > 0).mean()
    same = diagnose.depth_side_maps(pair, view, view, tiny, (0, 4))[1]
    for k in (0, 4):  # the same hint and noise draw: the pipeline's own maps
        np.testing.assert_array_equal(same["hint_from_frame"][k], same["freereg_d"][k])
    other = diagnose.depth_side_maps(pair, view, frame, tiny, (0, 4))[1]
    assert not np.allclose(other["hint_from_frame"][0], other["freereg_d"][0])
    np.testing.assert_array_equal(other["freereg_d"][0], same["freereg_d"][0])
    pair.depth_frame_gt = None
    with pytest.raises(ValueError, match="depth_frame_gt"):
        diagnose.frame_view(pair, cfg)


def test_the_recoloured_variant_is_the_true_image_pass_on_its_own_image(tiny):
    from freereg_lib import pipeline
    from freereg_lib.training import diagnose

    pair = diagnose.render_with_depth_camera_images("indoor", 3, image_size=SIZE)
    view = pipeline.depth_view(pair, FreeRegConfig())
    maps = diagnose.depth_side_maps(pair, view, view, tiny, (0, 4))[1]
    assert not np.allclose(maps["appearance_redrawn"][0], maps["generation_oracle"][0])
    pair.meta["depth_camera_image_redrawn"] = pair.meta["depth_camera_image"]
    same = diagnose.depth_side_maps(pair, view, view, tiny, (0, 4))[1]
    for k in (0, 4):  # the same image, hint and forward noise: the same maps
        np.testing.assert_array_equal(same["appearance_redrawn"][k], same["generation_oracle"][k])


def test_the_first_variant_is_the_pipelines_freereg_d():
    pytest.importorskip("diffusers")
    from freereg_lib.training import diagnose, evaluate

    # Both runs at 5 DDIM steps instead of 20 (as the tiny fixture): the three DDIM samplings
    # (FreeReg-D in each run, the frame hint's) are most of the time.
    ours = diagnose.diagnose(1, 2026, progress=False, ddim_steps=5)
    assert ours["config_changes"] == {"ddim_steps": 5}
    theirs = evaluate.evaluate(1, 2026, progress=False, which=("trained",), ddim_steps=5)
    assert ours["freereg_d"]["IR_per_pair"] == theirs["trained"]["IR_per_pair"]
    for name in diagnose.VARIANTS:
        assert 0.0 <= ours[name]["IR"] <= 100.0


def test_card_lists_the_decomposition_as_run(tmp_path):
    import json

    from freereg_lib.training import card

    assert card._diagnoses(tmp_path) == []
    run = {"n_pairs": 100, "seed": 2026, "noise_seed": None, "weights": "committed",
           "freereg_d": {"IR": 8.5, "IR_ci": [5.8, 11.7]}, "generation_oracle": {"IR": 27.0, "IR_ci": [22.3, 32.2]},
           "same_modality": {"IR": 36.3, "IR_ci": [31.2, 41.8]},
           "p_freereg_d_vs_generation_oracle": 1 / 20001, "p_generation_oracle_vs_same_modality": 0.0123}
    (tmp_path / "diagnose_100pairs_noise0.json").write_text(json.dumps(run))  # a run before the frame hint
    run = {**run, "noise_seed": 2, "hint_from_frame": {"IR": 9.0, "IR_ci": [6.0, 12.5]},
           "p_freereg_d_vs_hint_from_frame": 0.25}
    (tmp_path / "diagnose_100pairs_noise2.json").write_text(json.dumps(run))
    run = {**run, "noise_seed": 3, "appearance_redrawn": {"IR": 20.0, "IR_ci": [16.0, 24.5]},
           "p_freereg_d_vs_appearance_redrawn": 0.002, "p_appearance_redrawn_vs_generation_oracle": 0.5}
    (tmp_path / "diagnose_100pairs_noise3.json").write_text(json.dumps(run))
    rows = [line for line in card._diagnoses(tmp_path) if line.startswith("| 100")]
    assert rows == ["| 100 (2026) | default | committed | 8.5 [5.8, 11.7] | - | - | 27.0 [22.3, 32.2] | "
                    "36.3 [31.2, 41.8] | - | < 0.0001 | - | - | = 0.0123 |",
                    "| 100 (2026) | 2 | committed | 8.5 [5.8, 11.7] | 9.0 [6.0, 12.5] | - | 27.0 [22.3, 32.2] | "
                    "36.3 [31.2, 41.8] | = 0.2500 | < 0.0001 | - | - | = 0.0123 |",
                    "| 100 (2026) | 3 | committed | 8.5 [5.8, 11.7] | 9.0 [6.0, 12.5] | 20.0 [16.0, 24.5] | "
                    "27.0 [22.3, 32.2] | 36.3 [31.2, 41.8] | = 0.2500 | < 0.0001 | = 0.0020 | = 0.5000 | = 0.0123 |"]


def test_with_depth_camera_image_renders_the_same_pair_again():
    from freereg_lib.training import diagnose

    pair = synthetic.make_pair("indoor", seed=5, image_size=SIZE, overlap=(0.2, 0.9))
    again = diagnose.with_depth_camera_image(pair)
    np.testing.assert_array_equal(again.points, pair.points)
    np.testing.assert_array_equal(again.image, pair.image)
    assert again.meta["depth_camera_image"].shape == SIZE + (3,)
    redrawn = again.meta["depth_camera_image_redrawn"]
    assert redrawn.shape == SIZE + (3,) and not np.array_equal(redrawn, again.meta["depth_camera_image"])
    np.testing.assert_array_equal(diagnose.recoloured(pair).image, synthetic.make_pair(
        "indoor", seed=5, image_size=SIZE, overlap=(0.2, 0.9), appearance_seed=diagnose.appearance_seed(5)).image)
    outdoor = synthetic.make_pair("outdoor", seed=1, image_size=(32, 104))
    for render in (diagnose.with_depth_camera_image, diagnose.recoloured):
        with pytest.raises(ValueError, match="outdoor pair has no colouring"):
            render(outdoor)
    pair.meta = {"dataset": "3dmatch"}
    with pytest.raises(ValueError, match="only a synthetic pair"):
        diagnose.with_depth_camera_image(pair)
