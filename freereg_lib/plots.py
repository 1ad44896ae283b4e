"""Figures the notebooks draw: depth maps, feature PCA, matches, error curves.

Every function takes arrays, draws on a new or given Matplotlib figure, and returns it;
``save`` writes it under ``figures/`` with a stable name. Titles carry the backend that
produced the data, so a stub figure never passes for a real one.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

FIGURES = Path(__file__).resolve().parent.parent / "figures"


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save(fig, name: str, folder: str | Path | None = None) -> Path:
    """Write ``fig`` as ``<folder>/<name>.png`` (default ``figures/``); returns the path."""
    folder = Path(folder) if folder is not None else FIGURES
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return path


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
    fig, axes = plt.subplots(rows, cols, figsize=(size * cols * 1.3, size * rows), squeeze=False)
    for ax, img, title in zip(axes.ravel(), images, titles):
        img = np.asarray(img)
        if img.ndim == 2:
            im = ax.imshow(img, cmap="turbo")
            fig.colorbar(im, ax=ax, fraction=0.035)
        else:
            ax.imshow(img)
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

    One basis for both sides, so matching colours mean similar features (the paper's Fig. 3c).
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
    h1, w1 = image.shape[:2]
    h2, w2 = depth_rgb.shape[:2]
    canvas = np.zeros((max(h1, h2), w1 + w2, 3))
    canvas[:h1, :w1] = np.asarray(image, dtype=np.float64) / (255.0 if image.dtype == np.uint8 else 1.0)
    canvas[:h2, w1:] = depth_rgb
    fig, ax = plt.subplots(figsize=(12, 12 * canvas.shape[0] / canvas.shape[1] + 0.6))
    ax.imshow(canvas)
    rng = np.random.default_rng(seed)
    n = len(uv_image)
    show = rng.choice(n, min(n, max_lines), replace=False) if n else np.zeros(0, int)
    for k in show:
        ok = True if correct is None else bool(correct[k])
        ax.plot([uv_image[k, 0], uv_depth[k, 0] + w1], [uv_image[k, 1], uv_depth[k, 1]],
                color=(0.1, 0.8, 0.2) if ok else (0.9, 0.15, 0.1), lw=0.6, alpha=0.8)
    ax.set_title(title)
    ax.axis("off")
    fig.tight_layout()
    return fig


def error_curves(errors: dict[str, np.ndarray], xlabel: str, title: str, xmax: float | None = None):
    """Cumulative curves: for each label, the % of pairs with error below x."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, err in errors.items():
        e = np.sort(np.where(np.isfinite(err), err, np.inf))
        if len(e) == 0:
            continue
        top = xmax or (np.nanmax(e[np.isfinite(e)]) if np.isfinite(e).any() else 1.0)
        xs = np.linspace(0, top, 200)
        ax.plot(xs, 100.0 * np.searchsorted(e, xs, side="right") / len(e), label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("% of pairs below")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return fig


def bar_compare(table, metric: str, label_col: str, title: str):
    """Grouped bars of ``metric`` for the paper and the re-run (columns ``<metric>_paper`` and ``<metric>``)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(5, 0.6 * len(table) + 2), 3.6))
    x = np.arange(len(table))
    ax.bar(x - 0.2, table[f"{metric}_paper"], width=0.4, label="paper")
    ax.bar(x + 0.2, table[metric], width=0.4, label="re-run")
    ax.set_xticks(x, [str(v) for v in table[label_col]], rotation=30, ha="right")
    ax.set_ylabel(metric)
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    return fig
