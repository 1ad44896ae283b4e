"""Figures the notebooks draw: depth maps, feature PCA, matches (charts of numbers: :mod:`.charts`).

Every function takes arrays, draws on a new or given Matplotlib figure, and returns it;
``save`` writes it into the folder given (a notebook's ``figures_dir``) with a stable name, as a compact PNG a reader can read at
its natural size: at most :data:`MAX_WIDTH_PX` pixels wide (the dpi is lowered for a wide figure,
and the layouts here stay about :data:`FIG_WIDTH_IN` inches wide so that the text stays legible) and
at most :data:`MAX_BYTES` (256 colours, the gallery's ``compact_png``). Titles carry the short
name of the backend that produced the data (the notebooks print its full description once), so a
stub figure never passes for a real one. Axes of the percentage metrics (FMR, IR, RR) are
labelled in %; depth panels (:func:`depth_panel`) carry a colour bar in metres.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

DPI = 110  # the dpi of a figure narrow enough to fit MAX_WIDTH_PX at it
MAX_WIDTH_PX = 1000  # widest saved PNG, in pixels (what a notebook shows at its natural size)
MAX_BYTES = 400_000  # largest saved PNG
FIG_WIDTH_IN = 9.0  # the width the layouts here keep to (9 in at 110 dpi is 990 px)


def _plt():
    # No backend forced: Jupyter keeps its inline backend, headless runs fall back to Agg.
    import matplotlib.pyplot as plt

    return plt


def save(fig, name: str, folder: str | Path) -> Path:
    """Write ``fig`` as ``<folder>/<name>.png`` (a notebook passes its ``figures_dir``); returns the path.

    The dpi is :data:`DPI`, lowered when the figure's tight bounding box would be wider than
    :data:`MAX_WIDTH_PX` at it; the PNG is then compacted like the README's gallery (256 colours,
    ``optimize``; narrowed further only if it were still over :data:`MAX_BYTES`).
    """
    path = Path(folder) / f"{name}.png"  # _compact makes the folder
    # One layout pass for the tight box, one rendering, an uncompressed PNG in memory: a first full
    # draw, savefig's own "tight" pass and a compressed PNG file read back cost as much again.
    fig.draw_without_rendering()
    box = fig.get_tightbbox(fig.canvas.get_renderer()).padded(0.1)  # savefig's default pad_inches
    dpi = min(DPI, (MAX_WIDTH_PX - 2) / max(box.width, 1e-3))
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, bbox_inches=box, format="png", pil_kwargs={"compress_level": 0})
    with Image.open(buf) as im:
        _compact(im, path, MAX_WIDTH_PX, MAX_BYTES)
    return path


def compact_png(src: Path, dst: Path, max_width: int = 1000, max_bytes: int = 400_000) -> Path:
    """Write ``src`` as a small PNG: at most ``max_width`` px wide, 256 colours, at most ``max_bytes``
    (the width shrinks by steps until it fits)."""
    with Image.open(src) as im:
        return _compact(im, Path(dst), max_width, max_bytes)


def _compact(im: Image.Image, dst: Path, max_width: int, max_bytes: int) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    im = im.convert("RGB")
    width = min(max_width, im.width)
    while True:
        small = im.resize((width, max(1, round(im.height * width / im.width))), Image.LANCZOS) \
            if width < im.width else im
        small.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            dst, format="PNG", optimize=True)
        if dst.stat().st_size <= max_bytes or width <= 200:
            return dst
        width = int(width * 0.8)


def _fit_width(width: float, height: float, max_width: float = FIG_WIDTH_IN) -> tuple[float, float]:
    """``(width, height)`` scaled down together so that the width is at most ``max_width`` inches."""
    k = min(1.0, max_width / width)
    return width * k, height * k


class DepthPanel:
    """A depth map (metres, 0 = no depth) for :func:`show_images` / :func:`image_grid`: drawn in
    turbo from 0 to ``vmax`` (default its 98th percentile), empty pixels black, with a colour bar
    in metres. Make one with :func:`depth_panel`."""

    def __init__(self, depth: np.ndarray, vmax: float | None = None):
        self.depth = np.asarray(depth, dtype=np.float64)
        valid = self.depth > 0
        self.vmax = float(vmax or (np.percentile(self.depth[valid], 98) if valid.any() else 1.0))
        self.shape = self.depth.shape


def depth_panel(depth: np.ndarray, vmax: float | None = None) -> DepthPanel:
    """A depth map as a panel with a colour bar in metres (see :class:`DepthPanel`)."""
    return DepthPanel(depth, vmax)


def depth_image(depth: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """A depth map as an ``(H, W, 3)`` float RGB picture; empty pixels are black."""
    plt = _plt()
    d = np.asarray(depth, dtype=np.float64)
    valid = d > 0
    vmax = vmax or (np.percentile(d[valid], 98) if valid.any() else 1.0)
    rgb = plt.get_cmap("turbo")(np.clip(d / vmax, 0, 1))[..., :3]
    rgb[~valid] = 0
    return rgb


def show_images(images: list, titles: list[str], suptitle: str = "", cols: int | None = None, size: float = 3.2):
    """Images side by side (RGB arrays, or 2-D maps drawn with a colour bar)."""
    plt = _plt()
    cols = cols or len(images)
    rows = int(np.ceil(len(images) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=_fit_width(size * cols * 1.3, size * rows + (0.5 if suptitle else 0)),
                             squeeze=False)
    return _fill_panels(fig, axes, images, titles, suptitle, colorbar=True)


def _fill_panels(fig, axes, images: list, titles: list[str], suptitle: str, colorbar: bool):
    """Draw ``images`` into the grid ``axes`` (2-D maps in turbo, :class:`DepthPanel` with a colour bar
    in metres), blank the spare panels."""
    plt = _plt()
    for ax, img, title in zip(axes.ravel(), images, titles):
        if isinstance(img, DepthPanel):
            cmap = plt.get_cmap("turbo").with_extremes(bad="black")
            im = ax.imshow(np.where(img.depth > 0, img.depth, np.nan), cmap=cmap, vmin=0, vmax=img.vmax)
            fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02, label="depth (m)")
            ax.set_title(title, fontsize=9)
            ax.axis("off")
            continue
        img = np.asarray(img)
        im = ax.imshow(img, cmap="turbo" if img.ndim == 2 else None)
        if colorbar and img.ndim == 2:
            fig.colorbar(im, ax=ax, fraction=0.035)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    for ax in axes.ravel()[len(images):]:
        ax.axis("off")
    if suptitle:
        fig.suptitle(suptitle)
    fig.tight_layout()
    return fig


def pca_rgb(map_a: np.ndarray, map_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Feature maps ``(C, h, w)`` as RGB pictures via a 3-component PCA fitted on both maps.

    One basis for both sides, so matching colours mean similar features (the paper's Fig. 4c, PCA of
    decoder features).
    """
    maps = [m for m in (map_a, map_b) if m is not None]
    flat = np.concatenate([m.reshape(m.shape[0], -1).T for m in maps]).astype(np.float64)
    flat /= np.linalg.norm(flat, axis=1, keepdims=True) + 1e-8
    mean = flat.mean(0)
    _, _, vt = np.linalg.svd(flat - mean, full_matrices=False)
    proj = (flat - mean) @ vt[:3].T
    lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
    proj = np.clip((proj - lo) / (hi - lo + 1e-8), 0, 1)
    out, start = [], 0
    for m in maps:
        n = m.shape[1] * m.shape[2]
        out.append(proj[start : start + n].reshape(m.shape[1], m.shape[2], 3))
        start += n
    return out[0], (out[1] if map_b is not None else None)


