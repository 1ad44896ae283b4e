"""Pictures of the pipeline's intermediate outputs for the paper's figures that notebook 07 re-draws.

The floats: the pipeline on one pair (Fig. 3, the FreeReg pipeline), features spread on the
point cloud (Fig. 8, semantic properties of FreeReg features), image patches warped by the
matches (Fig. 10, patch warping), and several pairs' correspondences with their verdicts
(Figs. 6 and 9, qualitative and additional qualitative results).

This module owns the pieces those figures are made of:

* a colour basis for descriptors: a 3-component PCA fitted once, with numpy, on several
  feature sets together (:func:`fit_pca`, :func:`apply_pca`, :func:`pca_colours`), so that the
  image side and the cloud side share colours where their descriptors agree;
* pictures painted from per-keypoint colours (:func:`paint`), read back at pixels
  (:func:`sample_picture`) or at the visible points of a cloud (:func:`colour_cloud`);
* an oblique orthographic view of a cloud (:func:`oblique_view`);
* the patch warp (:func:`warp_patches`) and a choice of non-overlapping patches (:func:`spaced`);
* the figures built from them (:func:`pipeline_figure`, :func:`cloud_features_figure`,
  :func:`patches_figure`, :func:`outcomes_figure`).

Functions take arrays and return arrays or new Matplotlib figures; nothing is kept between
calls (a fitted basis is a frozen value the caller holds). Saving is :func:`plots.save` /
:func:`plots.show`. Pixels are ``(u, v)`` = (column, row), as everywhere in the library.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freereg_lib.report.plots import FIG_WIDTH_IN

GREEN = (0.1, 0.8, 0.2)  # a correct match, as plots.draw_matches
RED = (0.9, 0.15, 0.1)   # a wrong one
GREY = 0.55              # a keypoint or point without a feature


def _plt():
    # No backend forced: Jupyter keeps its inline backend, headless runs fall back to Agg.
    import matplotlib.pyplot as plt

    return plt


# --------------------------------------------------------------------------------------
# PCA colours.

@dataclass(frozen=True)
class PcaBasis:
    """A 3-component PCA of descriptors and the range each component is stretched over.

    ``mean (C,) float64``, ``axes (3, C) float64`` (orthonormal rows; zero rows when the data
    has fewer than three directions), ``lo (3,)`` and ``hi (3,)``: the scores mapped to 0 and 1.
    """

    mean: np.ndarray
    axes: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def _has_feature(x: np.ndarray) -> np.ndarray:
    """Rows that are finite and not all zero (a keypoint without a geometric feature is a zero row)."""
    return np.isfinite(x).all(axis=1) & (np.abs(x).sum(axis=1) > 0)


def fit_pca(*feature_sets: np.ndarray, clip: float = 1.0) -> PcaBasis:
    """One PCA basis for all ``feature_sets`` (each ``(N_i, C)``), fitted once on their rows together.

    Rows without a feature (all zeros, or not finite) are left out of the fit. Each axis' sign
    is fixed so that its largest-magnitude score is positive (the same data gives the same
    colours on every run). Scores are stretched so that the ``clip`` and ``100 - clip``
    percentiles of the fitted rows map to 0 and 1 (``clip=0``: minimum and maximum).
    """
    x = np.concatenate([np.asarray(f, dtype=np.float64).reshape(-1, np.shape(f)[-1]) for f in feature_sets])
    x = x[_has_feature(x)]
    C = x.shape[1]
    if len(x) < 2:
        return PcaBasis(np.zeros(C), np.zeros((3, C)), np.zeros(3), np.zeros(3))  # every colour mid-grey
    mean = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    axes = np.zeros((3, C))
    k = min(3, len(s))
    keep = s[:k] > 1e-10 * max(s[0], 1e-300)  # directions the data does not have stay zero, not noise
    axes[:k][keep] = vt[:k][keep]
    scores = (x - mean) @ axes.T
    for j in range(3):
        if np.any(scores[:, j]) and scores[np.argmax(np.abs(scores[:, j])), j] < 0:
            axes[j] = -axes[j]
            scores[:, j] = -scores[:, j]
    lo, hi = np.percentile(scores, clip, axis=0), np.percentile(scores, 100 - clip, axis=0)
    return PcaBasis(mean, axes, lo, hi)


def apply_pca(basis: PcaBasis, features: np.ndarray) -> np.ndarray:
    """Colours ``(N, 3) float64`` in [0, 1] of ``features (N, C)`` in ``basis``.

    A component the basis lacks (zero range) is 0.5; rows without a feature are NaN (the
    figures draw them grey).
    """
    f = np.asarray(features, dtype=np.float64).reshape(-1, np.shape(features)[-1])
    has = _has_feature(f)
    span = basis.hi - basis.lo
    flat = span <= 1e-12
    scores = (np.where(has[:, None], f, 0.0) - basis.mean) @ basis.axes.T
    out = np.clip((scores - basis.lo) / np.where(flat, 1.0, span), 0.0, 1.0)
    out[:, flat] = 0.5
    out[~has] = np.nan
    return out


def pca_colours(*feature_sets: np.ndarray, clip: float = 1.0) -> list[np.ndarray]:
    """Colours ``(N_i, 3)`` of every set in one basis fitted on all of them (:func:`fit_pca`)."""
    basis = fit_pca(*feature_sets, clip=clip)
    return [apply_pca(basis, f) for f in feature_sets]


# --------------------------------------------------------------------------------------
# Pictures from keypoints, and back.

def paint(uv: np.ndarray, colours: np.ndarray, shape: tuple[int, int], radius: float,
          mask: np.ndarray | None = None, background: float = 1.0) -> np.ndarray:
    """An ``(H, W, 3) float64`` picture: each pixel takes the colour of its nearest keypoint.

    ``uv (N, 2)`` keypoints (pixels), ``colours (N, 3)`` (a NaN row: no feature, painted grey).
    Pixels farther than ``radius`` pixels from every keypoint, or where ``mask (H, W) bool`` is
    False (no depth), are ``background`` (NaN allowed, for :func:`sample_picture`). On a
    keypoint grid a radius of about the grid step gives a mosaic of the feature map.
    """
    from scipy.spatial import cKDTree

    H, W = shape
    out = np.full((H, W, 3), float(background))
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return out
    col = np.where(np.isnan(colours), GREY, np.asarray(colours, dtype=np.float64))
    vv, uu = np.mgrid[0:H, 0:W]
    # nextafter: the query's bound is strict, and a pixel at exactly ``radius`` belongs in.
    dist, nearest = cKDTree(uv).query(np.stack([uu.ravel(), vv.ravel()], axis=1),
                                      distance_upper_bound=np.nextafter(radius, np.inf))
    hit = np.isfinite(dist)
    if mask is not None:
        hit &= np.asarray(mask, dtype=bool).ravel()
    flat = out.reshape(-1, 3)
    flat[hit] = col[nearest[hit]]
    return out


def sample_picture(picture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``picture (H, W, 3)`` at the nearest pixel of each ``uv (N, 2)``: ``(N, 3) float64``, NaN outside."""
    pic = np.asarray(picture, dtype=np.float64)
    H, W = pic.shape[:2]
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.full((len(uv), pic.shape[2]), np.nan)
    with np.errstate(invalid="ignore"):
        px = np.rint(uv)
        inside = np.isfinite(px).all(axis=1) & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    out[inside] = pic[px[inside, 1].astype(int), px[inside, 0].astype(int)]
    return out


