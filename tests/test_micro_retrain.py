"""The one-command retraining schedule: it is the committed weights' schedule, its phases
chain, and the smaller phase's views are the first rooms of the larger render."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from freereg_lib.training import retrain as R  # noqa: E402
from freereg_lib.training import train_diffusion as T  # noqa: E402
from freereg_lib.training.views import render_views  # noqa: E402

WEIGHTS = Path(__file__).resolve().parents[1] / "freereg_lib" / "models" / "micro" / "weights"


def test_the_schedule_is_the_one_the_committed_weights_record(tmp_path):
    first, second, last = (T.parse_args(a) for a in R.phase_argv(tmp_path, tmp_path / "w", threads=None))
    facts = json.loads((WEIGHTS / "training.json").read_text())
    steps = {k: v["steps"] for k, v in facts["stages"].items()}
    assert second.init_from == first.export and last.init_from == second.export
    assert last.export == str(tmp_path / "w")
    # The UNet's path: round 2 from scratch on 500 rooms, round 4 on 2,000, round 5 with the decay.
    assert first.init_from is None and first.stages == list(T.STAGES) and first.scenes == 500
    assert (first.steps_vae, first.steps_unet) == (steps["vae"], 2000)
    assert "unet from step 2000 to 4000" in facts["history"]
    assert (second.stages, second.steps_unet, second.lr_schedule) == (["unet"], 4000, "constant")
    assert "unet from step 4000 to 6000" in facts["history"] and "--lr-schedule cosine: unet" in facts["history"]
    assert (last.steps_unet, last.lr_schedule) == (steps["unet"], "cosine")
    # The ControlNet: the last round rebuilt it from the final UNet, so earlier phases train none.
    assert first.steps_controlnet == 0 and "controlnet" not in second.stages
    recorded = facts["arguments"]
    assert recorded["restart_controlnet"] and last.restart_controlnet and "controlnet" in last.stages
    for key in ("scenes", "views_per_scene", "batch", "lr_controlnet", "warmup", "lr_schedule", "seed"):
        assert getattr(last, key) == recorded[key], key
    assert last.steps_controlnet == steps["controlnet"] == recorded["steps_controlnet"]
    assert (f"controlnet rebuilt from this UNet (ControlNetModel.from_unet) and trained from step 0 to "
            f"{steps['controlnet']}") in facts["history"]


def test_first_rooms_of_a_render_are_the_smaller_render():
    small = render_views(1, 2, workers=1, progress=False)
    larger = render_views(2, 2, workers=1, progress=False)
    cut = R.first_rooms(larger, 1, views_per_scene=2)
    assert small.keys() == cut.keys()
    for k in small:
        np.testing.assert_array_equal(small[k], cut[k])
    with pytest.raises(ValueError, match="3 rooms asked for, the render holds 2"):
        R.first_rooms(larger, 3, views_per_scene=2)


def test_both_phases_run_in_order_and_the_second_continues_the_first(tmp_path, monkeypatch, capsys):
    tiny = ["--batch", "2", "--warmup", "1", "--checkpoint-every", "2"]
    # One view a room instead of four (rendering was a third of the test's time), so 5 and 6 rooms
    # (instead of 2 and 3 with four views): a fifth of the views, at least one, is held out for
    # the validation losses. (first_rooms's default views_per_scene is bound to the constant
    # when it is defined.)
    first_rooms = R.first_rooms
    monkeypatch.setattr(R, "VIEWS_PER_SCENE", 1)
    monkeypatch.setattr(R, "first_rooms", lambda views, n_scenes: first_rooms(views, n_scenes, views_per_scene=1))
    monkeypatch.setattr(R, "PHASES", (
        (5, ["--steps-vae", "2", "--steps-unet", "2", "--steps-controlnet", "0", *tiny]),
        (6, ["--stages", "unet", "controlnet", "--restart-controlnet", "--steps-unet", "3",
             "--steps-controlnet", "3", *tiny])))
    assert R.main(["--out", str(tmp_path), "--threads", "1"]) == 0
    with np.load(tmp_path / "views_indoor_5.npz") as z:
        assert int(z["n_scenes"]) == 5 and len(z["rgb"]) == 5 * R.VIEWS_PER_SCENE
    first = json.loads((tmp_path / "phase1_weights/training.json").read_text())
    final = json.loads((tmp_path / "weights/training.json").read_text())
    assert final["stages"]["vae"] == first["stages"]["vae"]
    assert final["stages"]["unet"]["loss"][:2] == first["stages"]["unet"]["loss"]
    assert len(final["stages"]["unet"]["loss"]) == len(final["stages"]["controlnet"]["loss"]) == 3
    assert first["stages"]["controlnet"]["loss"] == []
    assert ("unet from step 2 to 3, controlnet rebuilt from this UNet (ControlNetModel.from_unet) and trained "
            "from step 0 to 3") in final["history"]
    assert "total" in capsys.readouterr().out.strip().splitlines()[-1]


def test_the_training_benchmark_prices_every_committed_step_once(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_micro_training import schedule_steps

    facts = json.loads((WEIGHTS / "training.json").read_text())
    phases = schedule_steps()
    for stage in T.STAGES:
        assert sum(ph.get(stage, 0) for ph in phases) == facts["stages"][stage]["steps"], stage
    # A restarted ControlNet trains from step 0, whatever an earlier phase left it at.
    monkeypatch.setattr(R, "PHASES", ((2, ["--steps-controlnet", "1200"]),
                                      (2, ["--stages", "controlnet", "--restart-controlnet", "--steps-controlnet", "2600"])))
    assert [ph["controlnet"] for ph in schedule_steps()] == [1200, 2600]
