"""Parity with the official FreeReg code, measured on its own outputs (tests/fixtures/parity,
a subset of the official code's full fixture set made by tests/fixtures/make_parity_subset.py), and both settings
of every departure field the fixtures exposed (the fidelity rule: the default is official)."""
from __future__ import annotations

import dataclasses
import io
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from freereg_lib import features, pipeline
from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.geometry import cameras, densify, metrics, pose, projection

ROOT = Path(__file__).resolve().parents[1]
FIX = ROOT / "tests" / "fixtures" / "parity"
sys.path.insert(0, str(ROOT / "tools"))
import parity  # noqa: E402 - a repository tool beside the library, not in it


def case(function: str, name: str):
    return parity.load_case(FIX / function / f"{name}.npz")


def run_quiet(directory) -> tuple[int, list[str]]:
    buf = io.StringIO()
    rc = parity.run(directory, out=buf)
    return rc, buf.getvalue().splitlines()


# --------------------------------------------------------------------------------------
# The runner.

def test_every_bundled_function_is_within_its_tolerance():
    rc, lines = run_quiet(FIX)
    functions = sorted(p.name for p in FIX.iterdir() if p.is_dir())
    assert len(functions) == 26
    by_name = {ln.split(":")[0]: ln for ln in lines[:-1]}
    assert sorted(by_name) == functions
    bad = [ln for ln in lines[:-1] if not ln.endswith(" ok")]
    assert not bad, "\n".join(bad)
    assert lines[-1] == "26 functions: 26 ok, 0 FAIL, 0 skipped"
    assert rc == 0


def test_a_perturbed_fixture_fails_with_exit_code_1(tmp_path):
    src = FIX / "proj_pc2dpt" / "icl_identity.npz"
    (tmp_path / "proj_pc2dpt").mkdir()
    (tmp_path / "eval_pair").mkdir()
    shutil.copy(FIX / "eval_pair" / "icl_mixed.npz", tmp_path / "eval_pair")
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    depth = arrays["out_depth"].copy()
    v, u = np.argwhere(depth > 0)[100]
    depth[v, u] += 1e-6  # one pixel, one micrometre
    arrays["out_depth"] = depth
    np.savez(tmp_path / "proj_pc2dpt" / "icl_identity.npz", **arrays)
    rc, lines = run_quiet(tmp_path)
    assert rc == 1
    assert lines[0].startswith("eval_pair: ") and lines[0].endswith(" ok")
    assert lines[1] == "proj_pc2dpt: max error 1e-06 (tolerance 1e-12) FAIL"
    assert lines[-1] == "2 functions: 1 ok, 1 FAIL, 0 skipped"
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "parity.py"), str(tmp_path)], capture_output=True,
                          text=True, cwd=ROOT)
    assert proc.returncode == 1 and "proj_pc2dpt: max error 1e-06 (tolerance 1e-12) FAIL" in proc.stdout


def test_unknown_function_is_skipped_and_a_missing_output_fails(tmp_path):
    (tmp_path / "not_a_function").mkdir()
    np.savez(tmp_path / "not_a_function" / "c.npz", in_x=np.zeros(2), out_y=np.zeros(2))
    (tmp_path / "return_uv").mkdir()
    ins, outs = case("return_uv", "480x640_8x11")
    np.savez(tmp_path / "return_uv" / "c.npz", **{f"in_{k}": v for k, v in ins.items()},
             **{f"out_{k}": v for k, v in outs.items()}, out_extra=np.zeros(3))
    rc, lines = run_quiet(tmp_path)
    assert lines[0] == "not_a_function: skipped (no counterpart of this function in the project)"
    assert lines[1].startswith("return_uv: max error inf") and lines[1].endswith("FAIL")
    assert rc == 1


def test_pose_counterparts_are_not_skipped():
    # ransacor.run after RANSAC and Refine_trans map to pose.official_refinement / _refine_stage.
    for fn in ("ransacor_run_after_ransac", "Refine_trans", "pnpor_run"):
        r = parity.check_function(FIX / fn)
        assert r["status"] == "ok", parity.format_line(r)


