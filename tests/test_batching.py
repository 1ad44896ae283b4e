"""Batched diffusion features: several pairs per model call, the UNet stopped after
the last chosen layer, and a pipeline whose rows do not depend on the batch size."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from freereg_lib import config_for, pipeline
from freereg_lib.commands.cache import CachedBackend  # noqa: E402
from freereg_lib.data import synthetic
from freereg_lib.data.pair import UnreadablePair  # noqa: E402
from freereg_lib.geometry import cameras  # noqa: E402
from freereg_lib.models import get_backend  # noqa: E402

SMALL = (64, 128)
# A fast solver, and 12 x 16 keypoints instead of 32 x 44: matching and descriptors were most of
# the stub runs' CPU, and batching is about the model calls (the rows still mix registered and
# failed pairs).
CFG = config_for("synthetic_indoor", ddim_steps=5, ransac_iters=2000, keypoint_grid=(12, 16))


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def tiny():
    return get_backend("tiny", CFG, device="cpu", resize_hw=SMALL)


@pytest.fixture(scope="module")
def inputs():
    rng = np.random.default_rng(7)
    images = [(rng.random((48, 64, 3)) * 255).astype(np.uint8) for _ in range(3)]
    v, u = np.mgrid[0:48, 0:64]
    depths = [1.0 + 0.02 * u + k * 0.3 + 0.01 * v * k for k in range(3)]
    return images, depths


@pytest.fixture(scope="module")
def pairs():
    return [synthetic.make_pair("indoor", seed=s, image_size=(96, 128)) for s in range(3)]


def _assert_maps_close(a: dict, b: dict, rtol=1e-4, atol=1e-5):
    assert sorted(a) == sorted(b)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=rtol, atol=atol, err_msg=f"layer {k}")


def test_tiny_batch_equals_single_calls(tiny, inputs):
    images, depths = inputs
    rgb = tiny.diffusion_rgb_batch(images)
    dep = tiny.diffusion_depth_batch(depths)
    assert len(rgb) == len(dep) == 3
    for k in range(3):
        _assert_maps_close(rgb[k], dict(enumerate(tiny.diffusion_rgb(images[k]))))
        _assert_maps_close(dep[k], dict(enumerate(tiny.diffusion_depth(depths[k]))))
    # Different inputs give different features: the batch does not mix or repeat items.
    assert not np.allclose(dep[0][6], dep[1][6])
    assert not np.allclose(rgb[0][6], rgb[2][6])


def test_layer_choice_stops_the_unet_after_the_last_layer(tiny, inputs):
    images, depths = inputs
    up2 = tiny.diffusion.unet.up_blocks[2]
    calls = []
    handle = up2.register_forward_pre_hook(lambda m, a: calls.append(1))
    try:
        some = tiny.diffusion_rgb_batch(images[:2], layers=(0, 4, 6))
        assert calls == []  # layer 6 is up_blocks[1]'s output: up_blocks[2] never runs
        tiny.diffusion_rgb_batch(images[:1], layers=(8,))
        assert calls == [1]  # layer 8 lies inside up_blocks[2]
        tiny.diffusion_depth_batch(depths[:1], layers=(0, 4, 6))
        assert len(calls) == 1 + 8  # the 4 guided DDIM steps x 2 run whole; the feature pass stops
    finally:
        handle.remove()
    full = tiny.diffusion_rgb_batch(images[:2])
    for k in range(2):
        assert sorted(some[k]) == [0, 4, 6]
        _assert_maps_close(some[k], {i: full[k][i] for i in (0, 4, 6)}, rtol=0, atol=0)


def test_bad_layer_choice_is_a_clear_error(tiny, inputs):
    with pytest.raises(ValueError, match="layers must be"):
        tiny.diffusion_rgb_batch(inputs[0][:1], layers=(9,))


def test_stub_layer_subset_equals_the_full_set(pairs):
    be = get_backend("stub", CFG)
    pair = pairs[0]
    view = pipeline.depth_view(pair, CFG)
    full_img, full_dep = pipeline.diffusion_maps(pair, view, be)
    [(img, dep)] = pipeline.diffusion_maps_batch([pair], [view], be, layers=(6, 0))
    assert sorted(img) == sorted(dep) == [0, 6]
    for k in (0, 6):
        np.testing.assert_array_equal(img[k], full_img[k])
        np.testing.assert_array_equal(dep[k], full_dep[k])


def _same_rows(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        assert ra.keys() == rb.keys()
        for key in ra:
            x, y = ra[key], rb[key]
            if isinstance(x, float) and math.isnan(x):
                assert isinstance(y, float) and math.isnan(y), key
            else:
                assert x == y, (key, x, y)


@pytest.fixture(scope="module")
def items(pairs):
    """The pairs with an unreadable pair and a pair with no usable cloud among them."""
    empty = synthetic.make_pair("indoor", seed=9, image_size=(96, 128))
    # The depth camera turned around: the whole cloud lies behind it.
    empty.T_pc_sensor = empty.T_pc_sensor @ cameras.make_pose(cameras.rotation_about([0, 1, 0], np.pi), [0, 0, 0])
    return [pairs[0], UnreadablePair("missing.ply", FileNotFoundError("missing.ply")), empty, *pairs[1:]]


@pytest.fixture(scope="module")
def one_pair_a_call(items):
    """The stub's rows of ``items``, one pair at a time: what every batched run must give. Each
    pair's rows depend on that pair alone, so the rows of ``pairs`` are among them."""
    return pipeline.run_pairs(items, get_backend("stub", CFG), CFG.override(pair_batch=1), progress=False)


