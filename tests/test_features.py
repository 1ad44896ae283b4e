"""PCA reduction, align_corners=True sampling, L2 normalisation and fusion."""
from __future__ import annotations

import numpy as np
import pytest

from freereg_lib.features import (
    fuse,
    l2_normalize,
    pca_reduce,
    resize_bilinear,
    sample_features,
)
from freereg_lib.geometry.cameras import bilinear_sample

SIZES = [(8, 11)] * 3 + [(16, 22)] * 3 + [(32, 44)] * 3


def fake_layers(rng, channels=256, sizes=SIZES):
    return [rng.standard_normal((channels, h, w)).astype(np.float32) for h, w in sizes]


def reference_pca_scores(X, k):
    """Plain SVD PCA of row-normalised X (what the official code computes with eig)."""
    X = X / np.linalg.norm(X, axis=1, keepdims=True)
    Xc = X - X.mean(0)
    _, _, Vt = np.linalg.svd(Xc, full_matrices=False)
    return Xc @ Vt[:k].T


def test_pca_output_is_128_per_layer_and_not_normalised_by_default():
    # The official merge_feat does not normalise the merged map (features are normalised
    # after sampling at the keypoints); normalize=True is the option.
    rng = np.random.default_rng(0)
    src, tgt = fake_layers(rng), fake_layers(rng)
    fs, ft = pca_reduce(src, tgt, layers=(0, 4, 6), dim=128, normalize=True)
    assert fs.shape == ft.shape == (384, 32, 44)
    assert fs.dtype == np.float32
    assert np.allclose(np.linalg.norm(fs, axis=0), 1.0, atol=1e-5)
    assert np.allclose(np.linalg.norm(ft, axis=0), 1.0, atol=1e-5)
    raw_s, _ = pca_reduce(src, tgt, layers=(0, 4, 6), dim=128)
    assert not np.allclose(np.linalg.norm(raw_s, axis=0), 1.0)


def test_pca_fewer_channels_or_pixels_gives_fewer_components():
    rng = np.random.default_rng(1)
    fs, ft = pca_reduce(fake_layers(rng, 64), fake_layers(rng, 64), layers=(0, 6), dim=128)
    assert fs.shape == (128, 32, 44)  # 64 + 64
    tiny = [(2, 3)] * 3 + [(4, 6)] * 3 + [(8, 12)] * 3
    fs, ft = pca_reduce(fake_layers(rng, 256, tiny), fake_layers(rng, 256, tiny),
                        layers=(0, 4), dim=128)
    assert fs.shape == (12 + 48, 4, 6)  # 2*6 pixels for layer 0, 2*24 for layer 4


@pytest.mark.parametrize("channels,size", [(256, (8, 11)), (64, (32, 44))])
def test_pca_is_one_joint_basis(channels, size):
    """Both paths (Gram for N < C, covariance for N >= C) equal a reference SVD PCA fitted on
    source and target pixels together, up to each component's sign."""
    rng = np.random.default_rng(2)
    S = rng.standard_normal((channels, *size))
    T = rng.standard_normal((channels, *size)) + 0.5
    fs, ft = pca_reduce({0: S}, {0: T}, layers=(0,), dim=16, normalize=False)
    X = np.concatenate([S.reshape(channels, -1).T, T.reshape(channels, -1).T])
    ref = reference_pca_scores(X, 16)
    got = np.concatenate([fs.reshape(16, -1).T, ft.reshape(16, -1).T])
    for j in range(16):
        sgn = np.sign(ref[:, j] @ got[:, j])
        assert np.allclose(got[:, j], sgn * ref[:, j], atol=1e-4)
    var = got.var(axis=0)
    assert np.all(np.diff(var) <= 1e-9)  # ordered by explained variance
    # The target's mean offset is visible in the first component: one basis for both sides.
    assert abs(fs[0].mean() - ft[0].mean()) > 0.1


@pytest.mark.parametrize("channels,size", [(256, (8, 11)), (64, (32, 44))])
def test_pca_on_a_torch_device_equals_the_numpy_reference(channels, size):
    """cfg.pca_device: float32 torch (run here on the CPU; on a GPU in use) gives the float64
    NumPy maps up to float32 rounding, with the same signs and order, on both paths."""
    pytest.importorskip("torch")
    rng = np.random.default_rng(4)
    S = rng.standard_normal((channels, *size))
    T = rng.standard_normal((channels, *size)) + 0.5
    ref = pca_reduce({0: S, 4: S[:, ::2, ::2]}, {0: T, 4: T[:, ::2, ::2]}, layers=(0, 4), dim=16)
    got = pca_reduce({0: S, 4: S[:, ::2, ::2]}, {0: T, 4: T[:, ::2, ::2]}, layers=(0, 4), dim=16, device="cpu")
    for r, g in zip(ref, got):
        assert r.shape == g.shape and g.dtype == np.float32
        np.testing.assert_allclose(g, r, atol=2e-4)
    # Rank-deficient data: the components beyond the rank are zero in both.
    low = rng.standard_normal((40, 3)) @ rng.standard_normal((3, 64))  # 40 pixels, 64 channels, rank 3
    maps = {0: low.T.reshape(64, 5, 8)}
    ref0, _ = pca_reduce(maps, maps, layers=(0,), dim=8, normalize=False)
    got0, _ = pca_reduce(maps, maps, layers=(0,), dim=8, normalize=False, device="cpu")
    assert np.abs(got0[3:]).max() == 0 and np.abs(ref0[3:]).max() == 0
    np.testing.assert_allclose(got0[:3], ref0[:3], atol=1e-4)