# --------------------------------------------------------------------------------------
# Both settings of each departure field (defaults official; the other value measured).

def test_multiscale_holes_are_255_m_by_default_and_0_on_request():
    ins, outs = case("fill_in_multiscale", "kitti_full")
    official = densify.fill_in_multiscale(ins["depth_map"])
    np.testing.assert_array_equal(official, outs["depth"])
    holes = outs["depth"] == 255.0
    assert holes.sum() == 90825  # the sky above the synthetic scan (225 x 1242 pixels)
    empty = densify.fill_in_multiscale(ins["depth_map"], hole_value=0.0)
    assert np.all(empty[holes] == 0) and np.array_equal(empty[~holes], official[~holes])
    assert FreeRegConfig().multiscale_hole_m == 255.0
    ins0, outs0 = case("fill_in_multiscale", "all_zero")
    assert np.all(densify.densify(ins0["depth_map"], "multiscale") == 255.0)
    assert np.all(densify.densify(ins0["depth_map"], "multiscale", hole_value=0.0) == 0.0)


def test_fewer_than_3_evaluable_matches_score_ir_1_in_1_or_0_on_request():
    ins, outs = case("eval_pair", "fewer_than_3_evaluable")
    assert float(outs["IR"]) == 1.0 and int(outs["IN"]) == 1
    got = parity._eval_pair(ins)
    assert (got["IR"], got["IN"]) == (1.0, 1)
    assert FreeRegConfig().eval_few_matches == "official"
    zero = parity._score_pair(ins["rgb_kpts_uv"], ins["rgb_gtd"], ins["dpt_kpts_uv"], ins["dpt_gtd"], ins["pps"],
                              ins["gt"], ins["rgb_intrinsic"], ins["dpt_intrinsic"],
                              (float(ins["mask_min"]), float(ins["mask_max"])), float(ins["ir_thres"]), "zero")
    assert (zero["IR"], zero["IN"]) == (0.0, 0) and len(zero["gt_xyz_s"]) == 1
    rows = [{"IR": 1.0, "IN": 1, "n_evaluable": 1}, {"IR": 0.5, "IN": 10, "n_evaluable": 20},
            {"IR": 0.0, "IN": 0, "n_evaluable": -1}]
    assert metrics.aggregate(rows)["n_few_evaluable"] == 1


def test_cloud_projection_truncates_as_the_official_code_and_rounds_on_request():
    ins, outs = case("proj_pc2dpt", "icl_identity")
    T = np.linalg.inv(ins["extrinsic"])
    size = (int(ins["h"]), int(ins["w"]))
    official, _ = projection.project_to_depth(ins["ply"], ins["intrinsic"], T, size, pixel="official")
    np.testing.assert_array_equal(official, outs["depth"])
    rounded, _ = projection.project_to_depth(ins["ply"], ins["intrinsic"], T, size, 0.01, 10.0)
    differ = (rounded > 0) != (outs["depth"] > 0)
    assert differ.sum() == 37338  # of 307,200 pixels, filled by one rule and not the other (20k points)
    assert FreeRegConfig().cloud_projection == "official"


def test_depth_view_projects_officially_and_hints_from_the_unclipped_map():
    from freereg_lib.data import synthetic

    pair = synthetic.make_pair("outdoor", seed=3)
    cfg = config_for("synthetic_outdoor")
    view = pipeline.depth_view(pair, cfg)
    official, _ = projection.project_to_depth(pair.points, pair.K_depth, cameras.invert(pair.T_pc_sensor),
                                              pair.depth_size, pixel="official")
    np.testing.assert_array_equal(view.raw, official)
    # KITTI-style densification leaves the sky at 255 m: the hint sees it ("far"), the keypoints do not.
    assert (view.full == 255.0).any() and not (view.dense == 255.0).any()
    assert view.hint_depth is view.full
    rounded = pipeline.depth_view(pair, cfg.override(cloud_projection="round"))
    assert not np.array_equal(rounded.raw, view.raw)