def draw_matches(
    image: np.ndarray,
    depth_rgb: np.ndarray,
    uv_image: np.ndarray,
    uv_depth: np.ndarray,
    correct: np.ndarray | None = None,
    title: str = "",
    max_lines: int = 300,
    seed: int = 0,
):
    """Image (left) and depth map (right) with match lines: green correct, red wrong."""
    plt = _plt()
    canvas = _match_canvas(image, depth_rgb)
    w = FIG_WIDTH_IN
    fig, ax = plt.subplots(figsize=(w, w * canvas.shape[0] / canvas.shape[1] + 0.6))
    ax.imshow(canvas)
    _match_lines(ax, uv_image, uv_depth, correct, image.shape[1], max_lines, seed)
    ax.set_title(title, fontsize=10)
    ax.axis("off")
    fig.tight_layout()
    return fig


def _match_canvas(image: np.ndarray, depth_rgb: np.ndarray) -> np.ndarray:
    """The image (left) and the depth picture (right) side by side, float RGB."""
    h1, w1 = image.shape[:2]
    h2, w2 = depth_rgb.shape[:2]
    canvas = np.zeros((max(h1, h2), w1 + w2, 3))
    canvas[:h1, :w1] = np.asarray(image, dtype=np.float64) / (255.0 if image.dtype == np.uint8 else 1.0)
    canvas[:h2, w1:] = depth_rgb
    return canvas


