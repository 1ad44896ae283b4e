"""The notebooks' charts of numbers: metrics by method or parameter, the paper's rows beside the
re-run, error curves and registration-recall ladders (pictures of images and clouds are
:mod:`.plots`)."""
from __future__ import annotations

import numpy as np

from freereg_lib.report.plots import FIG_WIDTH_IN, _plt

PERCENT_METRICS = ("FMR", "IR", "RR")  # metrics in % (IN is a count per pair)


def metric_label(metric: str) -> str:
    """An axis label for a metric: ``"IR (%)"`` for the percentage metrics, the name otherwise."""
    base = str(metric).split("@")[0].split("_")[0]
    return f"{metric} (%)" if base in PERCENT_METRICS else ("IN (correct matches per pair)" if metric == "IN" else str(metric))


def _metric_axis(ax, metric: str, label: str | None = None) -> None:
    """Label ``ax``'s y axis for ``metric``; a percentage metric's ticks read e.g. ``40%``."""
    ax.set_ylabel(label or metric_label(metric))
    if str(metric).split("@")[0].split("_")[0] in PERCENT_METRICS:
        from matplotlib.ticker import PercentFormatter

        ax.yaxis.set_major_formatter(PercentFormatter(xmax=100, decimals=0))


def captioned(table, columns=("backend",)):
    """A paper-beside-run table for the page: each of ``columns`` that holds one value in every row (the
    backend that produced the re-run, the paper's dataset) is printed once, as a caption line above the
    table, and dropped from it; a column with several values stays. The CSV keeps every column."""
    same = [c for c in columns if c in table.columns and table[c].nunique(dropna=False) == 1]
    if same:
        print("; ".join(f"{c}: {table[c].iloc[0]}" for c in same))
    return table.drop(columns=same)


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
    fig, ax = plt.subplots(figsize=(min(FIG_WIDTH_IN, max(5, 0.6 * len(table) + 2)), 3.6))
    x = np.arange(len(table))
    ax.bar(x - 0.2, table[f"{metric}_paper"], width=0.4, label="paper")
    ax.bar(x + 0.2, table[metric], width=0.4, label="re-run")
    ax.set_xticks(x, [str(v) for v in table[label_col]], rotation=30, ha="right")
    _metric_axis(ax, metric)
    ax.set_title(title, fontsize=10)
    ax.legend()
    fig.tight_layout()
    return fig


