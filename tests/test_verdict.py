"""The verdict of ``freereg register`` (REGISTERED / FAILED without ground truth): the rows its rule
is fitted and reported on are measured with the command's chain (``tools/verdict_holdout.py``);
the rule and its rates: ``tests/test_verdict_holdout.py``."""
from __future__ import annotations

from conftest import load_tool


def test_the_rows_are_measured_with_the_commands_chain(tmp_path):
    tool = load_tool("verdict_holdout")
    out = tmp_path / "rows.csv"
    rows = tool.half_rows("report", str(out), n_pairs=1, iters=300)
    assert rows["pair"].tolist() == ["icl/00110-00120"] * 4 and (rows["gap"] == 10).all()
    assert set(zip(rows["depth"], rows["solver"])) == {(d, s) for d in ("stub", "true") for s in ("kabsch", "pnp")}
    assert (rows["n_matches"] > 50).all() and {"success", "n_inliers", "scale", "RE", "TE"} <= set(rows)
    assert tool.half_rows("report", str(out), n_pairs=1, iters=300).equals(rows)  # a rerun skips what is there


def test_the_null_is_the_solver_on_the_matches_shuffled():
    # The same solver on the same inputs with the matches' depth side shuffled: a right pose has
    # several times its support; the null is seeded (a rerun agrees) and cheap (10k iterations).
    import dataclasses

    from freereg_lib import pipeline
    from freereg_lib.config import config_for
    from freereg_lib.data.datasets.icl import ICLSample
    from freereg_lib.models import get_backend
    from freereg_lib.pipeline import verdict

    cfg = config_for("3dmatch", ransac_iters=2000)
    pair = dataclasses.replace(ICLSample().pair(0, 20), sensor_depth=None)
    feats = pipeline.compute_features(pair, get_backend("stub", cfg), cfg, diffusion=False, geometric=True,
                                      mono=pair.depth_gt)
    m = pipeline.match(feats, 0.0)
    res = pipeline.solve(pair, feats, m, cfg, "kabsch")
    nulls = verdict.null_inliers(pair, feats, m, cfg, "kabsch")
    assert len(nulls) == verdict.NULL_SHUFFLES["kabsch"] and nulls == verdict.null_inliers(pair, feats, m, cfg, "kabsch")
    assert max(nulls) < res.n_inliers / 3, (nulls, res.n_inliers)
    assert verdict.decide(res, nulls, "kabsch", cfg)[0]


def test_another_folder_is_measured_on_its_overlapping_pairs(tmp_path):
    # ``sample --root``: a folder in the ICL layout (here 2 of the shipped TUM frames), every ordered
    # pair i != j above the least overlap (i < j first), the JSON with the machine that measured it.
    import json
    import shutil

    from freereg_lib.data.datasets.icl import TUM_ROOT, ICLSample

    tool = load_tool("verdict_holdout")
    root = tmp_path / "tiny"
    for sub in ("color", "depth"):
        (root / sub).mkdir(parents=True)
        for f in (126, 129):
            name = f"{f:05d}.{'jpg' if sub == 'color' else 'png'}"
            shutil.copy(TUM_ROOT / sub / name, root / sub / name)
    for name in ("intrinsics.json", "trajectory.log", "trajectory_depth.log"):
        shutil.copy(TUM_ROOT / name, root / name)
    assert tool.overlapping_pairs(ICLSample(root)) == [(126, 129), (129, 126)]
    assert tool.overlapping_pairs(ICLSample(root), min_overlap=0.99) == []
    out = tmp_path / "rows.json"
    rows = tool.sample_rows(str(out), root, n_pairs=1, iters=300)
    assert rows["pair"].tolist() == ["tiny/00126-00129"] * 4 and (rows["gap"] == 3).all()
    assert (rows["setting"] == "3dmatch").all() and rows["null_inliers"].notna().all()
    doc = json.loads(out.read_text())
    assert doc["provenance"]["cpu"]["model"] and (doc["pairs_listed"], doc["pairs_chosen"]) == (2, 1)
    assert tool.sample_rows(str(out), root, n_pairs=1, iters=300).equals(rows)  # a rerun skips what is there
