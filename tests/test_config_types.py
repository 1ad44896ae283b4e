"""FreeRegConfig checks the types of its fields: a wrong-typed value fails once, naming the field."""
import dataclasses

import numpy as np
import pytest

from freereg_lib.config import FreeRegConfig, config_for

DATASETS = ["3dmatch", "scannet", "icl", "synthetic_indoor", "kitti", "synthetic_outdoor", "demo"]


@pytest.mark.parametrize("dataset", DATASETS)
def test_every_default_and_dataset_config_passes(dataset):
    cfg = config_for(dataset)
    assert dataclasses.replace(cfg) == cfg
    FreeRegConfig()


def test_lists_from_papermill_and_yaml_become_tuples_and_ints_are_floats():
    cfg = config_for("kitti", keypoint_grid=[8, 8], rr_ladder=[[1, 2], [3.0, 4.0]], layers=[0, 4],
                     depth_max=15, seed=np.int64(3))
    assert cfg.keypoint_grid == (8, 8) and cfg.layers == (0, 4) and cfg.rr_ladder == ((1, 2), (3.0, 4.0))
    hash(cfg.layers)
    assert cfg == config_for("kitti", keypoint_grid=(8, 8), rr_ladder=((1, 2), (3.0, 4.0)), layers=(0, 4),
                             depth_max=15.0, seed=3)


@pytest.mark.parametrize("change, message", [
    ({"ransac_iters": "2000"}, r"ransac_iters='2000' is str, expected int.*YAML reads 5e4"),
    ({"depth_max": "5e4"}, r"depth_max='5e4' is str, expected float"),
    ({"kabsch_with_scale": "false"}, r"kabsch_with_scale='false' is str, expected bool"),
    ({"ransac_iters": True}, r"ransac_iters=True is bool, expected int"),
    ({"keypoint_grid": (1, 2, 3)}, r"keypoint_grid"),
    ({"pca_device": 3}, r"pca_device=3 is int"),
    ({"layers": ["0", "4"]}, r"layers"),
])
def test_wrong_types_are_refused_naming_the_field(change, message):
    with pytest.raises(TypeError, match=message):
        config_for("3dmatch", **change)
    with pytest.raises(TypeError, match=message):
        FreeRegConfig().override(**change)


def test_every_config_field_is_in_exactly_one_group():
    import dataclasses

    from freereg_lib.config import GROUPS

    names = [f.name for f in dataclasses.fields(FreeRegConfig)]
    placed = [f for fields in GROUPS.values() for f in fields]
    assert sorted(placed) == sorted(names), (set(names) ^ set(placed), [f for f in placed if placed.count(f) > 1])
    cfg = FreeRegConfig().override(ransac_iters=7, tau_c=0.25)
    assert cfg.group("solvers")["ransac_iters"] == 7 and cfg.group("evaluation")["tau_c"] == 0.25
    with pytest.raises(KeyError, match="unknown config group"):
        cfg.group("solver")