def test_hint_from_the_unclipped_png_matches_load_dpt_and_a_clipped_one_does_not():
    from freereg_lib.models.base import hint_image, official_resize_hw

    ins, outs = case("load_dpt", "kitti_dense_full")
    png = ins["depth_png_u16"]
    hw = official_resize_hw(*png.shape)
    np.testing.assert_array_equal(hint_image(png, hw)[:, :, 0], outs["hint_c0"])
    clipped = projection.clip_to_range(png / 256.0, 0.5, 80.0)  # the 255 m holes become 0 ("near")
    assert np.abs(hint_image(clipped, hw)[:, :, 0].astype(int) - outs["hint_c0"]).max() == 255


def test_merged_pca_map_is_not_normalised_by_default():
    ins, outs = case("merge_feat", "layers046_diff_sizes")
    got = parity._merge_feat(ins)
    errs = {k: e for k, e, _ in parity.compare("merge_feat", got, outs)}
    assert max(errs.values()) < 1e-3
    layers = [int(k) for k in ins["checklayers"]]
    S = {k: ins[f"s_layer{k}"] for k in layers}
    T = {k: ins[f"t_layer{k}"] for k in layers}
    fs, ft = features.pca_reduce(S, T, layers, int(ins["pca_dim"]), normalize=True)
    errs_n = {k: e for k, e, _ in parity.compare("merge_feat", {**got, "fs": fs, "ft": ft}, outs)}
    assert errs_n["fs"] > 0.1 and errs_n["ft"] > 0.1


def test_feature_cloud_ends_at_10_m_on_scannet_as_the_official_proj():
    ins, outs = case("spconv_feature_extract", "scannet_dpt")
    cfg = config_for("scannet")
    assert (cfg.depth_max, cfg.cloud_far_m) == (15.0, 10.0)
    pts, _ = projection.feature_cloud(ins["dpt"], ins["intrinsic"], cfg, monocular=False)
    np.testing.assert_allclose(pts, outs["pc"], atol=1e-12)
    wide, _ = projection.feature_cloud(ins["dpt"], ins["intrinsic"], cfg.override(cloud_far_m=15.0), False)
    assert len(wide) > len(pts)


# --------------------------------------------------------------------------------------
# Evaluation truth: the demo's dense target_dpt.gtd.png, not the sparse projected cloud.

def test_demo_depth_side_is_scored_with_target_dpt_gtd(tmp_path):
    from test_loaders import POSES, make_demo, render, write_depth

    from freereg_lib.data.datasets.demo import load_demo_pair

    root, K_rgb, K_dpt, points = make_demo(tmp_path / "demo", rgb_size=(72, 96), dpt_size=(36, 48))
    truth = render(K_dpt, POSES[1], (36, 48))
    write_depth(root / "just_for_eval" / "target_dpt.gtd.png", truth)
    # A sparse cloud, as the demo's 17k points: a tenth of the pixels.
    keep = np.random.default_rng(0).random(len(points)) < 0.1
    ply = root / "target_pc.ply"
    header = (f"ply\nformat ascii 1.0\nelement vertex {keep.sum()}\nproperty double x\nproperty double y\n"
              "property double z\nend_header\n")
    ply.write_text(header + "\n".join(" ".join(repr(float(v)) for v in p) for p in points[keep]) + "\n")
    pair = load_demo_pair(root)
    assert pair.depth_frame_gt is not None
    np.testing.assert_allclose(pair.depth_frame_gt, np.round(truth * 1000) / 1000, atol=1e-3)
    cfg = config_for("demo")
    view = pipeline.depth_view(pair, cfg)
    gt, source = pipeline.evaluation_truth(pair, view, cfg)
    assert source == "truth file" and gt is pair.depth_frame_gt
    uv = np.argwhere(truth > 0)[:, ::-1].astype(float)[::7]
    n_file = np.isfinite(metrics.lift_truth(uv, gt, K_dpt)).all(1).sum()
    n_cloud = np.isfinite(metrics.lift_truth(uv, view.raw, K_dpt)).all(1).sum()
    assert n_file == len(uv) and n_cloud < 0.3 * len(uv)
    feats = pipeline.PairFeatures(uv_image=uv, pts_image=np.zeros((len(uv), 3)), uv_depth=uv,
                                  pts_depth=np.zeros((len(uv), 3)), diff_image=None, diff_depth=None,
                                  geo_image=None, geo_depth=None, mono_depth=None, view=view)
    m = pipeline.Matches(np.arange(len(uv)), np.arange(len(uv)))
    res = dataclasses.replace(pose.PoseResult(np.eye(4), False, "pnp"))
    row = pipeline.evaluate(pair, feats, m, res, cfg)
    assert row["n_evaluable"] > n_cloud