def test_pca_identical_sides_give_identical_maps():
    rng = np.random.default_rng(3)
    L = fake_layers(rng)
    fs, ft = pca_reduce(L, L, layers=(0, 4, 6))
    assert np.allclose(fs, ft)


def test_resize_bilinear_matches_torch():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(4)
    x = rng.standard_normal((5, 8, 11)).astype(np.float32)
    ref = torch.nn.functional.interpolate(torch.from_numpy(x)[None], size=(32, 44),
                                          mode="bilinear", align_corners=False)[0].numpy()
    assert np.allclose(resize_bilinear(x, (32, 44)), ref, atol=1e-5)


def test_sample_features_matches_align_corners_upsampling():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(5)
    fmap = rng.standard_normal((7, 32, 44)).astype(np.float32)
    H, W = 480, 640
    full = torch.nn.functional.interpolate(torch.from_numpy(fmap)[None], size=(H, W),
                                           mode="bilinear", align_corners=True)[0].numpy()
    # Integer keypoints, the official grid (cell centres of the 32 x 44 grid) and corners.
    sv, su = H // 32, W // 44
    v, u = np.mgrid[0:32, 0:44]
    uv = np.stack([u.ravel() * su + su // 2, v.ravel() * sv + sv // 2], axis=1)
    uv = np.concatenate([uv, [[0, 0], [W - 1, H - 1], [W - 1, 0], [17, 401]]])
    got = sample_features(fmap, uv, (H, W))
    assert got.shape == (len(uv), 7)
    assert np.allclose(got, full[:, uv[:, 1], uv[:, 0]].T, atol=1e-5)
    # Fractional pixels: the bilinear interpolation of the upsampled map.
    uvf = rng.uniform([0, 0], [W - 1, H - 1], (50, 2))
    ref = bilinear_sample(full.transpose(1, 2, 0), uvf)
    assert np.allclose(sample_features(fmap, uvf, (H, W)), ref, atol=1e-5)


def test_l2_normalize():
    x = np.array([[3.0, 4.0], [0.0, 0.0], [1e-7, 0.0]])
    y = l2_normalize(x)
    assert np.allclose(y[0], [0.6, 0.8])
    assert np.all(y[1] == 0)
    assert np.allclose(y[2], [1e-7 / (1e-7 + 1e-5), 0.0])  # x / (|x| + eps), the official form: not blown up


def test_fuse_weights_and_normalisation():
    rng = np.random.default_rng(6)
    fd = rng.standard_normal((10, 384))
    fg = rng.standard_normal((10, 32))
    fg[3] = 0.0  # beyond tau_g
    f = fuse(fd, fg, 0.5)
    assert f.shape == (10, 416)
    assert np.allclose(np.linalg.norm(f[:, :384], axis=1), 0.5)
    n_g = np.linalg.norm(f[:, 384:], axis=1)
    assert np.allclose(np.delete(n_g, 3), 0.5) and n_g[3] == 0
    assert np.allclose(fuse(fd, fg, 1.0)[:, 384:], 0)
    assert np.allclose(np.linalg.norm(fuse(fd, fg, 0.0)[:, 384:][[0, 1]], axis=1), 1.0)
    with pytest.raises(ValueError):
        fuse(fd, fg[:5], 0.5)


def test_pca_sample_fuse_path_is_normalised():
    """PCA -> concatenation -> sampling at keypoints -> fusion: the diffusion part of every
    fused descriptor has norm exactly w (the concatenated 384-d feature is L2-normalised)."""
    rng = np.random.default_rng(7)
    fs, ft = pca_reduce(fake_layers(rng), fake_layers(rng), layers=(0, 4, 6))
    uv = rng.uniform([0, 0], [639, 479], (100, 2))
    fd = sample_features(fs, uv, (480, 640))
    assert fd.shape == (100, 384)
    f = fuse(fd, rng.standard_normal((100, 33)), 0.7)
    assert np.allclose(np.linalg.norm(f[:, :384], axis=1), 0.7, atol=1e-5)
