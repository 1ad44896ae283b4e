"""The one-command retraining schedule: it is the committed weights' schedule, its phases
chain, and the smaller phase's views are the first rooms of the larger render."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from freereg_lib.micro import retrain as R  # noqa: E402
from freereg_lib.micro import train_diffusion as T  # noqa: E402
from freereg_lib.micro.views import render_views  # noqa: E402

WEIGHTS = Path(__file__).resolve().parents[1] / "freereg_lib" / "micro" / "weights"


def test_the_schedule_is_the_one_the_committed_weights_record(tmp_path):
    first, second, last = (T.parse_args(a) for a in R.phase_argv(tmp_path, tmp_path / "w", threads=None))
    facts = json.loads((WEIGHTS / "training.json").read_text())
    recorded = {k: v for k, v in facts["arguments"].items() if k != "init_from"}
    assert {k: v for k, v in vars(last).items() if k in recorded} == recorded
    assert second.init_from == first.export and last.init_from == second.export
    assert last.export == str(tmp_path / "w")
    assert first.init_from is None and first.stages == list(T.STAGES)
    # Phase 1 made the VAE (kept since) and the UNet / ControlNet that phase 2 continued.
    assert first.steps_vae == facts["stages"]["vae"]["steps"] and first.scenes == 500
    assert "unet from step 2000 to 4000" in facts["history"] and first.steps_unet == 2000
    assert "controlnet from step 1200 to 2000" in facts["history"] and first.steps_controlnet == 1200
    assert (second.steps_unet, second.steps_controlnet, second.lr_schedule) == (4000, 2000, "constant")
    assert "unet from step 4000 to 6000, controlnet from step 2000 to 2600" in facts["history"]


def test_first_rooms_of_a_render_are_the_smaller_render():
    small = render_views(2, 2, workers=1, progress=False)
    cut = R.first_rooms(render_views(3, 2, workers=1, progress=False), 2, views_per_scene=2)
    assert small.keys() == cut.keys()
    for k in small:
        np.testing.assert_array_equal(small[k], cut[k])
    with pytest.raises(ValueError, match="4 rooms asked for, the render holds 3"):
        R.first_rooms(render_views(3, 1, workers=1, progress=False), 4, views_per_scene=1)


def test_both_phases_run_in_order_and_the_second_continues_the_first(tmp_path, monkeypatch, capsys):
    tiny = ["--batch", "2", "--warmup", "1", "--checkpoint-every", "2"]
    monkeypatch.setattr(R, "PHASES", (
        (2, ["--steps-vae", "2", "--steps-unet", "2", "--steps-controlnet", "2", *tiny]),
        (3, ["--stages", "unet", "controlnet", "--steps-unet", "3", "--steps-controlnet", "3", *tiny])))
    assert R.main(["--out", str(tmp_path), "--threads", "1"]) == 0
    with np.load(tmp_path / "views_indoor_2.npz") as z:
        assert int(z["n_scenes"]) == 2 and len(z["rgb"]) == 2 * R.VIEWS_PER_SCENE
    first = json.loads((tmp_path / "phase1_weights/training.json").read_text())
    final = json.loads((tmp_path / "weights/training.json").read_text())
    assert final["stages"]["vae"] == first["stages"]["vae"]
    assert final["stages"]["unet"]["loss"][:2] == first["stages"]["unet"]["loss"]
    assert len(final["stages"]["unet"]["loss"]) == len(final["stages"]["controlnet"]["loss"]) == 3
    assert "unet from step 2 to 3, controlnet from step 2 to 3" in final["history"]
    assert "total" in capsys.readouterr().out.strip().splitlines()[-1]