# --------------------------------------------------------------------------------------
# The paper's setting on the real backend.

def test_table1_grid_runs_fcgf_and_the_official_kabsch():
    from freereg_lib.commands import batch

    grid = batch.load_grid(ROOT / "freereg_lib/data/grids/table1.yaml")
    assert len(grid.jobs) == 3
    for job in grid.jobs:
        p = job.params
        assert (p["backend"], p["geometric_method"], p["kabsch_scoring"]) == ("real", "fcgf", "official")
        cfg = config_for(p["dataset"], geometric=p["geometric_method"], kabsch_scoring=p["kabsch_scoring"])
        assert (cfg.geometric, cfg.kabsch_scoring) == ("fcgf", "official")


def test_benchmark_notebook_picks_fcgf_on_the_real_backend():
    import json

    nb = json.loads((ROOT / "notebooks/04_benchmark.ipynb").read_text())
    params = "".join(next(c for c in nb["cells"] if "parameters" in c.get("metadata", {}).get("tags", []))["source"])
    assert 'geometric_method: "Optional[str]" = None' in params and 'kabsch_scoring: str = "official"' in params
    setup = "".join(next(c for c in nb["cells"] if "cfg = config_for(" in "".join(c["source"]))["source"])
    env = {"geometric_method": None, "backend_name": "real"}
    exec(setup.split("cfg = config_for(")[0].split("backend_name = backend\n", 1)[1], env)
    assert env["geometric_method"] == "fcgf"
    env = {"geometric_method": None, "backend_name": "micro"}
    exec(setup.split("cfg = config_for(")[0].split("backend_name = backend\n", 1)[1], env)
    assert env["geometric_method"] == "fpfh"


def test_densified_map_goes_through_the_official_uint16_png_or_stays_float_on_request():
    ins, outs = case("gen_meta_run", "scannet")
    raw = ins["depth0"] / 1000.0
    dense = densify.densify(raw, "fast")
    np.testing.assert_array_equal(densify.png_round_trip(dense, 1000.0), outs["dense0"] / 1000.0)
    gap = dense - outs["dense0"] / 1000.0
    assert 0 < gap.max() < 1e-3 and gap.min() > -1e-6  # the float map is up to 1 mm deeper (float32 rounding aside)
    from freereg_lib.data.pair import Pair

    K = cameras.intrinsics(100.0, 100.0, 63.5, 47.5)
    pair = Pair(image=np.zeros((96, 128, 3), np.uint8), K_image=K, points=cameras.backproject(raw, K)[0], K_depth=K,
                depth_size=(96, 128), T_pc_sensor=np.eye(4), T_cam_pc=np.eye(4), sensor_depth=raw, name="s")
    view = pipeline.depth_view(pair, config_for("scannet"))
    np.testing.assert_array_equal(view.full, outs["dense0"] / 1000.0)
    floats = pipeline.depth_view(pair, config_for("scannet", dense_png=False))
    np.testing.assert_array_equal(floats.full, dense)
    assert config_for("kitti").depth_png_scale == 256.0
