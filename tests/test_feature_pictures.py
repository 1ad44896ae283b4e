"""The pieces of notebook 07's figures, on hand-made cases whose right answer is known exactly.

* PCA colours of features that are a known 3-D embedding are an affine image of that embedding,
  lie in [0, 1], give identical features identical colours, and come from one basis for all sets;
* a painted picture takes each keypoint's colour within its radius, nothing elsewhere;
* a patch warp with an identity match puts the patch's pixels where they were;
* the oblique view is the camera's own view at elevation 0 and the top view at 90.
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest

from freereg_lib.report import feature_pictures as FP


def _embedding(n=120, c=24, seed=0):
    """Features ``X A + b`` of a known 3-D embedding ``X (n, 3)``; ``A (3, c)`` has orthonormal rows."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 3)) * [3.0, 2.0, 1.0]
    A = np.linalg.qr(rng.normal(size=(c, 3)))[0].T
    return X, X @ A + rng.normal(size=c)


# --------------------------------------------------------------------------------------
# PCA colours.

def test_pca_colours_of_a_3d_embedding_are_its_affine_image_in_the_unit_cube():
    X, F = _embedding()
    (col,) = FP.pca_colours(F, clip=0.0)
    assert col.shape == (len(F), 3) and col.dtype == np.float64
    assert np.all((col >= 0) & (col <= 1))
    np.testing.assert_allclose(col.min(axis=0), 0.0, atol=1e-12)  # clip=0: minimum and maximum span [0, 1]
    np.testing.assert_allclose(col.max(axis=0), 1.0, atol=1e-12)
    # Three components of a 3-D embedding keep all of it: the colours are an affine map of X.
    design = np.hstack([X, np.ones((len(X), 1))])
    coef, *_ = np.linalg.lstsq(design, col, rcond=None)
    np.testing.assert_allclose(design @ coef, col, atol=1e-10)
    assert np.linalg.matrix_rank(coef[:3]) == 3


def test_identical_features_get_identical_colours():
    _, F = _embedding()
    F = np.vstack([F, F[[3, 3, 7]]])
    (col,) = FP.pca_colours(F)
    np.testing.assert_array_equal(col[-3], col[3])
    np.testing.assert_array_equal(col[-2], col[3])
    np.testing.assert_array_equal(col[-1], col[7])
    assert np.all((col >= 0) & (col <= 1))


def test_one_basis_for_all_sets():
    _, F = _embedding()
    (whole,) = FP.pca_colours(F)
    a, b = FP.pca_colours(F[:50], F[50:])
    np.testing.assert_allclose(np.vstack([a, b]), whole, atol=1e-12)
    basis = FP.fit_pca(F[:50], F[50:])
    np.testing.assert_allclose(FP.apply_pca(basis, F[50:]), b, atol=1e-12)
    assert basis.axes.shape == (3, F.shape[1])
    np.testing.assert_allclose(basis.axes @ basis.axes.T, np.eye(3), atol=1e-12)


def test_signs_are_fixed_so_negated_features_give_the_same_colours():
    _, F = _embedding()
    np.testing.assert_allclose(FP.pca_colours(-F)[0], FP.pca_colours(F)[0], atol=1e-12)


def test_rows_without_a_feature_are_nan_and_left_out_of_the_fit():
    _, F = _embedding()
    with_zeros = np.vstack([F, np.zeros((4, F.shape[1]))])
    (col,) = FP.pca_colours(with_zeros)
    assert np.isnan(col[-4:]).all()
    np.testing.assert_allclose(col[:-4], FP.pca_colours(F)[0], atol=1e-12)


def test_a_direction_the_data_lacks_is_mid_grey():
    rng = np.random.default_rng(1)
    F = np.zeros((30, 5))
    F[:, :2] = rng.normal(size=(30, 2))  # a 2-D embedding: no third component
    (col,) = FP.pca_colours(F, clip=0.0)
    np.testing.assert_array_equal(col[:, 2], 0.5)
    assert np.all((col[:, :2] >= 0) & (col[:, :2] <= 1))


# --------------------------------------------------------------------------------------
# Pictures from keypoints.

def test_paint_gives_each_pixel_its_nearest_keypoints_colour_within_the_radius():
    uv = np.array([[2.0, 1.0], [7.0, 4.0]])
    colours = np.array([[1.0, 0.0, 0.0], [np.nan, np.nan, np.nan]])
    pic = FP.paint(uv, colours, (6, 10), radius=1.0, background=0.0)
    assert pic.shape == (6, 10, 3)
    red = np.zeros((6, 10), bool)
    red[1, 1:4] = red[0, 2] = red[2, 2] = True  # pixels within 1 px of (u=2, v=1)
    grey = np.zeros((6, 10), bool)
    grey[4, 6:9] = grey[3, 7] = grey[5, 7] = True
    np.testing.assert_array_equal(pic[red], [[1.0, 0.0, 0.0]] * red.sum())
    np.testing.assert_array_equal(pic[grey], np.full((grey.sum(), 3), FP.GREY))  # no feature: grey
    np.testing.assert_array_equal(pic[~(red | grey)], 0.0)
    mask = np.ones((6, 10), bool)
    mask[1, 2] = False
    assert np.isnan(FP.paint(uv, colours, (6, 10), 1.0, mask=mask, background=np.nan)[1, 2]).all()