def _match_lines(ax, uv_image, uv_depth, correct, offset: int, max_lines: int, seed: int) -> None:
    """Up to ``max_lines`` seeded match lines, green correct and red wrong; depth side shifted by ``offset``."""
    uv_i = np.asarray(uv_image).reshape(-1, 2)
    uv_d = np.asarray(uv_depth).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    n = len(uv_i)
    for k in (rng.choice(n, min(n, max_lines), replace=False) if n else []):
        ok = True if correct is None else bool(correct[k])
        ax.plot([uv_i[k, 0], uv_d[k, 0] + offset], [uv_i[k, 1], uv_d[k, 1]],
                color=(0.1, 0.8, 0.2) if ok else (0.9, 0.15, 0.1), lw=0.6, alpha=0.8)


# ---- added for notebooks 00 and 02 ---------------------------------------------------------

def show(fig, name: str, folder: str | Path) -> Path:
    """``save`` the figure, show the saved PNG inline in a notebook, close the figure.

    Works whatever Matplotlib backend is active (``_plt`` selects Agg, which draws nothing
    inline), and closing avoids a second copy under the inline backend. Returns the path.
    """
    path = save(fig, name, folder)
    try:
        from IPython import get_ipython
        from IPython.display import Image, display

        if get_ipython() is not None:
            display(Image(filename=str(path)))
    except ImportError:  # plain Python: the file is the output
        pass
    _plt().close(fig)
    return path


def overlay_depth(image: np.ndarray, depth: np.ndarray, alpha: float = 0.7, vmax: float | None = None) -> np.ndarray:
    """An RGB image with a depth map drawn over it where the depth is valid; ``(H, W, 3)`` float."""
    img = np.asarray(image, dtype=np.float64) / (255.0 if np.asarray(image).dtype == np.uint8 else 1.0)
    d = np.asarray(depth, dtype=np.float64)
    rgb = depth_image(d, vmax)
    out = img.copy()
    valid = d > 0
    out[valid] = (1 - alpha) * img[valid] + alpha * rgb[valid]
    return out


