"""The calibrated "rooms" world and the statistics that compare worlds with real frames."""
from __future__ import annotations

import numpy as np
import pytest

from freereg_lib.config import config_for
from freereg_lib.data import sources
from freereg_lib.data.synthetic import WORLDS, make_pair
from freereg_lib.geometry.cameras import rotation_about
from freereg_lib.models import get_backend
from freereg_lib.training import world_stats as ws

SEED = 7000 * 1_000_003 + 3


def test_a_rooms_pair_is_the_same_for_the_same_seed_and_names_its_world():
    a, b = make_pair("indoor", seed=SEED, world="rooms"), make_pair("indoor", seed=SEED, world="rooms")
    assert a.image.tobytes() == b.image.tobytes() and a.points.tobytes() == b.points.tobytes()
    assert a.name.startswith("synthetic-rooms/") and a.meta["world"] == "rooms"
    assert 0.3 <= a.meta["overlap"] <= 1.0  # 3DMatch's protocol: above 30 %
    blocks = make_pair("indoor", seed=SEED)
    assert blocks.meta["world"] == "blocks" and blocks.name.startswith("synthetic-indoor/")
    assert blocks.points.shape != a.points.shape or not np.array_equal(blocks.points, a.points)


def test_an_unknown_world_or_an_outdoor_rooms_world_is_refused():
    with pytest.raises(ValueError, match="world 'attic'"):
        make_pair("indoor", seed=1, world="attic")
    with pytest.raises(ValueError, match="world 'rooms' for 'outdoor'"):
        make_pair("outdoor", seed=1, world="rooms")
    assert WORLDS == ("blocks", "rooms")


def test_the_rooms_dataset_yields_rooms_pairs():
    (pair,) = list(sources.iter_pairs("synthetic_rooms", 1, seed=7000))
    assert pair.meta["world"] == "rooms" and pair.name == f"synthetic-rooms/seed{7000 * 1_000_003}"


def test_the_geometric_half_registers_a_rooms_pair_with_the_true_depth():
    cfg = config_for("synthetic_rooms", ransac_iters=20_000)
    row = ws.pair_stats(make_pair("indoor", seed=SEED, world="rooms"), get_backend("stub", cfg), cfg)
    assert row["RR_kabsch"] and row["IR"] > 0.2


def test_baseline_reads_a_known_relative_pose():
    T = np.eye(4)
    T[:3, :3] = rotation_about([0.0, 1.0, 0.0], np.radians(30.0))
    T[:3, 3] = [0.3, 0.0, 0.4]
    rot, trans = ws.baseline(T)
    assert rot == pytest.approx(30.0) and trans == pytest.approx(0.5)


def test_depth_segments_count_regions_between_depth_steps():
    depth = np.full((100, 100), 2.0)
    depth[:, 50:] = 3.0  # a step of 1 m: two regions
    depth[10:20, 10:20] = 1.0  # a box in front: a third
    depth[0:1, 0:1] = 0.5  # a single pixel: too small to count
    assert ws.depth_segments(depth) == 3
    depth[:, 50:] = 2.01  # a 1 cm step is one surface
    assert ws.depth_segments(depth) == 2


def test_geometry_stats_tell_a_plane_from_a_sphere():
    g = np.mgrid[0:2:0.01, 0:2:0.01].reshape(2, -1).T
    plane = np.c_[g, np.zeros(len(g))]
    rng = np.random.default_rng(0)
    v = rng.normal(size=(40_000, 3))
    sphere = 0.15 * v / np.linalg.norm(v, axis=1, keepdims=True)
    flat, round_ = ws.geometry_stats(plane), ws.geometry_stats(sphere)
    assert flat["planar_share"] == pytest.approx(1.0) and flat["normal_variation_deg"] < 1.0
    assert round_["planar_share"] < 0.5 and round_["surface_variation"] > 10 * flat["surface_variation"]


def test_texture_stats_of_a_flat_and_a_striped_image():
    flat = np.full((40, 40, 3), 128, np.uint8)
    assert ws.texture_stats(flat) == {"gradient_mean": 0.0, "textured_share": 0.0}
    stripes = flat.copy()
    stripes[:, ::4] = 255
    assert 0.45 < ws.texture_stats(stripes)["textured_share"] <= 0.5  # the two columns beside each stripe


def test_summaries_and_table_name_every_statistic():
    rows = [{**{key: float(k) for key, _, _ in ws.SUMMARY}, "depth_shares": [1.0, 0, 0, 0, 0, 0]} for k in range(4)]
    s = ws.summarize(rows)
    assert s["n_pairs"] == 4 and s["overlap"]["mean"] == pytest.approx(150.0)
    text = ws.table({"a": s, "b": s})
    assert all(label in text for _, label, _ in ws.SUMMARY) and "a (4 pairs)" in text
    assert "| depth shares, 0-1 / 1-2 / 2-3 / 3-4 / 4-5 / 5+ m (%) | 100 / 0 / 0 / 0 / 0 / 0 |" in text


def test_the_rooms_splits_draw_rooms_pairs_and_the_old_splits_blocks_pairs(tmp_path, monkeypatch):
    import json

    from freereg_lib import pipeline
    from freereg_lib.training import evaluate_split
    from freereg_lib.training.splits import DEV, ROOMS_DEV, ROOMS_TEST, SPLITS, TEST

    assert (DEV.world, TEST.world, ROOMS_DEV.world, ROOMS_TEST.world) == ("blocks", "blocks", "rooms", "rooms")
    assert SPLITS["rooms-test"] is ROOMS_TEST and ROOMS_TEST.seed not in (DEV.seed, TEST.seed, ROOMS_DEV.seed)

    def no_features(*args, **kwargs):  # the pair is what is under test, not the models
        raise RuntimeError("features skipped")

    monkeypatch.setattr(pipeline, "compute_features", no_features)
    for name, world in (("rooms-dev", "rooms"), ("dev", "indoor")):
        rows = tmp_path / f"{name}.jsonl"
        evaluate_split.run(name, 1, rows, progress=False)
        (rec,) = [json.loads(line) for line in rows.read_text().splitlines()]
        assert rec["pair"] == f"synthetic-{world}/seed{SPLITS[name].seed * 1_000_003}"


def test_a_rooms_training_camera_inside_furniture_is_drawn_again():
    # Training room 931's third camera stands inside a piece of furniture (no pixel between 0.05
    # and 10 m: its views used to stop the whole render); every view kept sees the room.
    from freereg_lib.training import views

    depth = views._scene_views((931, 4, "rooms"))["depth"]
    lo, hi = views.OPEN_DEPTH_M
    assert np.all(np.mean((depth > lo) & (depth < hi), axis=(1, 2)) >= views.MIN_OPEN_SHARE)