def test_sample_picture_and_colour_cloud():
    pic = np.arange(4 * 5 * 3, dtype=np.float64).reshape(4, 5, 3)
    got = FP.sample_picture(pic, np.array([[1.2, 2.8], [4.0, 0.0], [-1.0, 0.0], [np.nan, 1.0]]))
    np.testing.assert_array_equal(got[0], pic[3, 1])
    np.testing.assert_array_equal(got[1], pic[0, 4])
    assert np.isnan(got[2:]).all()
    # A camera with f = 1 at the centre: point (x, y, z) lands on pixel (x / z + 2, y / z + 1.5).
    K = np.array([[1.0, 0, 2], [0, 1.0, 1.5], [0, 0, 1]])
    depth = np.full((4, 5), 2.0)
    pts = np.array([[0.0, 1.0, 2.0],     # seen: pixel (2, 2), depth 2
                    [0.0, 2.0, 4.0],     # behind that surface at the same pixel: hidden
                    [20.0, 0.0, 1.0],    # outside the view
                    [0.0, 0.0, -1.0]])   # behind the camera
    col = FP.colour_cloud(pts, K, pic, depth)
    np.testing.assert_array_equal(col[0], pic[2, 2])
    assert np.isnan(col[1:]).all()


def test_oblique_view_is_the_cameras_view_at_0_and_the_top_view_at_90():
    rng = np.random.default_rng(2)
    p = rng.normal(size=(20, 3))
    xy, d = FP.oblique_view(p, 0.0)
    np.testing.assert_allclose(xy, np.stack([p[:, 0], -p[:, 1]], 1), atol=1e-12)
    np.testing.assert_allclose(d, p[:, 2], atol=1e-12)
    xy, d = FP.oblique_view(p, 90.0)
    np.testing.assert_allclose(xy, p[:, [0, 2]], atol=1e-12)  # ahead is up on the page
    np.testing.assert_allclose(d, p[:, 1], atol=1e-12)        # looking down: depth grows downwards
    xy, d = FP.oblique_view(p, 35.0, 20.0)  # any view is a rotation: lengths are kept
    np.testing.assert_allclose((xy ** 2).sum(1) + d ** 2, (p ** 2).sum(1), atol=1e-12)


# --------------------------------------------------------------------------------------
# Patches.

def test_identity_warp_puts_the_patch_where_it_was():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, size=(60, 80, 3), dtype=np.uint8)
    canvas = np.zeros((60, 80, 3))
    out = FP.warp_patches(image, [[40.0, 30.0]], canvas, [[40.0, 30.0]], size=32)
    np.testing.assert_array_equal(out[14:46, 24:56], image[14:46, 24:56] / 255.0)
    rest = np.ones((60, 80), bool)
    rest[14:46, 24:56] = False
    np.testing.assert_array_equal(out[rest], 0.0)
    np.testing.assert_array_equal(canvas, 0.0)  # the canvas itself is not drawn on


def test_warp_moves_the_patch_and_cuts_it_at_the_borders():
    rng = np.random.default_rng(4)
    image = rng.random((60, 80, 3))
    canvas = np.zeros((50, 70, 3))
    out = FP.warp_patches(image, [[40.0, 30.0]], canvas, [[50.0, 20.0]], size=8)
    np.testing.assert_array_equal(out[16:24, 46:54], image[26:34, 36:44])
    assert np.count_nonzero(out.any(axis=2)) == 64
    # Near the source's corner only the part inside the image exists; it lands at the same offset.
    out = FP.warp_patches(image, [[1.0, 2.0]], canvas, [[30.0, 30.0]], size=8)
    np.testing.assert_array_equal(out[28:34, 29:34], image[0:6, 0:5])
    assert np.count_nonzero(out.any(axis=2)) == 30
    # A destination off the canvas or NaN pastes nothing.
    assert not FP.warp_patches(image, [[40.0, 30.0]] * 2, canvas, [[200.0, 20.0], [np.nan, 1.0]], 8).any()


def test_spaced_keeps_patches_that_do_not_overlap():
    uv = np.array([[0.0, 0.0], [10.0, 0.0], [32.0, 5.0], [np.nan, 0.0], [5.0, 40.0], [31.0, 31.0]])
    np.testing.assert_array_equal(FP.spaced(uv, 32), [0, 2, 4])


# --------------------------------------------------------------------------------------
# Figures: built from arrays, with the panels they promise.

def test_the_figures_have_their_panels():
    rng = np.random.default_rng(5)
    img, dep = rng.random((24, 32, 3)), rng.random((24, 32, 3))
    uv = rng.uniform(0, 20, size=(10, 2))
    ok = rng.random(10) > 0.5
    feats = {k: (img, dep) for k in ("diffusion", "geometric", "fused")}
    fig = FP.pipeline_figure(img, dep, feats, uv, uv, ok, [("estimated pose", img), ("true pose", img)])
    assert len(fig.axes) == 2 + 2 * 3 + 1 + 2
    fig = FP.cloud_features_figure({"diffusion": img, "fused": img}, rng.normal(size=(50, 2)), rng.random(50),
                                   {"diffusion": rng.random((50, 3)), "fused": np.full((50, 3), np.nan)})
    assert len(fig.axes) == 4
    fig = FP.patches_figure(img, uv, [("by the matches", dep, uv), ("true", dep, uv)], ok, size=4)
    assert len(fig.axes) == 3
    case = dict(image=img, depth_picture=dep, uv_image=uv, uv_depth=uv, correct=ok, title="pair")
    assert len(FP.outcomes_figure([case, case, case]).axes) == 4  # two to a row, the spare one blank
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.mark.parametrize("n", [0, 1])
def test_too_few_rows_give_grey_colours_not_an_error(n):
    (col,) = FP.pca_colours(np.arange(1.0, 1.0 + 5 * n).reshape(n, 5))
    assert col.shape == (n, 3)
    np.testing.assert_array_equal(col, 0.5)
