"""Ranges: every numeric setting has a range declared beside its default, and the one
check (freereg_lib.config.range_problem) runs in FreeRegConfig / config_for, in the notebooks'
parameter check and in the batch grid check; a grid with a duplicate key is refused naming it."""
import dataclasses
import json
import math
from pathlib import Path

import pytest

from freereg_lib.commands import batch
from freereg_lib.config import FreeRegConfig, config_for, field_range, range_problem
from freereg_lib.report.params import ParameterError, check_parameters

# (field, bad value) pairs of the issue and of the brief; each must be refused naming the field.
BAD = [
    ("fusion_w", 2.0), ("fusion_w", -0.5), ("fusion_w", 7), ("fusion_w", math.nan),
    ("t_hat", 5000), ("t_hat", -500),
    ("ransac_iters", 0), ("ransac_iters", -100),
    ("tau_c", -1.0), ("tau_c", 0.0),
    ("rr_rot_deg", -20.0), ("rr_rot_deg", 0.0), ("rr_rot_deg", 181.0),
    ("rr_trans_m", 0.0),
    ("layers", (0, 99)), ("layers", (-1, 4)), ("layers", ()), ("layers", (4, 4)),
    ("ddim_steps", 0), ("guidance_w", -1.0), ("pca_dim", 0), ("keypoint_grid", (0, 44)),
    ("kabsch_inlier_m", 0.0), ("pnp_reproj_px", -1.0), ("depth_min", -0.1),
    ("voxel_size", 0.0), ("fpfh_voxel", -0.05), ("tau_g", -1.0),
    ("kabsch_confidence", 0.0), ("kabsch_confidence", 1.5), ("fusion_w", math.inf),
    ("kabsch_max_scale_ratio", 0.5), ("ransac_n", 2), ("pair_batch", 0), ("seed", -1),
    ("rr_ladder", ((5.0, 0.1), (-5.0, 0.2))), ("fmr_ratio", 1.5), ("ddim_eta", -0.1),
]


@pytest.mark.parametrize("name,value", BAD, ids=[f"{n}={v}" for n, v in BAD])
def test_config_for_refuses_out_of_range_values_naming_the_field(name, value):
    with pytest.raises(ValueError) as err:
        config_for("3dmatch", **{name: value})
    msg = str(err.value)
    assert "\n" not in msg and f"{name}=" in msg
    assert "range" in msg or "distinct" in msg
    with pytest.raises(ValueError, match=name):
        FreeRegConfig(**{name: value})
    with pytest.raises(ValueError, match=name):
        FreeRegConfig().override(**{name: value})


def test_the_message_names_the_value_and_the_range():
    with pytest.raises(ValueError, match=r"fusion_w=2\.0 is out of range: expected \[0, 1\]"):
        config_for("scannet", fusion_w=2.0)
    with pytest.raises(ValueError, match=r"t_hat=5000 is out of range: expected \[0, 999\]"):
        config_for("kitti", t_hat=5000)
    with pytest.raises(ValueError, match=r"layers=\(0, 99\) .*\[0, 8\].*got 99"):
        config_for("3dmatch", layers=[0, 99])  # a list (papermill, YAML) as well


def test_depth_min_must_be_below_depth_max():
    with pytest.raises(ValueError, match="depth_min=10.0 must be below depth_max=10.0"):
        config_for("3dmatch", depth_min=10.0)
    assert config_for("kitti").depth_min < config_for("kitti").depth_max


def test_t_hat_is_not_clamped_and_the_edges_are_accepted():
    assert config_for("3dmatch", t_hat=999).t_hat == 999
    assert config_for("3dmatch", t_hat=0).t_hat == 0
    cfg = config_for("3dmatch", fusion_w=0, kabsch_confidence=1.0, rr_rot_deg=180, layers=[8],
                     kabsch_max_scale_ratio=0.0, edge_filter_m=0.0, tau_g=0.0, guidance_w=0)
    assert cfg.fusion_w == 0 and cfg.layers == (8,)
    assert config_for("3dmatch", kabsch_max_scale_ratio=1.5).kabsch_max_scale_ratio == 1.5


def test_every_numeric_field_declares_a_range_and_the_defaults_are_inside():
    def numeric(tp):
        text = str(tp)
        return any(t in text for t in ("int", "float"))

    hints = {f.name: f.type for f in dataclasses.fields(FreeRegConfig)}
    missing = [n for n, tp in hints.items() if numeric(tp) and field_range(n) is None]
    assert not missing, f"numeric fields without a range: {missing}"
    for dataset in ("3dmatch", "scannet", "demo", "icl", "synthetic_indoor", "kitti", "synthetic_outdoor"):
        cfg = config_for(dataset)
        assert all(range_problem(f.name, getattr(cfg, f.name)) == "" for f in dataclasses.fields(cfg))


