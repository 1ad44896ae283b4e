"""The mono-modality table's command (training/evaluate_mono, Table 10, mono-modality registration):
its features against the pipeline's, depth to depth with true matches recovering the pose, a one-pair
run on the stub backend and its summary, the verdict, and its bad arguments."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from freereg_lib import pipeline
from freereg_lib.config import FreeRegConfig
from freereg_lib.data import synthetic
from freereg_lib.geometry import cameras
from freereg_lib.models import get_backend
from freereg_lib.training import evaluate_mono, verdicts
from freereg_lib.training.splits import TEST

FAST = {"ransac_iters": 2000}


@pytest.fixture(scope="module")
def pair():
    return synthetic.make_pair("indoor", seed=TEST.pair_seeds(1)[0], depth_camera_image=True)


@pytest.fixture(scope="module")
def stub_sides(pair):
    cfg = FreeRegConfig(seed=0).override(**FAST)
    backend = get_backend("stub", cfg)
    by_modality, _ = evaluate_mono.sides(pair, backend, cfg)
    return cfg, backend, by_modality


def test_the_cross_row_has_the_pipelines_features(pair, stub_sides):
    cfg, backend, by_modality = stub_sides
    a, b = by_modality["cross"]
    ours = evaluate_mono.mono_features(pair, a, b, cfg, backend)
    theirs = pipeline.compute_features(pair, backend, cfg, maps=(a.maps, b.maps), mono=a.lift)
    for f in ("uv_image", "pts_image", "uv_depth", "pts_depth", "diff_image", "diff_depth", "geo_image", "geo_depth"):
        np.testing.assert_allclose(getattr(ours, f), getattr(theirs, f), err_msg=f)


def test_depth_to_depth_with_the_true_matches_recovers_the_pose(pair, stub_sides):
    """Both DPT sides' keypoints, lifted and put in the world with their own camera's pose, meet
    where the scene is the same: the true correspondences then give the known pose."""
    cfg, backend, by_modality = stub_sides
    feats = evaluate_mono.mono_features(pair, *by_modality["DPT"], cfg, backend, geometric=False)
    good = np.flatnonzero(np.isfinite(feats.pts_image).all(1))
    world_a = cameras.transform(cameras.invert(pair.T_cam_pc), feats.pts_image[good])
    dist, j = cKDTree(feats.pts_depth).query(world_a)
    close = dist < 0.02
    assert close.sum() > 50, close.sum()
    m = pipeline.Matches(good[close], j[close])
    res = pipeline.solve(pair, feats, m, cfg, "kabsch")
    scores = pipeline.evaluate(pair, feats, m, res, cfg)
    assert res.success and scores["registered"] and scores["RE"] < 1.0 and scores["TE"] < 0.05, scores
    assert scores["IR"] > 0.95, scores


def test_one_stub_pair_gives_every_row_and_its_summary_counts_them(tmp_path):
    rows = tmp_path / "rows.jsonl"
    evaluate_mono.run("test", 1, rows, "stub", progress=False, **FAST)
    evaluate_mono.run("test", 1, rows, "stub", progress=False, **FAST)  # resumes: nothing left to do
    recs = [json.loads(line) for line in rows.read_text().splitlines()]
    assert [r["k"] for r in recs] == [0] and recs[0]["config_changes"] == FAST
    got = [(r["modality"], r["solver"]) for r in recs[0]["rows"]]
    assert got == [("RGB", "kabsch"), ("DPT", "kabsch"), ("cross", "kabsch"), ("cross", "pnp")]
    assert all(not r["error"] and r["n_matches"] > 0 and 0 <= r["IR"] <= 1 for r in recs[0]["rows"]), recs[0]["rows"]
    res = evaluate_mono.summarize(recs, "test")
    assert res["n_pairs"] == 1 and all(v["n_rows"] == 1 for v in res["results"].values())
    for key, v in res["results"].items():
        m, s = key.split()
        row = next(r for r in recs[0]["rows"] if r["modality"] == m and r["solver"] == s)
        assert v["IR"]["mean"] == pytest.approx(100 * row["IR"]) and v["RR"]["mean"] == 100 * int(row["registered"])
    assert set(res["tests"]) == {f"{k}: {a} - {b}" for a, b in evaluate_mono.TESTS for k in ("RR kabsch", "IR")}


def test_the_verdict_reads_the_committed_json(tmp_path, monkeypatch):
    def rec(k, reg):
        return {"k": k, "label": "stub", "load_average": 1.0, "seconds": 2.0, "seconds_parts": {}, "rows": [
            {"modality": m, "solver": s, "n_matches": 10, "IR": 0.5, "IN": 5, "RE": 1.0, "TE": 0.1,
             "registered": reg[m], "n_evaluable": 10, "error": ""}
            for m in evaluate_mono.MODALITIES for s in evaluate_mono.SOLVERS[m]]}
    recs = [rec(k, {"RGB": True, "DPT": True, "cross": k % 2 == 0}) for k in range(4)]
    (tmp_path / verdicts.MONO_JSON).write_text(json.dumps(evaluate_mono.summarize(recs, "test")))
    monkeypatch.setattr(verdicts, "load", lambda name: json.loads((tmp_path / name).read_text()))
    lines = verdicts.table10()
    assert "4 synthetic indoor pairs" in lines[0] and "RR 74.2" in lines[1] and "RR 63.8" in lines[3], lines
    assert "RGB to RGB - image to cloud (the paper: RR +10.4" in lines[4] and "RR +50.0 points" in lines[4], lines
    assert "IR +0.0 points (p = 1.0000, not significant at 5 %) -> cannot be told (4 pairs, fewer than 30)" in lines[4], lines
    assert "RR +0.0 points [+0.0, +0.0]" in lines[6] and "cannot be told (4 pairs" in lines[6], lines
    assert lines[7].endswith("RGB to RGB cannot be told (4 pairs, fewer than 30); depth to depth cannot be told "
                             "(4 pairs, fewer than 30)"), lines


@pytest.mark.parametrize("argv, message", [
    (["--pairs", "0", "--rows", "r.jsonl"], "--pairs must be >= 1, got 0"),
    (["--summarize", "--rows", "missing.jsonl"], "no such file"),
])
def test_bad_arguments_stop_with_one_line(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        evaluate_mono.main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and message in err and len(err.strip().splitlines()[-1]) > 0
