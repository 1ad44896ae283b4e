"""The feature cache: an ablation after the backend does not call the backend again."""
import pickle
from collections import Counter

import numpy as np
import pytest

from freereg_lib.commands.cache import CachedBackend, feature_params
from freereg_lib.config import config_for


class CountingBackend:
    """A stand-in backend: outputs depend on the input arrays; every call is counted."""

    name = "fake"
    label = "fake backend for tests"

    def __init__(self):
        self.calls = Counter()

    def _layers(self, arr) -> list[np.ndarray]:
        rng = np.random.default_rng(int(np.asarray(arr, dtype=np.float64).sum() * 1000) % 2**32)
        return [rng.normal(size=(c, 4, 5)).astype(np.float32) for c in (8, 8, 4)]

    def diffusion_rgb(self, image, ids=None):
        self.calls["rgb"] += 1
        return self._layers(image)

    def diffusion_depth(self, depth, ids=None):
        self.calls["depth"] += 1
        return self._layers(depth)

    def mono_depth(self, image, depth_gt=None):
        self.calls["mono"] += 1
        return image[..., 0].astype(np.float64) / 100.0 + 0.5


def _frames(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [(rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), rng.uniform(0.5, 4, (6, 8))) for _ in range(n)]


def _ablation(backend, frames, weights=(0.0, 0.5, 1.0)):
    """What pipeline.run_pairs does to the backend in an ablation over w: every frame, every w."""
    out = []
    for _w in weights:
        for image, depth in frames:
            out.append((backend.diffusion_rgb(image), backend.diffusion_depth(depth), backend.mono_depth(image)))
    return out


def test_second_ablation_run_reads_everything_from_disk(tmp_path):
    cfg = config_for("3dmatch")
    frames = _frames(3)
    fake = CountingBackend()
    first = _ablation(CachedBackend(fake, tmp_path, feature_params(cfg)), frames)
    assert fake.calls == {"rgb": 3, "depth": 3, "mono": 3}  # once per frame, not per w
    again = CachedBackend(fake, tmp_path, feature_params(cfg))  # a new process, same folder
    second = _ablation(again, frames, weights=(0.25, 0.75))
    assert fake.calls == {"rgb": 3, "depth": 3, "mono": 3}
    assert again.hits == 2 * 3 * 3 and again.misses == 0
    for (r1, d1, m1), (r2, d2, m2) in zip(first, second):
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(r1 + d1, r2 + d2))
        assert m2.dtype == np.float64 and np.array_equal(m1, m2)


def test_params_backend_and_inputs_are_part_of_the_key(tmp_path):
    cfg = config_for("3dmatch")
    frames = _frames(2)
    fake = CountingBackend()
    _ablation(CachedBackend(fake, tmp_path, feature_params(cfg)), frames, weights=(0.5,))
    _ablation(CachedBackend(fake, tmp_path, feature_params(cfg.override(t_hat=300))), frames, weights=(0.5,))
    assert fake.calls == {"rgb": 4, "depth": 4, "mono": 4}
    # Knobs after the backend (w, layers, solver, RANSAC) do not change the key.
    after = cfg.override(fusion_w=0.0, layers=(1, 2, 3), ransac_iters=10, kabsch_inlier_m=1.0)
    assert feature_params(after) == feature_params(cfg)
    other = CountingBackend()
    other.name = "other"
    _ablation(CachedBackend(other, tmp_path, feature_params(cfg)), frames, weights=(0.5,))
    assert other.calls == {"rgb": 2, "depth": 2, "mono": 2}
    cached = CachedBackend(fake, tmp_path, feature_params(cfg))
    image, depth = frames[0]
    cached.mono_depth(image, depth_gt=depth)  # the stub reads depth_gt: it is an input too
    cached.diffusion_rgb(image.copy())        # equal bytes, another array: a hit
    assert cached.misses == 1 and cached.hits == 1


def test_half_storage_is_float32_close_and_the_same_on_both_runs(tmp_path):
    frames = _frames(1)
    fake = CountingBackend()
    a = CachedBackend(fake, tmp_path, {"t_hat": 150}, half=True).diffusion_rgb(frames[0][0])
    b = CachedBackend(fake, tmp_path, {"t_hat": 150}, half=True).diffusion_rgb(frames[0][0])
    exact = fake._layers(frames[0][0])
    assert fake.calls["rgb"] == 1
    for x, y, z in zip(a, b, exact):
        assert x.dtype == np.float32 and np.array_equal(x, y)
        np.testing.assert_allclose(x, z, rtol=2e-3, atol=2e-3)


def test_wrapper_passes_other_attributes_through_and_pickles(tmp_path):
    cached = CachedBackend(CountingBackend(), tmp_path, {})
    assert cached.name == "fake" and cached.label == "fake backend for tests"
    with pytest.raises(AttributeError):
        cached.no_such_attribute
    assert pickle.loads(pickle.dumps(cached)).label == cached.label
