"""The feature cache never serves a stale or corrupt entry.

The key holds the backend's full identity (kind, settings, dtype, device, weights folder and
files, library and backend code); each entry stores its key; a corrupt entry is reported
with its path, removed and computed again.
"""
import os
import warnings
from collections import Counter

import numpy as np
import pytest

from freereg_lib.commands.cache import CachedBackend, backend_identity, feature_params
from freereg_lib.config import config_for
from freereg_lib.models import get_backend


class Fake:
    name = "fake"

    def __init__(self, **settings):
        self.calls = Counter()
        self.__dict__.update(settings)

    def diffusion_rgb(self, image, ids=None):
        self.calls["rgb"] += 1
        return [np.full((2, 3, 4), float(image.sum()) + getattr(self, "noise", 0.0), np.float32)]

    def diffusion_depth(self, depth, ids=None):
        self.calls["depth"] += 1
        return [np.zeros((2, 3, 4), np.float32)]

    def mono_depth(self, image, depth_gt=None):
        self.calls["mono"] += 1
        return np.ones(image.shape[:2])


IMAGE = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)


def _key(backend, tmp_path):
    return CachedBackend(backend, tmp_path, {}).path("diffusion_rgb", (IMAGE, None, None))


def test_stub_noise_tiny_seed_and_dtype_change_the_key(tmp_path):
    cfg = config_for("synthetic_indoor")
    stub = _key(get_backend("stub", cfg), tmp_path)
    assert _key(get_backend("stub", cfg), tmp_path) == stub  # the same backend: the same key
    assert _key(get_backend("stub", cfg, noise=0.5), tmp_path) != stub
    assert _key(get_backend("stub", cfg, texture_noise=1.0), tmp_path) != stub
    pytest.importorskip("torch")
    tiny = _key(get_backend("tiny", cfg, device="cpu"), tmp_path)
    assert _key(get_backend("tiny", cfg, device="cpu", seed=1), tmp_path) != tiny
    assert _key(get_backend("tiny", cfg, device="cpu", dtype="float16"), tmp_path) != tiny
    assert backend_identity(get_backend("tiny", cfg, device="cpu"))["settings"]["device"] == "cpu"


def test_device_weights_folder_and_weight_files_change_the_key(tmp_path):
    weights = tmp_path / "weights"
    (weights / "unet").mkdir(parents=True)
    (weights / "unet" / "model.safetensors").write_bytes(b"x" * 100)
    base = _key(Fake(device="cpu", weights_dir=weights), tmp_path)
    assert _key(Fake(device="cuda:0", weights_dir=weights), tmp_path) != base
    other = tmp_path / "other"
    other.mkdir()
    assert _key(Fake(device="cpu", weights_dir=other), tmp_path) != base
    (weights / "unet" / "model.safetensors").write_bytes(b"y" * 101)  # new weights in the same folder
    assert _key(Fake(device="cpu", weights_dir=weights), tmp_path) != base
    identity = backend_identity(Fake(device="cpu", weights_dir=weights))
    assert identity["weights"][str(weights / "unet" / "model.safetensors")][0] == 101
    assert identity["library"] and identity["code"] and identity["class"].endswith("Fake")


def test_a_stale_entry_of_other_settings_is_not_served(tmp_path):
    a = Fake(noise=1.0)
    first = CachedBackend(a, tmp_path, feature_params(config_for("3dmatch"))).diffusion_rgb(IMAGE)
    b = Fake(noise=2.0)
    second = CachedBackend(b, tmp_path, feature_params(config_for("3dmatch"))).diffusion_rgb(IMAGE)
    assert b.calls["rgb"] == 1  # computed, not read from the first backend's entry
    again = CachedBackend(Fake(noise=1.0), tmp_path, feature_params(config_for("3dmatch")))
    assert np.array_equal(again.diffusion_rgb(IMAGE)[0], first[0]) and again.hits == 1
    assert not np.array_equal(first[0], second[0])


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "another key"])
def test_a_corrupt_entry_is_reported_removed_and_recomputed(tmp_path, damage):
    fake = Fake()
    cached = CachedBackend(fake, tmp_path, {})
    want = cached.diffusion_rgb(IMAGE)
    path = cached.path("diffusion_rgb", (IMAGE, None, None))
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00" * 64)
    elif damage == "empty":
        path.write_bytes(b"")
    else:  # a valid entry of another input, copied under this name
        other = cached.path("diffusion_rgb", (IMAGE + 1, None, None))
        cached.diffusion_rgb(IMAGE + 1)
        os.replace(other, path)
    fresh = CachedBackend(fake, tmp_path, {})
    with pytest.warns(RuntimeWarning, match=rf"feature cache: {path} is corrupt .*removed, computing it again"):
        got = fresh.diffusion_rgb(IMAGE)
    assert fresh.repaired == 1 and fresh.misses == 1 and fresh.hits == 0
    assert got[0].shape == want[0].shape
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # repaired: the next read is a plain hit
        again = CachedBackend(fake, tmp_path, {})
        assert np.array_equal(again.diffusion_rgb(IMAGE)[0], got[0]) and again.hits == 1


def test_a_corrupt_entry_in_a_batch_is_recomputed(tmp_path):
    fake = Fake()
    cached = CachedBackend(fake, tmp_path, {})
    cached.diffusion_rgb_batch([IMAGE, IMAGE + 1], layers=[0])
    path = cached.path("diffusion_rgb", (IMAGE + 1, None, None))
    path.write_bytes(b"PK\x03\x04 not a zip")
    fresh = CachedBackend(fake, tmp_path, {})
    with pytest.warns(RuntimeWarning, match=str(path)):
        out = fresh.diffusion_rgb_batch([IMAGE, IMAGE + 1], layers=[0])
    assert fresh.hits == 1 and fresh.misses == 1 and len(out) == 2
