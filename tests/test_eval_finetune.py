"""The fine-tuning table's code (Table 11, fine-tuning): the sensor-like hints, a few fine-tuning steps
on tiny data from the committed weights (the loss falls; CI never trains for real), the evaluation
summary on hand-made rows, and bad arguments. The committed run is read by
``verdicts_appendix.table11``."""
from __future__ import annotations

import json

import numpy as np
import pytest

from freereg_lib.training import evaluate_finetune as E
from freereg_lib.training import finetune_controlnet as F
from freereg_lib.training import verdicts_appendix


def test_sensor_depth_adds_noise_and_holes_and_is_seeded():
    depth = np.full((60, 80), 2.0)
    depth[:, 40:] = 3.0  # a discontinuity: its shadow becomes a hole
    a = F.sensor_depth(depth, np.random.default_rng(0), blobs=0)
    b = F.sensor_depth(depth, np.random.default_rng(0), blobs=0)
    assert np.array_equal(a, b)
    assert np.all(a[:, 38:43] == 0) and np.all(a[:, :30] > 0)
    noise = a[:, :30] - 2.0
    assert 0.001 < noise.std() < 0.02  # twice the Kinect model at 2 m: 2 * 0.0061 m
    assert np.all(F.sensor_depth(depth, np.random.default_rng(0), far_m=2.5, edge_px=0, blobs=0)[:, 40:] == 0)


def _tiny_views(tmp_path, n: int = 5) -> dict:
    """``n`` copies of one 64 x 96 view (a ramp image, a step hint): training and validation see the
    same view, so a few steps must fit it."""
    rng = np.random.default_rng(0)
    rgb = np.repeat(np.linspace(0, 255, 96, dtype=np.uint8)[None, None, None], 64, axis=2)
    rgb = np.repeat(np.concatenate([rgb, 255 - rgb, rgb], axis=1), n, axis=0)
    hint = np.zeros((n, 3, 64, 96), np.uint8)
    hint[:, :, :, 48:] = 200
    views = {"rgb": rgb, "hint": hint, "depth": rng.random((n, 30, 40)).astype(np.float32)}
    meta = {"noise_scale": 2.0, "edge_px": 2, "blobs": 3, "far_m": 6.0, "scenes": n, "vps": 1}
    from freereg_lib.training.views import save_views

    save_views(views, tmp_path / "views_sensor.npz", n, 1)
    (tmp_path / "views_sensor.json").write_text(json.dumps(meta))
    return views


def test_a_few_fine_tuning_steps_lower_the_loss_and_change_only_the_controlnet(tmp_path):
    _tiny_views(tmp_path)
    out = tmp_path / "weights"
    argv = ["--out", str(tmp_path), "--export", str(out), "--scenes", "5", "--views-per-scene", "1",
            "--steps", "6", "--batch", "2", "--lr", "2e-3", "--warmup", "1", "--checkpoint-every", "1",
            "--threads", "1"]
    assert F.main(argv) == 0
    facts = json.loads((out / "training.json").read_text())
    log = facts["stages"]["controlnet"]
    start = facts["finetune"]["from_step"]
    assert log["steps"] == start + 6 and len(log["loss"]) == start + 6
    val = [v for _, v in log["val"][-6:]]  # the validation loss (fixed noise and timesteps) after each step
    assert val[-1] < val[0], val
    assert E.differing_parts(out) == ["controlnet"]


def _rec(k: int, model: str, registered: bool, ir: float) -> dict:
    rows = [{"solver": s, "n_matches": 100, "IR": ir, "IN": 100 * ir, "RE": 1.0, "TE": 0.1,
             "registered": registered, "error": "" if registered else "no pose"} for s in E.SOLVERS]
    return {"k": k, "model": model, "pair_seed": k, "pair": f"p{k}", "label": "micro", "weights": "w",
            "depth_weights": "d", "load_average": 1.0, "seconds_geometric": 1.0, "seconds_diffusion": 2.0,
            "rows": rows}