def colour_cloud(points_cam: np.ndarray, K: np.ndarray, picture: np.ndarray, depth: np.ndarray,
                 tol: float = 0.05) -> np.ndarray:
    """Colours ``(P, 3) float64`` of cloud points read from a picture of their depth camera.

    ``points_cam (P, 3)`` in the depth camera's frame, ``K (3, 3)`` its intrinsics,
    ``picture (H, W, 3)`` drawn on its view (:func:`paint`), ``depth (H, W)`` the depth map of
    that view. A point takes the colour of the pixel it projects to when it is the surface seen
    there (its depth within ``tol`` metres of the map's); hidden points, points outside the
    view and pixels without a colour give NaN rows.
    """
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p @ np.asarray(K, dtype=np.float64).T)[:, :2] / z[:, None]
    uv[~(z > 0)] = np.nan
    seen = sample_picture(np.asarray(depth, dtype=np.float64)[..., None], uv)[:, 0]
    out = sample_picture(picture, uv)
    with np.errstate(invalid="ignore"):
        visible = (seen > 0) & (np.abs(seen - z) <= tol)
    out[~visible] = np.nan
    return out


def oblique_view(points: np.ndarray, elevation_deg: float, azimuth_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An orthographic view of ``points (N, 3)`` given in a camera frame (x right, y down, z ahead).

    The viewer turns by ``azimuth_deg`` about the vertical (y) axis, then looks down by
    ``elevation_deg``: 0 is the camera's own view, 90 the top view (ahead is up on the page).
    Returns ``xy (N, 2) float64`` on the page (x right, y up) and ``depth (N,)`` along the
    viewing direction (draw the largest first).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    turn = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
    q = p @ turn.T
    up = np.array([0.0, -np.cos(e), np.sin(e)])
    ahead = np.array([0.0, np.sin(e), np.cos(e)])
    return np.stack([q[:, 0], q @ up], axis=1), q @ ahead


# --------------------------------------------------------------------------------------
# Patches.

def _unit_rgb(a: np.ndarray) -> np.ndarray:
    """A picture as float64 in [0, 1] (a ``uint8`` one read as 0..255); always a new array."""
    a = np.asarray(a)
    return a.astype(np.float64) / (255.0 if a.dtype == np.uint8 else 1.0)


def spaced(uv: np.ndarray, min_dist: float) -> np.ndarray:
    """Indices ``(K,) int64`` of points of ``uv (N, 2)`` kept in order when at least ``min_dist``
    from every point kept before (Chebyshev distance, so square patches of that side do not
    overlap); rows with NaN are skipped."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    kept: list[int] = []
    for i in range(len(uv)):
        if not np.isfinite(uv[i]).all():
            continue
        if all(np.max(np.abs(uv[i] - uv[j])) >= min_dist for j in kept):
            kept.append(i)
    return np.asarray(kept, dtype=np.int64)


def _box(centre: float, size: int, limit: int) -> tuple[int, int, int]:
    """``(start, offset, length)``: the patch of side ``size`` centred at ``centre`` cut to ``[0, limit)``;
    ``offset`` is how much was cut at the start."""
    start = int(np.rint(centre)) - size // 2
    lo, hi = max(start, 0), min(start + size, limit)
    return lo, lo - start, max(hi - lo, 0)


def warp_patches(image: np.ndarray, uv_src: np.ndarray, canvas: np.ndarray, uv_dst: np.ndarray,
                 size: int = 32) -> np.ndarray:
    """Square ``size`` x ``size`` patches of ``image (H, W, 3)`` centred at ``uv_src (K, 2)``,
    pasted onto a copy of ``canvas (H2, W2, 3)`` centred at ``uv_dst (K, 2)``; ``(H2, W2, 3)
    float64`` in [0, 1].

    A match moves its patch without turning or scaling it (a matched keypoint says where its
    neighbourhood goes, not how it turns). Patches are pasted in order, a later one over an
    earlier; parts falling off either picture are cut; a NaN destination pastes nothing. A
    ``uint8`` picture is read as 0..255.
    """
    img, out = _unit_rgb(image), _unit_rgb(canvas)
    src = np.asarray(uv_src, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(uv_dst, dtype=np.float64).reshape(-1, 2)
    H, W = img.shape[:2]
    H2, W2 = out.shape[:2]
    for (us, vs), (ud, vd) in zip(src, dst):
        if not np.isfinite([us, vs, ud, vd]).all():
            continue
        # Cut the patch to the part that exists in both pictures, then copy it.
        (x0, ox, nx), (y0, oy, ny) = _box(us, size, W), _box(vs, size, H)
        (X0, OX, NX), (Y0, OY, NY) = _box(ud, size, W2), _box(vd, size, H2)
        a, b = max(ox, OX), max(oy, OY)
        w = min(ox + nx, OX + NX) - a
        h = min(oy + ny, OY + NY) - b
        if w <= 0 or h <= 0:
            continue
        out[Y0 + b - OY:Y0 + b - OY + h, X0 + a - OX:X0 + a - OX + w] = \
            img[y0 + b - oy:y0 + b - oy + h, x0 + a - ox:x0 + a - ox + w]
    return out


# --------------------------------------------------------------------------------------
# Figures.

def _canvas(image: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``image`` (left) and ``right`` side by side, ``(max(H1, H2), W1 + W2, 3)`` float RGB."""
    a, b = _unit_rgb(image), _unit_rgb(right)
    out = np.zeros((max(a.shape[0], b.shape[0]), a.shape[1] + b.shape[1], 3))
    out[:a.shape[0], :a.shape[1]] = a
    out[:b.shape[0], a.shape[1]:] = b
    return out


def _lines(ax, uv_image, uv_depth, correct, offset: int, max_lines: int, seed: int) -> None:
    """Up to ``max_lines`` seeded match lines, green correct and red wrong; the depth side shifted by ``offset``."""
    ui = np.asarray(uv_image, dtype=np.float64).reshape(-1, 2)
    ud = np.asarray(uv_depth, dtype=np.float64).reshape(-1, 2)
    n = len(ui)
    pick = np.random.default_rng(seed).choice(n, min(n, max_lines), replace=False) if n else []
    for k in pick:
        ok = True if correct is None else bool(correct[k])
        ax.plot([ui[k, 0], ud[k, 0] + offset], [ui[k, 1], ud[k, 1]], color=GREEN if ok else RED, lw=0.6, alpha=0.8)


def _panel(ax, picture, title: str) -> None:
    ax.imshow(np.clip(np.nan_to_num(_unit_rgb(picture), nan=1.0), 0, 1))
    ax.set_title(title, fontsize=8)
    ax.axis("off")


def pipeline_figure(image: np.ndarray, depth_picture: np.ndarray, features: dict, uv_image: np.ndarray,
                    uv_depth: np.ndarray, correct: np.ndarray | None, poses: list, title: str = "",
                    max_lines: int = 150, seed: int = 0):
    """One pair through the chain, left to right as the paper's pipeline figure.

    Top two rows, one column per stage: the inputs (``image (H, W, 3)``; ``depth_picture
    (Hd, Wd, 3)``, the cloud on its depth camera), then for each entry of ``features``
    (name -> ``(picture of the image side, picture of the cloud side)``, e.g. diffusion,
    geometric, fused) its two feature pictures. Bottom row: the matches (``uv_image (K, 2)`` ->
    ``uv_depth (K, 2)``, green where ``correct (K,) bool``, red elsewhere) and the ``poses``
    (a list of ``(title, picture)``: the cloud drawn on the image with a pose).
    """
    plt = _plt()
    cols = 1 + len(features)
    h, w = np.asarray(image).shape[:2]
    pw = FIG_WIDTH_IN / cols
    ph = pw * h / w
    fig = plt.figure(figsize=(FIG_WIDTH_IN, 2 * (ph + 0.35) + (FIG_WIDTH_IN / 2) * h / (2 * w) + 0.9))
    grid = fig.add_gridspec(3, 2 * cols, height_ratios=[ph + 0.3, ph + 0.3, FIG_WIDTH_IN / 2 * h / (2 * w) + 0.3])
    _panel(fig.add_subplot(grid[0, 0:2]), image, "input: image")
    _panel(fig.add_subplot(grid[1, 0:2]), depth_picture, "input: point cloud (depth view)")
    for c, (name, (pic_img, pic_dep)) in enumerate(features.items(), start=1):
        _panel(fig.add_subplot(grid[0, 2 * c:2 * c + 2]), pic_img, f"{name}: image")
        _panel(fig.add_subplot(grid[1, 2 * c:2 * c + 2]), pic_dep, f"{name}: cloud")
    ax = fig.add_subplot(grid[2, 0:cols])
    n_ok = "" if correct is None else f", {int(np.sum(correct))} correct"
    _panel(ax, _canvas(image, depth_picture), f"matches: {len(np.asarray(uv_image).reshape(-1, 2))}{n_ok}")
    _lines(ax, uv_image, uv_depth, correct, w, max_lines, seed)
    span = max(1, cols // max(len(poses), 1)) if poses else cols
    for k, (ptitle, pic) in enumerate(poses):
        start = cols + k * span
        _panel(fig.add_subplot(grid[2, start:min(start + span, 2 * cols)]), pic, ptitle)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def cloud_features_figure(image_pictures: dict, xy: np.ndarray, depth: np.ndarray, cloud_colours: dict,
                          title: str = "", point_size: float = 1.5, view_name: str = "cloud"):
    """Features on the cloud's points beside the image's, one row per kind of feature.

    ``image_pictures``: name -> ``(H, W, 3)`` picture of the image side's features;
    ``cloud_colours``: the same names -> ``(P, 3)`` colours of the cloud points (NaN rows: no
    colour, drawn light grey), in the same basis as the image's. ``xy (P, 2)`` and ``depth
    (P,)``: the points as :func:`oblique_view` places them (the farthest drawn first).
    """
    plt = _plt()
    names = list(image_pictures)
    h, w = np.asarray(image_pictures[names[0]]).shape[:2]
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(-np.asarray(depth, dtype=np.float64))
    rh = FIG_WIDTH_IN / 2 * h / w + 0.35
    fig, axes = plt.subplots(len(names), 2, figsize=(FIG_WIDTH_IN, len(names) * rh + 0.5), squeeze=False)
    for row, name in zip(axes, names):
        _panel(row[0], image_pictures[name], f"{name}: image")
        col = np.asarray(cloud_colours[name], dtype=np.float64)[order]
        none = np.isnan(col).any(axis=1)
        p = xy[order]
        row[1].scatter(p[none, 0], p[none, 1], s=point_size * 0.5, color="0.85", edgecolors="none", rasterized=True)
        row[1].scatter(p[~none, 0], p[~none, 1], s=point_size, c=col[~none], edgecolors="none", rasterized=True)
        row[1].set_aspect("equal")
        row[1].set_title(f"{name}: {view_name}", fontsize=8)
        row[1].axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def patches_figure(image: np.ndarray, uv_src: np.ndarray, panels: list, correct: np.ndarray | None = None,
                   size: int = 32, title: str = ""):
    """The image with its chosen patches outlined, then each warped picture with its patches outlined.

    ``uv_src (K, 2)``: the patch centres in the image; ``panels``: ``(title, picture (H2, W2, 3),
    uv_dst (K, 2))`` triples, e.g. from :func:`warp_patches` with the matches and with the true
    positions; outlines green where ``correct (K,) bool``, red elsewhere (white without it).
    """
    plt = _plt()
    from matplotlib.patches import Rectangle

    n = 1 + len(panels)
    cols = min(n, 3)  # one row for the image and two warps: the patches stay comparable side by side
    rows = int(np.ceil(n / cols))
    h, w = np.asarray(image).shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(FIG_WIDTH_IN, rows * (FIG_WIDTH_IN / cols * h / w + 0.35) + 0.6),
                             squeeze=False)
    items = [("image patches", image, uv_src)] + list(panels)
    for ax, (ptitle, pic, uv) in zip(axes.ravel(), items):
        _panel(ax, pic, ptitle)
        ph, pw = np.asarray(pic).shape[:2]
        ax.set_xlim(-0.5, pw - 0.5)  # an outline falling off the picture must not widen the panel
        ax.set_ylim(ph - 0.5, -0.5)
        for k, (u, v) in enumerate(np.asarray(uv, dtype=np.float64).reshape(-1, 2)):
            if not np.isfinite([u, v]).all():
                continue
            edge = "white" if correct is None else (GREEN if correct[k] else RED)
            ax.add_patch(Rectangle((np.rint(u) - size // 2 - 0.5, np.rint(v) - size // 2 - 0.5), size, size,
                                   fill=False, edgecolor=edge, lw=0.8))
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def outcomes_figure(cases: list, title: str = "", max_lines: int = 150, seed: int = 0, cols: int = 2):
    """Several pairs' matches, one panel each (``cols`` to a row): image (left) and cloud depth view
    (right), match lines green correct and red wrong.

    Each case is a dict with ``image (H, W, 3)``, ``depth_picture (Hd, Wd, 3)``, ``uv_image
    (K, 2)``, ``uv_depth (K, 2)``, ``correct (K,) bool`` and ``title`` (the pair, its RE / TE
    and verdict).
    """
    plt = _plt()
    canvases = [_canvas(c["image"], c["depth_picture"]) for c in cases]
    cols = max(1, min(cols, len(cases)))
    rows = max(1, int(np.ceil(len(cases) / cols)))
    pw = FIG_WIDTH_IN / cols
    rh = max((pw * cv.shape[0] / cv.shape[1] for cv in canvases), default=1.0) + 0.55
    fig, axes = plt.subplots(rows, cols, figsize=(FIG_WIDTH_IN, rows * rh + 0.6), squeeze=False)
    for ax, case, cv in zip(axes.ravel(), cases, canvases):
        _panel(ax, cv, case.get("title", ""))
        _lines(ax, case["uv_image"], case["uv_depth"], case.get("correct"), np.asarray(case["image"]).shape[1],
               max_lines, seed)
    for ax in axes.ravel()[len(cases):]:
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