def test_run_pairs_rows_do_not_depend_on_the_batch_size(items, one_pair_a_call):
    """Stub: the same rows, exactly, with batches of 1, 2 and 4 pairs, an unreadable pair and
    a pair with no usable cloud among them."""
    empty = items[2]
    be = get_backend("stub", CFG)
    results = {b: pipeline.run_pairs(items, be, CFG.override(pair_batch=b), progress=False) for b in (2, 4)}
    results[1] = one_pair_a_call
    _same_rows(results[1], results[2])
    _same_rows(results[1], results[4])
    by_pair = {r["pair"]: r for r in results[4]}
    assert "FileNotFoundError" in by_pair["missing.ply"]["error"]
    assert "no point of the cloud projects" in by_pair[empty.name]["error"]
    assert all(r["error"] == "" or not r["registered"] for r in results[4])
    assert sum(r["registered"] for r in results[4]) > 0


def test_run_pairs_batches_the_model_calls(pairs):
    be = get_backend("stub", CFG)
    sizes = []
    real = be.diffusion_depth_batch
    be.diffusion_depth_batch = lambda depths, hints=None, layers=None: (sizes.append(len(depths)), real(depths, hints, layers))[1]
    # One variant that needs the diffusion features: the geometric features and the other
    # solvers do not call the model, and were most of this run's CPU.
    pipeline.run_pairs(iter(pairs), be, CFG.override(pair_batch=2), [("FreeReg-D", "kabsch")],
                       progress=False)  # a generator works too
    assert sizes == [2, 1]
    with pytest.raises(ValueError, match="pair_batch"):
        pipeline.run_pairs(pairs, be, CFG.override(pair_batch=0), progress=False)


def test_a_failing_batch_falls_back_to_one_pair_at_a_time(pairs, one_pair_a_call):
    """A batched model call that fails (say, out of GPU memory) costs speed, not rows."""
    be = get_backend("stub", CFG)
    real = be.diffusion_rgb_batch

    def picky(images, hints=None, layers=None):
        if len(images) > 1:
            raise RuntimeError("CUDA out of memory (simulated)")
        return real(images, hints, layers)

    be.diffusion_rgb_batch = picky
    batched = pipeline.run_pairs(pairs, be, CFG.override(pair_batch=3), progress=False)
    names = {p.name for p in pairs}
    single = [r for r in one_pair_a_call if r["pair"] in names]
    _same_rows(batched, single)


