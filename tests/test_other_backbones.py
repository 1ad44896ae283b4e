"""The other-backbones path (freereg_lib.training.other_backbones): tiny DINOv2 / CLIP feature maps on
the patch grid, the depth-as-RGB image, the missing-weights line, and the pipeline's matching on them."""
from __future__ import annotations

import numpy as np
import pytest

from freereg_lib.config import FreeRegConfig
from freereg_lib.models import MissingWeightsError
from freereg_lib.training import other_backbones as ob


@pytest.fixture(scope="module")
def tiny():
    cfg = FreeRegConfig()
    return {kind: ob.load_backbone(kind, "tiny", cfg) for kind in ("dinov2", "clip")}


@pytest.mark.parametrize("kind, image_hw, short_side, grid", [
    ("dinov2", (48, 64), 56, (4, 5)),     # 56 x 74.7 -> 56 x 70 pixels: 4 x 5 patches of 14
    ("dinov2", (60, 30), 28, (4, 2)),     # 56 x 28 pixels
    ("clip", (48, 64), 64, (4, 5)),       # 64 x 85.3 -> 64 x 80 pixels: 4 x 5 patches of 16
    ("clip", (100, 100), 48, (3, 3)),
])
def test_tiny_maps_follow_the_patch_grid(tiny, kind, image_hw, short_side, grid):
    bb = tiny[kind]
    bb.short_side = short_side
    img = np.random.default_rng(0).integers(0, 256, image_hw + (3,), dtype=np.uint8)
    fmap = bb(img)
    assert fmap.shape == (bb.model.config.hidden_size,) + grid
    assert bb.grid(image_hw) == grid
    assert fmap.dtype == np.float32 and np.isfinite(fmap).all()
    # A float image in 0..1 is the same picture as its uint8.
    np.testing.assert_allclose(bb(img.astype(np.float32) / 255), fmap, atol=1e-4)


def test_a_patch_token_reads_its_own_part_of_the_image(tiny):
    """Features map back to pixels: changing the top-left corner changes the top-left token most
    (the CLS token is dropped, the grid is not transposed, nothing is cropped)."""
    bb = tiny["dinov2"]
    bb.short_side = 56
    img = np.full((56, 70, 3), 128, dtype=np.uint8)
    a = bb(img)
    img[:14, :14] = 255
    change = np.linalg.norm(bb(img) - a, axis=0)
    assert np.unravel_index(change.argmax(), change.shape) == (0, 0)


def test_depth_as_rgb_of_a_hand_made_map():
    # 2nd / 85th percentiles of [0, 1, 2, 3, 4]: 0.08 and 3.4; x = 1 - (d - 0.08) / 3.32; 255 x clipped, truncated.
    depth = np.array([[0.0, 1.0, 2.0, 3.0, 4.0]])
    out = ob.depth_as_rgb(depth)
    assert out.shape == (1, 5, 3) and out.dtype == np.uint8
    expected = [255, 184, 107, 30, 0]  # 255, 184.34, 107.53, 30.72, -46.1
    assert out[0, :, 0].tolist() == expected
    assert (out[..., 0] == out[..., 1]).all() and (out[..., 1] == out[..., 2]).all()


def test_input_hw_resizes_the_whole_image_to_whole_patches():
    assert ob.input_hw((480, 640), 14, 448) == (448, 602)
    assert ob.input_hw((480, 640), 16, 224) == (224, 304)
    assert ob.input_hw((10, 10), 14, 1) == (14, 14)