def depth_error_maps(image: np.ndarray, depth_gt: np.ndarray, depth_est: np.ndarray, title: str = "",
                     est_label: str = "estimated depth"):
    """Image, true depth, estimated depth (same colour scale) and the signed error map.

    The error panel (estimate minus truth, metres, blue = too near, red = too far) carries
    the mean absolute error over pixels where both depths are valid in its title.
    """
    plt = _plt()
    gt = np.asarray(depth_gt, dtype=np.float64)
    est = np.asarray(depth_est, dtype=np.float64)
    valid = (gt > 0) & (est > 0) & np.isfinite(gt) & np.isfinite(est)
    err = np.where(valid, est - gt, np.nan)
    mae = float(np.nanmean(np.abs(err))) if valid.any() else float("nan")
    vmax = float(np.percentile(gt[gt > 0], 98)) if (gt > 0).any() else 1.0
    lim = float(np.nanpercentile(np.abs(err), 98)) if valid.any() else 1.0
    h, w_ = np.asarray(image).shape[:2]
    fig, axes = plt.subplots(2, 2, figsize=(FIG_WIDTH_IN, 2 * (FIG_WIDTH_IN / 2 * 0.85 * h / w_ + 0.4) + 0.5))
    axes = axes.ravel()
    axes[0].imshow(image)
    axes[0].set_title("RGB image", fontsize=9)
    for ax, d, lab in ((axes[1], gt, "true depth"), (axes[2], est, est_label)):
        im = ax.imshow(np.where(d > 0, d, np.nan), cmap="turbo", vmin=0, vmax=vmax)
        fig.colorbar(im, ax=ax, fraction=0.035, label="depth (m)")
        ax.set_title(lab, fontsize=9)
    im = axes[3].imshow(err, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[3], fraction=0.035, label="error (m)")
    axes[3].set_title(f"estimate - truth; mean |error| = {mae:.3f} m", fontsize=9)
    for ax in axes:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def topdown_clouds(clouds: dict, title: str = "", max_points: int = 20000, seed: int = 0,
                   axes: tuple[int, int] = (0, 2), axis_labels: tuple[str, str] = ("x (m)", "z (m)")):
    """Top-down scatter of several ``(N, 3)`` clouds in one frame (default the camera's x-z plane).

    Each cloud is randomly thinned to ``max_points`` (seeded) and drawn in its own colour.
    """
    plt = _plt()
    from matplotlib.lines import Line2D

    rng = np.random.default_rng(seed)
    fig, ax = plt.subplots(figsize=(6.5, 6))
    handles = []
    for k, (label, pts) in enumerate(clouds.items()):
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p) > max_points:
            p = p[rng.choice(len(p), max_points, replace=False)]
        ax.scatter(p[:, axes[0]], p[:, axes[1]], s=0.4, alpha=0.4, color=f"C{k}", rasterized=True)
        handles.append(Line2D([], [], ls="", marker="o", markersize=5, color=f"C{k}", label=label))
    ax.scatter([0], [0], marker="^", s=60, color="k")
    handles.append(Line2D([], [], ls="", marker="^", markersize=7, color="k", label="camera centre"))
    ax.set_xlabel(axis_labels[0])
    ax.set_ylabel(axis_labels[1])
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=8, loc="best")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def keypoint_colours(feats_a: np.ndarray, feats_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The RGB colours of :func:`keypoint_feature_pca`: a 3-component PCA of the unit descriptors of
    both sides, one basis, each channel stretched to its 1-99 % range; ``(colours (Na + Nb, 3), has)``,
    the rows of ``feats_a`` first, grey where a keypoint has no feature (``has`` False)."""
    flat = np.concatenate([np.asarray(feats_a, dtype=np.float64), np.asarray(feats_b, dtype=np.float64)])
    norm = np.linalg.norm(flat, axis=1)
    has = norm > 0
    colours = np.full((len(flat), 3), 0.5)
    if has.sum() >= 3:
        x = flat[has] / norm[has, None]
        mean = x.mean(0)
        _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
        proj = (x - mean) @ vt[:3].T
        lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
        colours[has] = np.clip((proj - lo) / (hi - lo + 1e-8), 0, 1)
    return colours, has


def keypoint_feature_pca(image_a: np.ndarray, uv_a: np.ndarray, feats_a: np.ndarray,
                         image_b: np.ndarray, uv_b: np.ndarray, feats_b: np.ndarray,
                         titles: tuple[str, str] = ("image", "depth map"), title: str = "",
                         size: float = 14.0):
    """Keypoints of two views coloured by a 3-component PCA of their features (one basis for both).

    Like :func:`pca_rgb` for per-keypoint features ``(N, C)``: equal colours mean similar
    descriptors. Keypoints whose feature is all zeros (no feature) are drawn as grey crosses.
    """
    plt = _plt()
    fa = np.asarray(feats_a, dtype=np.float64)
    colours, has = keypoint_colours(fa, feats_b)
    fig, axes = plt.subplots(1, 2, figsize=(FIG_WIDTH_IN, 3.7))
    parts = ((image_a, uv_a, slice(0, len(fa))), (image_b, uv_b, slice(len(fa), len(colours))))
    for ax, (img, uv, sl), sub in zip(axes, parts, titles):
        uv = np.asarray(uv, dtype=np.float64)
        ax.imshow(img, alpha=0.45)
        h = has[sl]
        ax.scatter(uv[h, 0], uv[h, 1], c=colours[sl][h], s=size, edgecolors="none")
        ax.scatter(uv[~h, 0], uv[~h, 1], c="0.4", marker="x", s=size * 0.6, linewidths=0.6)
        ax.set_title(sub, fontsize=9)
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def noise_schedule(alphas_cumprod: np.ndarray, marks: dict | None = None, title: str = ""):
    """``sqrt(abar_t)`` (signal) and ``sqrt(1 - abar_t)`` (noise) against ``t``, with labelled marks.

    ``marks`` maps a label to a timestep, drawn as a vertical line.
    """
    plt = _plt()
    a = np.asarray(alphas_cumprod, dtype=np.float64)
    t = np.arange(len(a))
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    ax.plot(t, np.sqrt(a), label=r"signal weight $\sqrt{\bar\alpha_t}$")
    ax.plot(t, np.sqrt(1 - a), label=r"noise weight $\sqrt{1-\bar\alpha_t}$")
    for k, (label, tm) in enumerate((marks or {}).items()):
        ax.axvline(tm, color=f"C{k + 2}", ls="--", lw=1)
        ax.text(tm, 1.02, label, color=f"C{k + 2}", ha="center", va="bottom", fontsize=8,
                transform=ax.get_xaxis_transform())
    ax.set_xlabel("timestep t")
    ax.set_ylabel("weight")
    ax.set_ylim(0, 1.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="center right")
    ax.set_title(title, fontsize=10, pad=16)
    fig.tight_layout()
    return fig


def ddim_timeline(timesteps: np.ndarray, n_run: int, t_feature: int, title: str = ""):
    """The DDIM timesteps from noise (left) to image (right): the first ``n_run`` are sampled
    (filled), then one feature pass at ``t_feature`` (star); the rest are never run (hollow)."""
    plt = _plt()
    ts = np.asarray(timesteps)
    fig, ax = plt.subplots(figsize=(FIG_WIDTH_IN, 2.8))
    run, rest = ts[:n_run], ts[n_run:]
    ax.scatter(run, np.zeros(len(run)), s=60, color="C0", label=f"{n_run} guided DDIM steps")
    ax.scatter(rest, np.zeros(len(rest)), s=60, facecolors="none", edgecolors="0.5",
               label="not run")
    ax.scatter([t_feature], [0], marker="*", s=320, color="C3", zorder=3,
               label=f"feature pass at t = {t_feature}")
    for k, tv in enumerate(ts):
        ax.text(tv, 0.012, str(int(tv)), ha="center", va="bottom", fontsize=7, rotation=90)
    ax.set_xlim(ts.max() + 30, min(ts.min(), t_feature) - 30)
    ax.set_ylim(-0.05, 0.035)
    ax.set_yticks([])
    ax.set_xlabel("timestep t (sampling runs left to right: noise -> image)")
    ax.legend(fontsize=8, loc="lower center", ncol=3)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------
# Added for notebooks 01 and 03: several match sets on one pair, a metric against a knob
# (paper vs re-run), and a descriptor-similarity map over the depth keypoints.

def match_panels(image: np.ndarray, depth_rgb: np.ndarray, panels: list[dict], suptitle: str = "",
                 max_lines: int = 200, seed: int = 0, ncols: int = 1):
    """Several match sets on the same pair, one panel each (the paper's Fig. 5 e-g, D / G / fused
    matches).

    Each panel is a dict with ``uv_image (K, 2)``, ``uv_depth (K, 2)``, ``correct (K,) bool``
    (or None) and ``title``. A panel shows the image (left) and the depth map (right) with
    up to ``max_lines`` match lines, green correct and red wrong.
    """
    plt = _plt()
    canvas = _match_canvas(image, depth_rgb)
    n = len(panels)
    nrows = int(np.ceil(n / ncols))
    pw = FIG_WIDTH_IN / max(ncols, 1)
    ph = pw * canvas.shape[0] / canvas.shape[1] + 0.5
    fig, axes = plt.subplots(nrows, ncols, figsize=(pw * ncols, ph * nrows + 0.4), squeeze=False)
    for ax, panel in zip(axes.ravel(), panels):
        ax.imshow(canvas)
        _match_lines(ax, panel["uv_image"], panel["uv_depth"], panel.get("correct"), image.shape[1], max_lines, seed)
        ax.set_title(panel.get("title", ""), fontsize=10)
        ax.axis("off")
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    fig.tight_layout()
    return fig


def similarity_maps(image: np.ndarray, uv_query: np.ndarray, depth_rgb: np.ndarray,
                    uv_depth: np.ndarray, sims: dict, uv_true: np.ndarray | None = None,
                    suptitle: str = "", size: float = 3.2, cbar_label: str = "similarity", cols: int = 2):
    """How one image keypoint's descriptor resembles every depth keypoint's.

    Left: the image with the query pixel ``uv_query (2,)``. Then one panel per entry of
    ``sims`` (label -> ``(M,)`` similarities of the query to the depth keypoints
    ``uv_depth (M, 2)``), drawn as coloured dots on the (dimmed) depth map; a black-ringed
    star marks each panel's best match, a cross ``uv_true`` (the true partner), if given.
    The panels fill a grid ``cols`` wide.
    """
    plt = _plt()
    n = 1 + len(sims)
    cols = max(1, min(cols, n))
    rows = int(np.ceil(n / cols))
    h, w = np.asarray(image).shape[:2]
    pw = min(FIG_WIDTH_IN / cols, size * 1.35)
    fig, axes = plt.subplots(rows, cols, figsize=(pw * cols, rows * (pw / 1.2 * h / w + 0.45) + 0.5), squeeze=False)
    axes = axes.ravel()
    for ax in axes[n:]:
        ax.axis("off")
    axes[0].imshow(image)
    axes[0].plot(uv_query[0], uv_query[1], marker="*", ms=16, color="yellow", mec="black")
    axes[0].set_title("image, query keypoint", fontsize=9)
    axes[0].axis("off")
    dim = 0.35 * np.asarray(depth_rgb, dtype=np.float64)
    for ax, (label, s) in zip(axes[1:], sims.items()):
        s = np.asarray(s, dtype=np.float64)
        ax.imshow(dim)
        sc = ax.scatter(uv_depth[:, 0], uv_depth[:, 1], c=s, s=9, cmap="magma")
        best = int(np.argmax(s))
        ax.plot(uv_depth[best, 0], uv_depth[best, 1], marker="*", ms=14, color="yellow", mec="black")
        if uv_true is not None:
            ax.plot(uv_true[0], uv_true[1], marker="x", ms=12, mew=2.5, color="cyan")
        fig.colorbar(sc, ax=ax, fraction=0.035, label=cbar_label)
        ax.set_title(label, fontsize=9)
        ax.axis("off")
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    return fig


def image_grid(images: list, titles: list[str], suptitle: str = "", cols: int = 2, width: float = FIG_WIDTH_IN):
    """Like :func:`show_images` but each panel keeps its image's aspect ratio (wide LiDAR views
    stay readable); RGB arrays as they are, 2-D maps with the turbo colour map, a
    :class:`DepthPanel` with a colour bar in metres. ``width`` is capped at :data:`FIG_WIDTH_IN`."""
    plt = _plt()
    width = min(width, FIG_WIDTH_IN)
    rows = int(np.ceil(len(images) / cols))
    shapes = [img.shape if isinstance(img, DepthPanel) else np.asarray(img).shape for img in images]
    aspect = max(sh[0] / sh[1] for sh in shapes)
    panel_w = width / cols
    fig, axes = plt.subplots(rows, cols, figsize=(width, rows * (panel_w * aspect + 0.45) + (0.4 if suptitle else 0)),
                             squeeze=False)
    return _fill_panels(fig, axes, images, titles, suptitle, colorbar=False)


# --------------------------------------------------------------------------------------
# Added for notebook 04 (benchmark): a re-run table beside the paper's as bars, and RR over
# a threshold ladder (the paper's Table 9, PnP vs Kabsch, in its appendix).