def test_tiny_features_of_a_batch_match_single_pairs(tiny, pairs):
    batch = pipeline.compute_features_batch(pairs[:2], tiny, CFG, geometric=False)
    for pair, feats in zip(pairs[:2], batch):
        alone = pipeline.compute_features(pair, tiny, CFG, geometric=False)
        np.testing.assert_allclose(feats.diff_image, alone.diff_image, atol=1e-3)
        np.testing.assert_allclose(feats.diff_depth, alone.diff_depth, atol=1e-3)
        np.testing.assert_allclose(feats.mono_depth, alone.mono_depth, rtol=1e-4)


def test_tiny_zoedepth_batch_equals_single_calls(tiny, inputs):
    images = [*inputs[0][:2], inputs[0][2][:40, :50]]  # two sizes: two model calls
    batch = tiny.mono_depth_batch(images)
    assert [d.shape for d in batch] == [(48, 64), (48, 64), (40, 50)]
    for img, d in zip(images, batch):
        np.testing.assert_allclose(d, tiny.mono_depth(img), rtol=1e-4, atol=1e-6)
    assert not np.allclose(batch[0], batch[1])


def test_cache_serves_batches_and_computes_only_the_misses(tmp_path, inputs):
    images, _ = inputs
    be = get_backend("stub", CFG)
    ids = [np.full(im.shape[:2], k + 1) for k, im in enumerate(images)]
    hints = [{"ids": i} for i in ids]
    cached = CachedBackend(be, tmp_path, {"seed": 0})
    first = cached.diffusion_rgb_batch(images[:1], hints[:1], layers=(0, 4, 6))
    assert (cached.hits, cached.misses) == (0, 1)
    out = cached.diffusion_rgb_batch(images, hints, layers=(4,))
    assert (cached.hits, cached.misses) == (1, 3)
    np.testing.assert_array_equal(out[0][4], first[0][4])
    for k in range(3):
        assert list(out[k]) == [4]
        np.testing.assert_array_equal(out[k][4], be.diffusion_rgb(images[k], ids=ids[k])[4])
    # The single-call entries and the batch entries are the same files.
    assert len(cached.diffusion_rgb(images[2], ids=ids[2])) == 9 and cached.hits == 2


def test_match_on_a_missing_gpu_is_a_clear_error(pairs):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    feats = pipeline.compute_features(pairs[0], get_backend("stub", CFG), CFG)
    with pytest.raises(RuntimeError, match="CUDA is not available"):
        pipeline.match(feats, 0.5, device="cuda")
    rows = pipeline.run_pair(pairs[0], get_backend("stub", CFG), CFG.override(match_device="cuda"))
    assert all("CUDA is not available" in r["error"] for r in rows)


def test_float16_batches_track_float32(tiny, inputs):
    """The dtype CUDA runs in (float16), checked on the CPU: the batched branches run and their
    maps stay within 1 % of float32's (measured ~0.2 %)."""
    images, depths = inputs
    out = {}
    # float32 is the module's backend (the default dtype): one tiny model fewer to build.
    backends = {"float32": tiny, "float16": get_backend("tiny", CFG, device="cpu", dtype="float16", resize_hw=SMALL)}
    for dtype, be in backends.items():
        out[dtype] = (be.diffusion_rgb_batch(images[:2], layers=(0, 6)), be.diffusion_depth_batch(depths[:2], layers=(0, 6)))
    for side in (0, 1):
        for a, b in zip(out["float32"][side], out["float16"][side]):
            for k in (0, 6):
                assert b[k].dtype == np.float32 and np.isfinite(b[k]).all()
                assert np.linalg.norm(a[k] - b[k]) < 0.01 * np.linalg.norm(a[k])
