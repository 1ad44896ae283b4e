"""The stub backend: shapes of the real model, semantic + cross-modal consistency,
determinism, its errors, and the monocular-depth error model."""
from __future__ import annotations

import numpy as np
import pytest

from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.models import StubBackend, get_backend
from freereg_lib.models.stub import PAPER_CHANNELS

H, W = 120, 160


def blocks_ids(h=H, w=W):
    """A scene-like id map: 0 (nothing) on top, a floor, and three objects."""
    ids = np.zeros((h, w), np.int32)
    ids[h // 3:, :] = 1
    ids[h // 2:h - 10, 10:50] = 2
    ids[h // 4:h // 2 + 20, 70:110] = 3
    ids[h // 2:, 120:150] = 4
    return ids


def cos(a, b):
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)
    num = (a * b).sum(0)
    den = np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0) + 1e-12
    return num / den


def test_stub_shapes_follow_resize_hw():
    be = get_backend("stub", FreeRegConfig())
    layers = be.diffusion_rgb(np.zeros((H, W, 3), np.uint8), blocks_ids())
    assert [x.shape for x in layers] == [(256, 8, 11)] * 3 + [(256, 16, 22)] * 3 + [
        (256, 32, 44)] + [(128, 32, 44)] * 2
    paper = StubBackend(FreeRegConfig(), channels=PAPER_CHANNELS)
    layers = paper.diffusion_rgb(np.zeros((H, W, 3), np.uint8), blocks_ids())
    assert [x.shape for x in layers] == [(1280, 8, 11)] * 3 + [(1280, 16, 22)] * 3 + [
        (1280, 32, 44)] + [(640, 32, 44)] * 2
    assert all(x.dtype == np.float32 for x in layers)
    out = StubBackend(config_for("kitti"), channels=(32, 32, 16, 8))
    layers = out.diffusion_depth(np.ones((H, W)), blocks_ids())
    assert [x.shape for x in layers] == [(32, 8, 20)] * 3 + [(32, 16, 40)] * 3 + [
        (16, 32, 80)] + [(8, 32, 80)] * 2


def test_stub_features_are_semantic_and_cross_modal():
    be = StubBackend(FreeRegConfig(), noise=0.3)
    ids = blocks_ids()
    rgb = be.diffusion_rgb(np.zeros((H, W, 3), np.uint8), ids)
    dep = be.diffusion_depth(np.ones((H, W)), ids)
    # Same scene: the RGB and depth maps agree (cosine well above chance) but are not equal.
    for layer in (0, 4, 6):
        c = cos(rgb[layer], dep[layer])
        filled = np.linalg.norm(rgb[layer].reshape(rgb[layer].shape[0], -1), axis=0) > 0.5
        assert c[filled].mean() > 0.8
        assert not np.allclose(rgb[layer], dep[layer])
    # Texture layers 7-8 lose the cross-modal consistency.
    assert cos(rgb[8], dep[8]).mean() < cos(rgb[6], dep[6]).mean() - 0.3
    # Different classes give different features: cells of class 2 vs class 3 at layer 6.
    f = rgb[6]
    a = f[:, 24, 8]   # class 2 region (rows 60..110, cols 10..50 in 120x160 -> 32x44 grid)
    b = f[:, 12, 24]  # class 3 region
    assert abs(cos(a[:, None], b[:, None])[0]) < 0.3


def test_stub_deterministic_and_noise_level():
    ids = blocks_ids()
    a = StubBackend(FreeRegConfig()).diffusion_rgb(None, ids)
    b = StubBackend(FreeRegConfig()).diffusion_rgb(None, ids)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    c = StubBackend(FreeRegConfig(seed=1)).diffusion_rgb(None, ids)
    assert not np.allclose(a[6], c[6])
    clean_r = StubBackend(FreeRegConfig(), noise=0.0).diffusion_rgb(None, ids)
    clean_d = StubBackend(FreeRegConfig(), noise=0.0).diffusion_depth(None, ids)
    assert all(np.allclose(x, y) for x, y in zip(clean_r[:7], clean_d[:7]))
    # The noise level is the per-pixel norm of the added noise.
    noisy = StubBackend(FreeRegConfig(), noise=0.35).diffusion_rgb(None, ids)
    noise = noisy[6] - clean_r[6]
    assert np.isclose(np.linalg.norm(noise, axis=0).mean(), 0.35, rtol=0.05)


def test_stub_context_varies_features_inside_a_region():
    """Without context a uniform region has one feature; the context channels (blurred class
    fractions, like a decoder's receptive field) make cells differ by what is around them."""
    ids = blocks_ids()
    flat = StubBackend(FreeRegConfig(), noise=0.0, context=(0.0,)).diffusion_rgb(None, ids)[6]
    ctx = StubBackend(FreeRegConfig(), noise=0.0).diffusion_rgb(None, ids)[6]
    # Two cells of pure floor (class 1) on the 32 x 44 grid: one near the top edge of the
    # floor, one near the bottom of the image.
    for r, c in [(12, 16), (28, 16)]:
        v0, v1 = int(r * 120 / 32), int((r + 1) * 120 / 32)
        u0, u1 = int(c * 160 / 44), int((c + 1) * 160 / 44)
        assert np.all(ids[v0:v1 + 1, u0:u1 + 1] == 1)
    assert np.allclose(flat[:, 12, 16], flat[:, 28, 16])
    assert not np.allclose(ctx[:, 12, 16], ctx[:, 28, 16], atol=1e-3)


def test_stub_requires_ids():
    be = StubBackend(FreeRegConfig())
    with pytest.raises(ValueError, match="synthetic scene"):
        be.diffusion_rgb(np.zeros((H, W, 3), np.uint8))
    with pytest.raises(ValueError, match="synthetic scene"):
        be.diffusion_depth(np.ones((H, W)))
    with pytest.raises(ValueError, match="true depth"):
        be.mono_depth(np.zeros((H, W, 3), np.uint8))


def test_stub_mono_depth_error_model():
    v, u = np.mgrid[0:H, 0:W]
    D = 1.5 + 2.0 * v / H + 0.5 * np.sin(u / 20.0)
    D[:10, :20] = 0.0
    valid = D > 0
    be = StubBackend(FreeRegConfig())
    Z = be.mono_depth(np.zeros((H, W, 3), np.uint8), D)
    assert Z.shape == D.shape and Z.dtype == np.float64
    assert np.all(Z[~valid] == 0) and np.all(Z[valid] > 0)
    err = np.abs(Z - D)[valid].mean()
    assert abs(err - 0.27) < 0.02  # ZoeDepth's reported indoor error
    assert np.array_equal(Z, be.mono_depth(None, D))  # deterministic
    # A global scale error: the best single scale explains a good part of the error.
    s = (Z[valid] * D[valid]).sum() / (D[valid] ** 2).sum()
    assert abs(s - 1.0) > 0.02
    # Smooth: the relative error varies slowly between neighbouring pixels.
    rel = np.where(valid, Z / np.where(valid, D, 1) - 1, np.nan)
    span = np.nanmax(rel) - np.nanmin(rel)
    assert span > 0.05
    assert np.nanmax(np.abs(np.diff(rel, axis=1))) < 0.05 * span
    assert np.nanmax(np.abs(np.diff(rel, axis=0))) < 0.05 * span
    # Chosen size.
    Z2 = StubBackend(FreeRegConfig(), mono_mae=0.1).mono_depth(None, D)
    assert abs(np.abs(Z2 - D)[valid].mean() - 0.1) < 0.01
    Z0 = StubBackend(FreeRegConfig(), mono_mae=0.0).mono_depth(None, D)
    assert np.allclose(Z0, D)