def test_a_type_error_still_comes_first():
    with pytest.raises(TypeError, match="ransac_iters"):
        config_for("3dmatch", ransac_iters="0")


# --------------------------------------------------------------------------------------
# The notebooks' papermill parameters.

@pytest.mark.parametrize("params,named", [
    ({"fusion_w": 2.0}, "fusion_w"),
    ({"ransac_iters": 0}, "ransac_iters"),
    ({"layers": [0, 99]}, "layers"),
    ({"t_hats": [300, 5000]}, "t_hat"),             # notebook 01's sweep of t_hat
    ({"weights": [1.0, 0.5, -0.5]}, "fusion_w"),    # notebook 03's fusion weights
    ({"w_fused": 7.0}, "fusion_w"),
    ({"sweep_ransac_iters": -100}, "ransac_iters"),
    ({"config_overrides": {"tau_c": -1.0}}, "tau_c"),
    ({"seed": -1}, "seed"),
])
def test_check_parameters_refuses_out_of_range_config_values(params, named):
    spec = {k: type(v) for k, v in params.items()}
    with pytest.raises(ParameterError, match=named) as err:
        check_parameters(params, spec, injected=[])
    assert "out of range" in str(err.value) and "\n" not in str(err.value)


def test_check_parameters_accepts_values_in_range():
    params = {"fusion_w": 0.5, "t_hats": [300, 150, 0], "weights": [1.0, 0.0], "layers": [0, 4, 6],
              "config_overrides": {"pair_batch": 4, "batched_guidance": True}, "n_pairs": 3}
    assert check_parameters(params, {k: type(v) for k, v in params.items()}, injected=[]) == params


# --------------------------------------------------------------------------------------
# Batch grids.

def _notebook(tmp_path: Path) -> Path:
    """A batch notebook that declares a few config fields (only its parameters are read)."""
    source = ('out_dir = ""\nshard = "0/1"\ndataset = "3dmatch"\nfusion_w = 0.5\nt_hats = [150]\n'
              "config_overrides = {}\n")
    nb = {"cells": [{"cell_type": "code", "execution_count": None, "id": "p", "metadata": {"tags": ["parameters"]},
                     "outputs": [], "source": source}],
          "metadata": {"kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"}},
          "nbformat": 4, "nbformat_minor": 5}
    path = tmp_path / "nb.ipynb"
    path.write_text(json.dumps(nb))
    return path


@pytest.mark.parametrize("line,named", [
    ("base: {fusion_w: 2.0}", "fusion_w"),
    ("grid: {fusion_w: [0.5, -0.5]}", "fusion_w"),
    ("base: {t_hats: [150, 5000]}", "t_hat"),
    ("base: {config_overrides: {rr_rot_deg: -20}}", "rr_rot_deg"),
    ("base: {config_overrides: {layers: [0, 99]}}", "layers"),
])
def test_a_grid_with_an_out_of_range_value_is_refused(tmp_path, line, named):
    grid = tmp_path / "g.yaml"
    grid.write_text(f"notebooks: [{_notebook(tmp_path)}]\n{line}\n")
    with pytest.raises(ValueError, match=named) as err:
        batch.load_grid(grid)
    assert "out of range" in str(err.value)


def test_a_grid_with_a_duplicate_key_is_refused_naming_it(tmp_path, capsys):
    nb = _notebook(tmp_path)
    grid = tmp_path / "dup.yaml"
    grid.write_text(f"notebooks: [{nb}]\nbase:\n  fusion_w: 0.5\n  t_hats: [150]\n  fusion_w: 0.7\n")
    with pytest.raises(ValueError, match=r"line 5.*duplicate key 'fusion_w' \(first at line 3") as err:
        batch.load_grid(grid)
    assert "\n" not in str(err.value)
    top = tmp_path / "dup_top.yaml"
    top.write_text(f"notebooks: [{nb}]\nname: a\nname: b\n")
    assert batch.main(["run", str(top), "--runs-dir", str(tmp_path / "runs")]) == 2
    assert "duplicate key 'name'" in capsys.readouterr().err
    fine = tmp_path / "fine.yaml"  # the same key in two mappings is no duplicate
    fine.write_text(f"notebooks: [{nb}]\nbase: {{fusion_w: 0.5}}\ngrid: {{fusion_w: [0.4, 0.6]}}\n")
    assert len(batch.load_grid(fine).jobs) == 2
