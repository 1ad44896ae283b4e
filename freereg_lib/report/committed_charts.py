"""The result figures of the committed test split, drawn from committed numbers only.

A run's few live pairs move by a whole pair's share when one outcome flips, and which outcome flips
depends on the CPU (docs/reproducibility.md). The figures that state a result of the paper are
therefore drawn here from the committed JSON of the micro models' test split (100 pairs no choice
was made on) with their 95 % intervals, labelled with the pair count and the backend; they come
out the same on every machine. Each function takes the loaded JSON (and the paper's table) and
returns a Matplotlib figure:

    split = json.loads((WEIGHTS_DIR / "test_split.json").read_text())
    fig = committed_charts.table1(split, paper.table("table1_main"))

The one-pair pictures (decoder layers as PCA colours, D / G / fused matches) are drawn from the
committed arrays of their pair: :func:`load_picture` reads them.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from freereg_lib.report.charts import _metric_axis
from freereg_lib.report.plots import FIG_WIDTH_IN, _plt

VARIANTS = (("FreeReg-D", "pnp"), ("FreeReg-D", "kabsch"), ("FreeReg-G", "pnp"), ("FreeReg-G", "kabsch"),
            ("FreeReg", "pnp"), ("FreeReg", "kabsch"))
PAPER_COLOUR, OURS_COLOUR = "0.6", "tab:blue"


def caption(res: dict) -> str:
    """The line every committed figure carries: what it is drawn from."""
    backend = str(res.get("backend") or "micro backend").split(" (")[0]
    return (f"committed test split: {res['n_pairs']} synthetic indoor pairs, {backend}, 95 % intervals "
            f"(the same on every machine)")


def wilson_interval(share: float, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a proportion (in %) from its value ``share`` (%) over ``n`` pairs: a
    rung of Table 9's ladder is stored as a share only."""
    p = share / 100.0
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return 100 * max(0.0, centre - half), 100 * min(1.0, centre + half)


def _bars(ax, x, values, lows, highs, offset, colour, label):
    values = np.asarray(values, dtype=np.float64)
    err = np.vstack([values - np.asarray(lows, dtype=np.float64), np.asarray(highs, dtype=np.float64) - values])
    ax.bar(x + offset, np.nan_to_num(values), width=0.4, color=colour, label=label,
           yerr=None if not np.nan_to_num(err).any() else np.nan_to_num(err), capsize=2, error_kw={"lw": 0.8})