def test_the_summary_counts_equal_its_rows_and_pairs_the_models(tmp_path, capsys):
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text("".join(json.dumps(_rec(k, "committed", k < 2, 0.2)) + "\n" for k in range(4)))
    # the fine-tuned model has pairs 0..2 only: the summary pairs 3
    b.write_text("".join(json.dumps(_rec(k, "finetuned", k < 3, 0.3)) + "\n" for k in range(3)))
    weights = tmp_path / "w"
    (weights / "controlnet").mkdir(parents=True)
    (weights / "training.json").write_text(json.dumps({"finetune": {"steps": 6}}))
    out = tmp_path / "s.json"
    assert E.main(["--summarize", "--weights", str(weights), "--rows", str(a), str(b), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["n_pairs"] == 3 and res["finetune"] == {"steps": 6}
    for key in ("committed kabsch", "committed pnp", "finetuned kabsch", "finetuned pnp"):
        r = res["results"][key]
        assert r["n"] == 3 == len(r["registered_per_pair"]) == len(r["IR_per_pair"])
    assert res["results"]["committed kabsch"]["RR"]["mean"] == pytest.approx(200 / 3)
    assert res["results"]["finetuned pnp"]["RR"]["mean"] == 100.0
    assert res["results"]["committed kabsch"]["failed"] == 1 and res["results"]["finetuned kabsch"]["failed"] == 0
    t = res["tests"]["RR kabsch: finetuned - committed"]
    assert t["diff"] == pytest.approx(100 / 3) and t["diff_ci"][0] <= t["diff"] <= t["diff_ci"][1]
    assert res["tests"]["IR pnp: finetuned - committed"]["diff"] == pytest.approx(10.0)
    assert "finetuned kabsch" in capsys.readouterr().out


def test_the_verdict_reads_the_committed_json(tmp_path, monkeypatch):
    pairs = [{"committed": _rec(k, "committed", k == 0, 0.2), "finetuned": _rec(k, "finetuned", True, 0.3)}
             for k in range(3)]
    res = E.summarize(pairs, "test")
    res["finetune"] = {"steps": 6, "from_step": 2600, "lr": 1e-4, "scenes": 5}
    monkeypatch.setattr(verdicts_appendix, "load", lambda name: res if name == verdicts_appendix.FINETUNE_JSON else None)
    lines = verdicts_appendix.table11()
    text = "\n".join(lines)
    assert "63.8" in text and "70.1" in text  # the paper's 3DMatch RR before and after
    assert lines[-2].startswith("  fine-tuning raises IR (Kabsch; the paper on 3DMatch: ") and "cannot be told (3 pairs" in lines[-2], lines
    assert lines[-1].startswith("  fine-tuning raises RR (Kabsch; the paper on 3DMatch: +6.3 points)"), lines


@pytest.mark.parametrize("argv, message", [
    (["--pairs", "0", "--rows", "r.jsonl"], "--pairs 0: expected >= 1"),
    (["--shard", "2/2", "--rows", "r.jsonl"], "--shard 2/2: expected 0 <= i < n"),
    (["--model", "finetuned", "--rows", "r.jsonl"], "--weights is needed"),
    (["--summarize", "--weights", ".", "--rows", "r.jsonl"], "no controlnet/ folder"),
])
def test_bad_evaluation_arguments_stop_with_one_line(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        E.main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and message in err.splitlines()[-1]


@pytest.mark.parametrize("argv, message", [
    (["--steps", "0"], "--steps, --batch and --views-per-scene must be >= 1"),
    (["--lr", "0"], "--lr and --far-m must be > 0"),
    (["--init-from", "nowhere"], "--init-from nowhere: no training.json there"),
])
def test_bad_fine_tuning_arguments_stop_with_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        F.parse_args(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err.splitlines()[-1]