def test_missing_weights_give_one_clear_line(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty_cache"))
    with pytest.raises(MissingWeightsError) as err:
        ob.load_backbone("dinov2", "real", FreeRegConfig(), weights_dir=tmp_path / "nowhere")
    msg = str(err.value)
    assert "\n" not in msg
    assert "facebook/dinov2-base" in msg and str(tmp_path / "nowhere" / "dinov2-base") in msg
    assert "download" in msg
    with pytest.raises(ValueError, match="unknown backbone"):
        ob.load_backbone("sam", "tiny")


def test_backbone_features_match_a_pair_through_the_pipeline(tiny):
    """A synthetic pair whose 'depth side' is the image itself: the backbone sees the same picture on
    both sides, so the pipeline's joint PCA, sampling and mutual nearest neighbours pair every
    keypoint with itself."""
    from freereg_lib import pipeline
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    cfg = FreeRegConfig(keypoint_grid=(6, 8))
    pair = synthetic.make_pair("indoor", seed=4049 * 1_000_003, image_size=(48, 64))
    view = pipeline.depth_view(pair, cfg)
    bb = tiny["clip"]
    bb.short_side = 64
    fmap = bb(pair.image)
    feats = ob.backbone_features(pair, ({0: fmap}, {0: fmap.copy()}), get_backend("stub", cfg), cfg, view=view,
                                 mono=pair.depth_gt)
    assert feats.diff_image.shape[1] == feats.diff_depth.shape[1] == fmap.shape[0]
    m = pipeline.match(feats, 1.0)
    assert tuple(pair.image_size) == tuple(pair.depth_size) and len(feats.uv_depth) > 10
    # Every depth keypoint is matched, to the image keypoint at its own pixel, and nothing else is.
    assert len(m) == len(feats.uv_depth)
    np.testing.assert_array_equal(feats.uv_image[m.idx_image], feats.uv_depth[m.idx_depth])


def test_standin_maps_are_the_rgb_branch_on_the_depth_image():
    """The stand-in's maps are the backend's RGB maps of depth_as_rgb(view.dense) (notebook 01's row)."""
    from freereg_lib import pipeline
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    cfg = FreeRegConfig()
    backend = get_backend("stub", cfg)
    pair = synthetic.make_pair("indoor", seed=4049 * 1_000_003 + 1, image_size=(48, 64))
    view = pipeline.depth_view(pair, cfg)
    got = ob.standin_maps(pair, view, backend, cfg.layers)
    hints = pipeline.scene_hints(pair, view)[1]
    want = backend.diffusion_rgb_batch([ob.depth_as_rgb(view.dense)], [hints], cfg.layers)[0]
    assert sorted(got) == sorted(want) == sorted(cfg.layers)
    for k in got:
        np.testing.assert_array_equal(got[k], want[k])


def test_summarize_and_tests_on_made_up_rows():
    recs = []
    for k in range(6):
        rows = []
        for name in ob.ROWS:
            good = name.startswith("freereg")
            for s in ob.SOLVERS:
                rows.append({"row": name, "solver": s, "n_matches": 10, "IR": 0.4 if good else 0.01, "IN": 4 if good else 0,
                             "RE": 1.0, "TE": 0.1, "registered": good and k % 2 == 0, "n_evaluable": 10, "error": ""})
        recs.append({"k": k, "label": "test", "seconds": 1.0, "load_average": 1.0, "seconds_parts": {}, "rows": rows})
    res = ob.summarize(recs, "test")
    assert res["n_pairs"] == 6
    assert res["results"]["standin kabsch"]["IR"]["mean"] == pytest.approx(1.0)
    assert res["results"]["freereg kabsch"]["FMR"]["mean"] == pytest.approx(100.0)
    assert res["tests"]["IR: standin - freereg"]["diff"] == pytest.approx(-39.0)
    assert res["tests"]["IR: standin - freereg"]["p"] < 0.05
    assert "standin kabsch" in ob.report(res)


def test_pair_rows_on_the_stub_give_every_row_and_solver():
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    cfg = FreeRegConfig(ransac_iters=200)
    backend = get_backend("stub", cfg)
    pair = synthetic.make_pair("indoor", seed=4049 * 1_000_003 + 2, image_size=(60, 80))
    rows, sec = ob.pair_rows(pair, backend, cfg)
    assert [(r["row"], r["solver"]) for r in rows] == [(n, s) for n in ob.ROWS for s in ob.SOLVERS]
    assert all(not r["error"] or "matches" in r["error"] for r in rows), [r["error"] for r in rows]
    assert "stand-in diffusion" in sec
    # The stand-in alone skips the depth branch.
    rows, sec = ob.pair_rows(pair, backend, cfg, rows=("standin",), solvers=("kabsch",))
    assert [r["row"] for r in rows] == ["standin"] and "image diffusion" in sec


def test_real_weights_load_from_the_weights_folder_with_its_normalisation(tiny, tmp_path):
    """A folder laid out as the download command makes it (<weights_dir>/<name>) is found and loaded
    with from_pretrained, and its preprocessor_config.json's mean / std replace the kind's."""
    import json

    folder = tmp_path / "clip-vit-base-patch16"
    tiny["clip"].model.save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(json.dumps({"image_mean": [0.5, 0.5, 0.5],
                                                                 "image_std": [0.25, 0.25, 0.25]}))
    bb = ob.load_backbone("clip", "real", FreeRegConfig(), weights_dir=tmp_path, short_side=64)
    assert bb.mean == (0.5, 0.5, 0.5) and bb.std == (0.25, 0.25, 0.25) and bb.backend == "real"
    img = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    assert bb(img).shape == (32, 4, 5)