def table1(split: dict, paper_table, reference: str = "3DMatch", metrics=("FMR", "IR", "RR")):
    """Table 1 (main results): each FreeReg variant's FMR, IR and RR on the committed split with its
    interval, beside the paper's row on ``reference``."""
    plt = _plt()
    paper_rows = paper_table[(paper_table["dataset"] == reference)].assign(solver=lambda t: t["solver"].str.lower())
    paper_of = {(r.method, r.solver): r for r in paper_rows.itertuples()}
    labels = [f"{m} + {s}" for m, s in VARIANTS]
    x = np.arange(len(labels))
    fig, axes = plt.subplots(1, len(metrics), figsize=(FIG_WIDTH_IN, 3.9), squeeze=False)
    for ax, metric in zip(axes.ravel(), metrics):
        ours = [split["results"][f"{m} {s}"][metric] for m, s in VARIANTS]
        theirs = [getattr(paper_of.get(v), metric, np.nan) for v in VARIANTS]
        _bars(ax, x, theirs, theirs, theirs, -0.2, PAPER_COLOUR, f"paper ({reference})")
        _bars(ax, x, [o["mean"] for o in ours], [o["ci"][0] for o in ours], [o["ci"][1] for o in ours], 0.2,
              OURS_COLOUR, "micro, committed")
        for k in np.nonzero(~np.isfinite(np.asarray(theirs, dtype=np.float64)))[0]:
            ax.text(x[k] - 0.2, 0, "n/a", ha="center", va="bottom", fontsize=6, rotation=90)
        ax.set_xticks(x, labels, rotation=35, ha="right", fontsize=7)
        _metric_axis(ax, metric)
        ax.set_title(metric, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    handles, names = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(f"Table 1 (main results), FreeReg variants: paper ({reference}) vs micro models\n{caption(split)}",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig


def rr_ladder(split: dict, paper_ladder, reference: str = "3DMatch"):
    """Table 9 (PnP vs Kabsch): fused FreeReg's RR over the threshold ladder with each rung's 95 %
    Wilson interval, beside the paper's ladders (dashed)."""
    plt = _plt()
    n = split["n_pairs"]
    rungs = list(split["results"]["FreeReg kabsch"]["ladder"])
    x = np.arange(len(rungs))
    fig, ax = plt.subplots(figsize=(min(FIG_WIDTH_IN, 7.5), 4.0))
    paper_rows = paper_ladder[paper_ladder["dataset"] == reference].assign(solver=lambda t: t["solver"].str.lower())
    for k, solver in enumerate(("pnp", "kabsch")):
        ladder = split["results"][f"FreeReg {solver}"]["ladder"]
        y = np.array([ladder[r] for r in rungs])
        lo, hi = np.array([wilson_interval(v, n) for v in y]).T
        dodge = 0.05 * (2 * k - 1)
        ax.errorbar(x + dodge, y, yerr=[y - lo, hi - y], fmt="o-", color=f"C{k}", capsize=3,
                    label=f"FreeReg + {solver}, micro (committed)")
        row = paper_rows[paper_rows["solver"] == solver]
        if not row.empty:
            ax.plot(x, [row.iloc[0][f"RR_{j + 1}"] for j in range(len(rungs))], "s--", color=f"C{k}", alpha=0.55,
                    label=f"FreeReg + {solver}, paper ({reference})")
    ax.set_xticks(x, [r.replace("RR@", "") for r in rungs], fontsize=8)
    ax.set_xlabel("threshold (rotation / translation), tighter to looser")
    ax.set_ylabel("RR (% of pairs registered)")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(f"Table 9, RR over the threshold ladder: paper (dashed) vs micro models\n{caption(split)}",
                 fontsize=9)
    fig.tight_layout()
    return fig


def table4(split: dict, paper_table, metrics=("IR", "RR")):
    """Table 4 (fusion weight): IR and RR with Kabsch at w = 1 (FreeReg-D), the split's w (FreeReg)
    and 0 (FreeReg-G) with their intervals, beside the paper's sweep on 3DMatch."""
    plt = _plt()
    w_fused = float(split["config"]["fusion_w"])
    ws = {1.0: "FreeReg-D", w_fused: "FreeReg", 0.0: "FreeReg-G"}
    fig, axes = plt.subplots(1, len(metrics), figsize=(min(FIG_WIDTH_IN, 3.8 * len(metrics)), 3.6), squeeze=False)
    t = paper_table.sort_values("w")
    for ax, metric in zip(axes.ravel(), metrics):
        ax.plot(t["w"], t[metric], "o--", color="0.35", label="paper (3DMatch)")
        xs = sorted(ws)
        s = [split["results"][f"{ws[w]} kabsch"][metric] for w in xs]
        y = np.array([v["mean"] for v in s])
        lo, hi = np.array([v["ci"] for v in s]).T
        ax.errorbar(xs, y, yerr=[y - lo, hi - y], fmt="o-", color=OURS_COLOUR, capsize=3, label="micro (committed)")
        ax.set_xlabel("fusion weight w (1 = diffusion only, 0 = geometric only)", fontsize=8)
        _metric_axis(ax, metric)
        ax.set_title(metric, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"Table 4, fusion weight w (Kabsch): paper (3DMatch) vs micro models\n{caption(split)}", fontsize=9)
    fig.tight_layout()
    return fig


def table2(layers: dict, paper_table, metric: str = "IR"):
    """Table 2 (layer selection): FreeReg-D's ``metric`` per row a-m on the committed split with its
    interval, beside the paper's 3DMatch column."""
    plt = _plt()
    rows = list(layers["rows"])
    paper_of = dict(zip(paper_table["id"], paper_table[f"3DMatch_{metric}"]))
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(min(FIG_WIDTH_IN, 0.6 * len(rows) + 2.5), 3.8))
    _bars(ax, x, [paper_of.get(r, np.nan) for r in rows], [paper_of.get(r, np.nan) for r in rows],
          [paper_of.get(r, np.nan) for r in rows], -0.2, PAPER_COLOUR, "paper (3DMatch)")
    s = [layers["rows"][r][metric] for r in rows]
    _bars(ax, x, [v["mean"] for v in s], [v["ci"][0] for v in s], [v["ci"][1] for v in s], 0.2, OURS_COLOUR,
          "micro (committed)")
    ax.set_xticks(x, [f"{r}: {','.join(map(str, layers['rows'][r]['layers']))}" for r in rows], rotation=35,
                  ha="right", fontsize=7)
    ax.set_xlabel("Table 2 row: decoder layers")
    _metric_axis(ax, metric)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"Table 2, FreeReg-D {metric} by decoder layers: paper (3DMatch) vs micro models\n{caption(layers)}",
                 fontsize=9)
    fig.tight_layout()
    return fig


def save_picture(path: str | Path, meta: dict, **arrays: np.ndarray) -> Path:
    """The arrays of a one-pair picture (``<path>.npz``) and what made them (``<path>.json``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path.with_suffix(".npz"), **arrays)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    return path.with_suffix(".npz")


def load_picture(path: str | Path) -> tuple[dict, dict]:
    """``(arrays, meta)`` of a picture :func:`save_picture` wrote; ``FileNotFoundError`` naming it."""
    path = Path(path)
    if not path.with_suffix(".npz").is_file():
        raise FileNotFoundError(f"{path.with_suffix('.npz')}: no committed picture arrays "
                                "(python -m freereg_lib.commands.gallery --record-pictures RUN writes them)")
    with np.load(path.with_suffix(".npz")) as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, json.loads(path.with_suffix(".json").read_text())


def _recorded(meta: dict) -> str:
    cpu = (meta.get("provenance") or {}).get("cpu", {}).get("model", "an unrecorded CPU")
    git = (meta.get("provenance") or {}).get("git") or {}
    commit = (git.get("commit") or "an unrecorded commit")[:8] + (" with local changes" if git.get("dirty") else "")
    return f"committed arrays of pair {meta['pair']} ({meta['backend']}; recorded on {cpu}, commit {commit})"


def record_pca_layers(path: str | Path, panels: list, titles: list[str], meta: dict) -> Path:
    """Save the PCA panels of the decoder layers (``(h, w, 3)`` floats in [0, 1], RGB then depth for
    each layer) with ``meta`` (``pair``, ``backend``, ``title``) and this machine's provenance."""
    from freereg_lib.training.provenance import machine_record

    arrays = {f"panel_{k}": np.asarray(p, dtype=np.float32) for k, p in enumerate(panels)}
    return save_picture(path, {**meta, "titles": list(titles), "provenance": machine_record()}, **arrays)


def pca_layers(arrays: dict, meta: dict, cols: int = 6, width: float = 9.0):
    """The decoder layers as PCA colours (the paper's Fig. 4c) from :func:`record_pca_layers`'s arrays."""
    from freereg_lib.report.plots import image_grid

    panels = [arrays[f"panel_{k}"] for k in range(len(meta["titles"]))]
    return image_grid(panels, meta["titles"], suptitle=f"{meta['title']}\n{_recorded(meta)}", cols=cols, width=width)


def record_matches(path: str | Path, image: np.ndarray, depth_rgb: np.ndarray, panels: list[dict], meta: dict) -> Path:
    """Save a match picture's inputs: the image ``(H, W, 3) uint8``, the depth picture ``(h, w, 3)``
    in [0, 1] (stored as uint8), and each panel's ``uv_image``, ``uv_depth``, ``correct`` and title."""
    from freereg_lib.training.provenance import machine_record

    arrays = {"image": np.asarray(image), "depth_rgb": np.round(np.clip(depth_rgb, 0, 1) * 255).astype(np.uint8)}
    for k, p in enumerate(panels):
        arrays.update({f"uv_image_{k}": p["uv_image"], f"uv_depth_{k}": p["uv_depth"], f"correct_{k}": p["correct"]})
    meta = {**meta, "titles": [p["title"] for p in panels], "provenance": machine_record()}
    return save_picture(path, meta, **arrays)


def matches(arrays: dict, meta: dict):
    """D / G / fused matches (the paper's Fig. 5 e-g) from :func:`record_matches`'s arrays."""
    from freereg_lib.report.plots import match_panels

    panels = [{"uv_image": arrays[f"uv_image_{k}"], "uv_depth": arrays[f"uv_depth_{k}"],
               "correct": arrays[f"correct_{k}"], "title": t} for k, t in enumerate(meta["titles"])]
    return match_panels(arrays["image"], arrays["depth_rgb"].astype(np.float64) / 255, panels,
                        seed=meta.get("seed", 0), suptitle=f"{meta['title']}\n{_recorded(meta)}")


def same_arrays(a: dict, b: dict) -> bool:
    """Whether two pictures' arrays are bit-identical (this run's against the committed ones)."""
    return set(a) == set(b) and all(np.array_equal(a[k], b[k]) for k in a)


def committed(name: str) -> dict | None:
    """A committed result JSON of the micro models (``freereg_lib/models/micro/weights/<name>``);
    None when it is absent."""
    from freereg_lib.models.micro.diffusion import WEIGHTS_DIR

    path = Path(WEIGHTS_DIR) / name
    return json.loads(path.read_text()) if path.is_file() else None


def picture_path(name: str) -> Path:
    """Where the committed arrays of the one-pair picture ``name`` lie (without suffix)."""
    from freereg_lib.models.micro.diffusion import WEIGHTS_DIR

    return Path(WEIGHTS_DIR) / "pictures" / name


def gallery_picture(name: str, draw, run_arrays: str | Path, figures_dir: str | Path) -> str:
    """Draw the committed arrays of picture ``name`` with ``draw`` (:func:`pca_layers` or :func:`matches`)
    as ``<figures_dir>/<name>_committed.png`` (the README's gallery copy) and return a line saying whether
    this run's arrays (``run_arrays``, written by a ``record_*`` function) are bit-identical to them."""
    from freereg_lib.report.plots import _plt, save

    try:
        arrays, meta = load_picture(picture_path(name))
    except FileNotFoundError as exc:
        return f"the gallery's {name}: {exc}"
    fig = draw(arrays, meta)
    save(fig, f"{name}_committed", figures_dir)
    _plt().close(fig)
    mine, mine_meta = load_picture(run_arrays)
    if mine_meta["pair"] != meta["pair"]:
        return f"the gallery's {name}: committed arrays of pair {meta['pair']}; this run drew {mine_meta['pair']}"
    same = same_arrays(mine, arrays)
    return (f"the gallery's {name}: drawn from the committed arrays of pair {meta['pair']}; this run's arrays of "
            f"that pair are {'bit-identical to them' if same else 'NOT bit-identical to them (another CPU or thread count: docs/reproducibility.md)'}")


def table1_markdown(split: dict, paper_table, reference: str = "3DMatch") -> str:
    """Table 1's FreeReg rows on the committed split as Markdown: each metric with its 95 % interval,
    the paper's value on ``reference`` beside it."""
    paper_rows = paper_table[paper_table["dataset"] == reference].assign(solver=lambda t: t["solver"].str.lower())
    paper_of = {(r.method, r.solver): r for r in paper_rows.itertuples()}
    lines = [f"| method | solver | {' | '.join(f'{m} | {m} paper' for m in ('FMR', 'IR', 'RR'))} |",
             "|---|---|" + "---|---|" * 3]
    for m, s in VARIANTS:
        r = split["results"][f"{m} {s}"]
        cells = []
        for metric in ("FMR", "IR", "RR"):
            v = r[metric]
            theirs = getattr(paper_of.get((m, s)), metric, float("nan"))
            cells += [f"{v['mean']:.1f} [{v['ci'][0]:.1f}, {v['ci'][1]:.1f}]",
                      "-" if theirs != theirs else f"{theirs:.1f}"]
        lines.append(f"| {m} | {s} | {' | '.join(cells)} |")
    return (f"Table 1 (main results), the verdict: {caption(split)}; paper: {reference}. FMR, IR, RR in % "
            f"[95 % interval].\n\n" + "\n".join(lines))


def paper_gaps(split: dict, paper_table, reference: str = "3DMatch", metrics=("FMR", "IR", "RR")) -> list[str]:
    """One line per Table 1 column: each FreeReg variant the paper reports, the committed value with
    its interval against the paper's on ``reference``, and the gap in points."""
    paper_rows = paper_table[paper_table["dataset"] == reference].assign(solver=lambda t: t["solver"].str.lower())
    paper_of = {(r.method, r.solver): r for r in paper_rows.itertuples()}
    lines = []
    for metric in metrics:
        parts = []
        for m, s in VARIANTS:
            theirs = getattr(paper_of.get((m, s)), metric, float("nan"))
            if theirs != theirs:  # the paper has no such row
                continue
            v = split["results"][f"{m} {s}"][metric]
            parts.append(f"{m} + {s} {v['mean']:.1f} [{v['ci'][0]:.1f}, {v['ci'][1]:.1f}] vs {theirs:.1f} "
                         f"({v['mean'] - theirs:+.1f})")
        lines.append(f"{metric}: " + "; ".join(parts))
    return lines
