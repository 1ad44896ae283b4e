"""The micro models' held-out comparison (freereg_lib.training.evaluate): its statistics on
hand-made numbers, and the reuse of an earlier random-weight run only where it is comparable."""
from __future__ import annotations

import pytest

from freereg_lib.training import evaluate as E


def test_bootstrap_and_permutation_on_hand_made_numbers():
    assert E.bootstrap_ci([0.25] * 7) == (0.25, 0.25)
    assert E.paired_permutation_p([0.1, 0.2], [0.1, 0.2]) == 1.0
    # Six equal positive differences: only the two all-same sign patterns of 64 reach |mean|.
    p = E.paired_permutation_p([1.0] * 6, [0.0] * 6, n=20000)
    assert p == pytest.approx(2 / 64, abs=0.006)
    # A difference that flips sign half the time is no evidence.
    assert E.paired_permutation_p([1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]) == 1.0


def _earlier(n_pairs=2, seed=2026, changes=None):
    return {"seed": seed, "config_changes": changes or {},
            "random": {"n_pairs": n_pairs, "IR": 2.0, "IR_per_pair": [0.0, 0.04][:n_pairs]}}


def test_reuse_random_takes_only_a_run_of_the_same_pairs_and_config():
    earlier = _earlier(changes={"seed": 1})
    assert E.reuse_random(earlier, 2, 2026, {"seed": 1}) is earlier["random"]
    with pytest.raises(ValueError, match="n_pairs|pairs"):
        E.reuse_random(earlier, 3, 2026, {"seed": 1})
    with pytest.raises(ValueError, match="config changes"):
        E.reuse_random(earlier, 2, 2026, {"seed": 2})  # another noise seed: other random weights
    with pytest.raises(ValueError, match="seed"):
        E.reuse_random(earlier, 2, 7, {"seed": 1})
    with pytest.raises(ValueError, match="no random-weight run"):
        E.reuse_random({"seed": 2026, "config_changes": {}}, 2, 2026, {})


def test_evaluate_with_a_reused_random_run_compares_against_it():
    pytest.importorskip("torch")
    earlier = _earlier(n_pairs=1)
    out = E.evaluate(1, 2026, progress=False, random_from=earlier)
    assert out["random"] is earlier["random"]
    ir = out["trained"]["IR_per_pair"]
    assert len(ir) == 1
    assert out["IR_ratio"] == pytest.approx(out["trained"]["IR"] / 2.0)
    assert out["p_value"] == 1.0  # one pair: both signs of its difference reach |mean|


def test_the_command_line_records_only_the_config_fields_it_was_given(monkeypatch, capsys):
    seen = []

    def fake_evaluate(n_pairs, seed, weights_dir, **kw):
        seen.append(kw)
        return {"seed": seed, "config_changes": {k: v for k, v in kw.items() if k in E.SWEPT_FIELDS},
                "trained": {"n_pairs": n_pairs, "IR": 1.0, "IR_ci": (0.0, 2.0), "FMR": 0.0, "FMR_ci": (0.0, 0.0),
                            "RR": 0.0, "RR_ci": (0.0, 0.0)}}

    monkeypatch.setattr(E, "evaluate", fake_evaluate)
    E.main(["--pairs", "2", "--trained-only", "--ddim-eta", "0", "--ddim-steps", "50"])
    E.main(["--pairs", "2", "--trained-only"])
    E.main(["--pairs", "2", "--trained-only", "--controlnet-scale", "1.5"])
    assert {k: v for k, v in seen[0].items() if k in E.SWEPT_FIELDS} == {"ddim_eta": 0.0, "ddim_steps": 50}
    assert {k: v for k, v in seen[2].items() if k in E.SWEPT_FIELDS} == {"controlnet_scale": 1.5}
    assert not any(k in E.SWEPT_FIELDS for k in seen[1])  # a default run records no change
    out = capsys.readouterr().out
    assert "{'ddim_steps': 50, 'ddim_eta': 0.0}" in out and "default config" in out