def metric_vs_param(table, x: str, metrics: list[str], group: str, title: str = "",
                    xlabel: str | None = None, ylabels: dict | None = None):
    """One panel per metric: ``metric`` against ``x``, one line per value of ``group`` (up to three
    panels a row)."""
    plt = _plt()
    cols = min(len(metrics), 3)
    rows = int(np.ceil(len(metrics) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(min(FIG_WIDTH_IN, 4.2 * cols), 3.4 * rows + 0.3), squeeze=False)
    for ax in axes.ravel()[len(metrics):]:
        ax.axis("off")
    for ax, m in zip(axes.ravel(), metrics):
        for k, (g, sub) in enumerate(table.groupby(group, sort=False)):
            sub = sub.sort_values(x)
            ax.plot(sub[x], sub[m], marker="o", color=f"C{k}", label=str(g))
        ax.set_xlabel(xlabel or x, fontsize=9)
        _metric_axis(ax, m, (ylabels or {}).get(m))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def paper_vs_rerun(table, x: str, metrics: list[str], title: str, xlabel: str | None = None,
                    ours_label: str = "re-run"):
    """One panel per metric: the paper's ``<metric>_paper`` and the re-run's ``<metric>``
    against the knob ``x`` (a column of ``table``, e.g. the output of ``paper.side_by_side``)."""
    plt = _plt()
    t = table.sort_values(x)
    fig, axes = plt.subplots(1, len(metrics), figsize=(min(FIG_WIDTH_IN, 3.6 * len(metrics)), 3.4), squeeze=False)
    for ax, m in zip(axes.ravel(), metrics):
        if f"{m}_paper" in t.columns:
            ax.plot(t[x], t[f"{m}_paper"], "o--", color="0.35", label="paper (3DMatch)")
        if m in t.columns:
            ax.plot(t[x], t[m], "o-", color="tab:blue", label=ours_label)
        ax.set_xlabel(xlabel or x)
        _metric_axis(ax, m)
        ax.set_title(m)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def metric_bars(table, metrics: list[str], label_col: str, title: str, ours_label: str = "re-run",
                paper_label: str = "paper"):
    """One panel per metric: grouped bars of the paper (``<metric>_paper``) and the re-run
    (``<metric>``) for each row of ``table`` (e.g. ``paper.side_by_side``), labelled by
    ``label_col``. A missing value (NaN) draws no bar and is marked "n/a" under its slot."""
    plt = _plt()
    labels = [str(v) for v in table[label_col]]
    x = np.arange(len(labels))
    cols = 1 if len(metrics) == 1 else 2
    rows = int(np.ceil(len(metrics) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(min(FIG_WIDTH_IN, max(3.2, 0.75 * len(labels) + 1.6) * cols),
                                                  3.3 * rows + 0.6), squeeze=False)
    for ax in axes.ravel()[len(metrics):]:
        ax.axis("off")
    for ax, m in zip(axes.ravel(), metrics):
        for offset, col, lab, colour in ((-0.2, f"{m}_paper", paper_label, "0.6"), (0.2, m, ours_label, "tab:blue")):
            vals = np.asarray(table[col], dtype=np.float64) if col in table.columns else np.full(len(x), np.nan)
            ax.bar(x + offset, np.nan_to_num(vals), width=0.4, label=lab, color=colour)
            for k in np.nonzero(~np.isfinite(vals))[0]:
                ax.text(x[k] + offset, 0, "n/a", ha="center", va="bottom", fontsize=7, rotation=90)
        ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
        _metric_axis(ax, m)
        ax.set_title(m)
        ax.grid(axis="y", alpha=0.3)
    handles, names = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.05 / rows, 1, 1))  # room for the legend under the panels
    return fig


def rr_ladder(table, rungs: list[str], label_col: str, title: str, ours_label: str = "re-run",
              paper_label: str = "paper"):
    """RR (%) over a ladder of (rotation, translation) thresholds, one line per row of ``table``.

    ``rungs`` are the ladder's column names, loosest last (e.g. ``"RR@5deg/0.1m"``); a row's
    re-run values are ``table[rung]`` (solid) and the paper's ``table[rung + "_paper"]``
    (dashed, same colour). Rows without any finite value on a side draw no line for it.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(rungs) + 2), 4.0))
    x = np.arange(len(rungs))
    for k, (_, row) in enumerate(table.iterrows()):
        dodge = 0.06 * (k - (len(table) - 1) / 2)  # rows with equal values stay visible side by side
        for suffix, style, who in (("", "o-", ours_label), ("_paper", "s--", paper_label)):
            cols = [f"{r}{suffix}" for r in rungs]
            if not all(c in table.columns for c in cols):
                continue
            y = np.array([row[c] for c in cols], dtype=np.float64)
            if np.isfinite(y).any():
                ax.plot(x + dodge, y, style, color=f"C{k}", label=f"{row[label_col]} ({who})",
                        alpha=1.0 if suffix == "" else 0.6)
    ax.set_xticks(x, [r.replace("RR@", "") for r in rungs], fontsize=8)
    ax.set_xlabel("threshold (rotation / translation), tighter to looser")
    ax.set_ylabel("RR (% of pairs registered)")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def paper_scatter(paper_values, ours, labels, metric: str, title: str, ours_label: str = "re-run"):
    """Each row of a table as a point: the paper's value (x) against the re-run's (y), labelled,
    so that agreement in *order* shows as a rising cloud whatever the two scales are."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(min(FIG_WIDTH_IN, 6.0), 4.2))
    x, y = np.asarray(paper_values, dtype=float), np.asarray(ours, dtype=float)
    ax.scatter(x, y, color="tab:blue")
    for xi, yi, text in zip(x, y, labels):
        ax.annotate(str(text), (xi, yi), textcoords="offset points", xytext=(3, 3), fontsize=7)
    ax.set_xlabel(f"{metric} (%), paper")
    ax.set_ylabel(f"{metric} (%), {ours_label}")
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig
