"""Figures a reader can read at their natural size: ``plots.save`` writes PNGs
at most ``plots.MAX_WIDTH_PX`` wide and ``plots.MAX_BYTES`` large, whatever the figure's size, and
the layouts keep metric axes in % and depth panels with a colour bar in metres."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

from freereg_lib.report import charts, plots  # noqa: E402


def _noisy_wide_figure():
    """A deliberately bad figure: 24 x 5 inches (2640 px at the old 110 dpi) of random colours,
    which a plain ``savefig`` writes as several MB."""
    rng = np.random.default_rng(0)
    fig, axes = plt.subplots(1, 4, figsize=(24, 5))
    for ax in axes:
        ax.imshow(rng.random((240, 320, 3)))
        ax.set_title("a wide strip of noisy panels")
    return fig


def test_save_caps_width_and_bytes(tmp_path):
    fig = _noisy_wide_figure()
    fig.savefig(tmp_path / "plain.png", dpi=110, bbox_inches="tight")  # what save used to write
    path = plots.save(fig, "wide", tmp_path)
    plt.close(fig)
    with Image.open(tmp_path / "plain.png") as im:
        assert im.width > 2000  # the figure really is too wide for a plain savefig
    assert (tmp_path / "plain.png").stat().st_size > plots.MAX_BYTES
    assert path == tmp_path / "wide.png"
    with Image.open(path) as im:
        assert im.width <= plots.MAX_WIDTH_PX <= 1000
        assert im.width >= 0.9 * plots.MAX_WIDTH_PX  # lowered dpi, not a thumbnail
    assert path.stat().st_size <= plots.MAX_BYTES <= 400_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain.png", "wide.png"]  # no temporary left behind


def test_save_keeps_a_narrow_figure_at_full_dpi(tmp_path):
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.plot([0, 1], [0, 1])
    path = plots.save(fig, "narrow", tmp_path)
    plt.close(fig)
    with Image.open(path) as im:
        # 5 in at 110 dpi is 550 px (the tight box trims a little, never adds 100 px)
        assert 450 <= im.width <= 5 * plots.DPI + 20


@pytest.mark.parametrize("draw", ["depth_error_maps", "similarity_maps", "metric_bars", "show_images", "match_panels"])
def test_layouts_fit_the_width(draw):
    rng = np.random.default_rng(1)
    image = rng.random((120, 160, 3))
    depth = rng.uniform(0.5, 4.0, (120, 160))
    if draw == "depth_error_maps":
        fig = plots.depth_error_maps(image, depth, depth * 1.1, title="t")
    elif draw == "similarity_maps":
        uv = rng.uniform(0, 120, (50, 2))
        fig = plots.similarity_maps(image, uv[0], image, uv, {k: rng.random(50) for k in "abc"}, suptitle="s")
    elif draw == "metric_bars":
        t = pd.DataFrame({"method": list("abcdef"), **{m: rng.random(6) * 100 for m in ("FMR", "IR", "IN", "RR")},
                          **{f"{m}_paper": rng.random(6) * 100 for m in ("FMR", "IR", "IN", "RR")}})
        fig = charts.metric_bars(t, ["FMR", "IR", "IN", "RR"], "method", "Table 1")
    elif draw == "show_images":
        fig = plots.show_images([image, plots.depth_panel(depth), plots.depth_panel(depth, 5.0)], list("abc"), "s")
    else:
        uv = rng.uniform(0, 120, (20, 2))
        fig = plots.match_panels(image, image, [dict(uv_image=uv, uv_depth=uv, correct=None, title="x")] * 3)
    # the layout, not a lowered dpi, keeps the width: at the full dpi it fits MAX_WIDTH_PX
    assert fig.get_size_inches()[0] * plots.DPI <= plots.MAX_WIDTH_PX
    plt.close(fig)


def test_metric_axes_in_percent_and_depth_colour_bars_in_metres():
    assert charts.metric_label("IR") == "IR (%)"
    assert charts.metric_label("RR@5deg/0.1m") == "RR@5deg/0.1m (%)"
    assert "%" not in charts.metric_label("IN")
    t = pd.DataFrame({"w": [0.0, 0.5, 1.0], "IR": [10.0, 20.0, 15.0], "IR_paper": [30.0, 45.0, 39.0]})
    fig = charts.paper_vs_rerun(t, "w", ["IR"], "Table 4")
    ax = fig.axes[0]
    fig.canvas.draw()
    assert ax.get_ylabel() == "IR (%)"
    assert all(lab.get_text().endswith("%") for lab in ax.get_yticklabels() if lab.get_text())
    plt.close(fig)
    for draw in (plots.show_images, plots.image_grid):
        fig = draw([np.zeros((10, 20, 3)), plots.depth_panel(np.full((10, 20), 2.0))], ["a", "b"])
        assert [a.get_ylabel() for a in fig.axes if a.get_label() == "<colorbar>"] == ["depth (m)"]
        plt.close(fig)


def test_a_paper_beside_run_table_names_its_backend_once_above_it(capsys):
    """The backend (and any column given that holds one value) is a caption line, not a column repeated in
    every row; a column with several values stays."""
    from freereg_lib.data import paper

    ours = pd.DataFrame({"w": [1.0, 0.5, 0.0], "IR": [19.4, 20.3, 4.3], "RR": [10.0, 17.0, 1.0]})
    label = "micro backend (SD-layout diffusion models + ZoeDepth, trained on synthetic rooms)"
    table = paper.side_by_side(paper.table("table4_fusion_weight"), ours, ["w"], ["IR", "RR"], backend=label)
    assert (table["backend"] == label).all()  # the CSV keeps it
    shown = charts.captioned(table.assign(split=["a", "b"] * (len(table) // 2) + ["a"] * (len(table) % 2)),
                             ("backend", "split"))
    assert capsys.readouterr().out == f"backend: {label}\n"
    assert "backend" not in shown.columns and "split" in shown.columns and len(shown) == len(table)
