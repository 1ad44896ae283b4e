"""``pipeline.run_pairs(on_pair=...)``: each pair's features and rows handed out as the run goes,
one pair at a time and in batches, so that a caller (notebook 04's failure pictures) can keep
them instead of computing them again."""
import dataclasses

import numpy as np
import pytest

from freereg_lib import config_for, pipeline
from freereg_lib.data import synthetic
from freereg_lib.models import get_backend

VARIANTS = [("FreeReg-D", "pnp"), ("FreeReg", "kabsch")]


@pytest.fixture(scope="module")
def pairs():
    return synthetic.make_pairs(2, "indoor", seed=7, image_size=(240, 320))


@pytest.mark.parametrize("pair_batch", [1, 2])
def test_on_pair_gets_each_pairs_features_and_rows_in_run_order(pairs, pair_batch):
    cfg = config_for("synthetic_indoor", ransac_iters=500, pair_batch=pair_batch)
    backend = get_backend("stub", cfg)
    seen = []
    rows = pipeline.run_pairs(pairs, backend, cfg, VARIANTS, progress=False,
                              on_pair=lambda p, f, r: seen.append((p, f, r)))
    assert [p.name for p, _, _ in seen] == [p.name for p in pairs]
    assert [row for _, _, r in seen for row in r] == rows
    for pair, feats, pair_rows in seen:
        alone = pipeline.compute_features(pair, backend, cfg)
        np.testing.assert_array_equal(feats.uv_image, alone.uv_image)
        np.testing.assert_allclose(feats.diff_depth, alone.diff_depth, rtol=1e-6)
        np.testing.assert_array_equal(feats.geo_image, alone.geo_image)
        # The kept features give the matches the rows counted.
        for row in pair_rows:
            assert len(pipeline.match(feats, row["w"])) == row["n_matches"]


def test_on_pair_gets_the_exception_of_a_pair_that_failed(pairs):
    cfg = config_for("synthetic_indoor", ransac_iters=500)
    pairs = [pairs[0], dataclasses.replace(pairs[1], points=np.zeros((0, 3)))]  # an empty cloud: no depth view
    seen = []
    rows = pipeline.run_pairs(pairs, get_backend("stub", cfg), cfg, VARIANTS, progress=False,
                              on_pair=lambda p, f, r: seen.append((f, r)))
    assert not isinstance(seen[0][0], Exception)
    assert isinstance(seen[1][0], Exception)
    assert all(r["error"] and r["n_matches"] == 0 for r in seen[1][1]) and len(rows) == 4
