"""fusion_sweep's FPFH choice lifts the image side with the depth model of the weights it is given."""
from __future__ import annotations

import pytest

from freereg_lib.training import fusion_sweep as S


def test_the_fpfh_choice_uses_the_given_weights(tmp_path, monkeypatch):
    seen = []

    def backend(name, cfg=None, device=None, **kw):
        seen.append((name, kw.get("weights_dir")))
        raise RuntimeError("stop here")

    monkeypatch.setattr("freereg_lib.models.get_backend", backend)
    with pytest.raises(RuntimeError, match="stop here"):
        S.choose_fpfh(None, [], [(0.05, 5.0)], None, weights_dir=tmp_path)
    with pytest.raises(RuntimeError, match="stop here"):
        S.choose_fpfh(None, [], [(0.05, 5.0)], None)
    assert seen == [("micro", tmp_path), ("micro", None)]


def test_a_split_without_cached_features_is_named(tmp_path):
    with pytest.raises(SystemExit, match=r"no cached features for pairs \[0, 1\]"):
        S.main(["--split", "rooms-dev", "--pairs", "2", "--cache", str(tmp_path), "--weights", str(tmp_path)])
