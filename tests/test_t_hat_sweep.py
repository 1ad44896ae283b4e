"""Table 3's t_hat sweep from one DDIM trajectory gives, at every t_hat, the maps of a backend
built with that t_hat (the shorter runs are prefixes of the longest)."""
import copy

import numpy as np
import pytest

from freereg_lib import config_for, pipeline
from freereg_lib.data import synthetic
from freereg_lib.models import get_backend
from freereg_lib.models.base import n_guided_steps

# At 5 DDIM steps: 2, 4, 5 and 0 guided steps (990: none at all before the feature pass).
T_HATS = [600, 300, 50, 990]
LAYERS = [0, 4, 6]


def _alone(backend, cfg, t):
    """The backend as if built with ``t_hat = t`` (the tiny models' weights do not depend on it)."""
    if backend.name == "stub":
        return get_backend("stub", cfg.override(t_hat=t))
    alone = copy.copy(backend)
    alone._diffusion = copy.copy(backend.diffusion)
    alone.cfg = alone._diffusion.cfg = cfg.override(t_hat=t)
    return alone


@pytest.mark.parametrize("name", ["tiny", "stub"])
def test_one_trajectory_gives_each_t_hats_own_maps(name):
    cfg = config_for("synthetic_indoor", ddim_steps=5, ddim_eta=0.5)  # eta > 0: the step noise must line up too
    assert sorted(n_guided_steps(t, 5) for t in T_HATS) == [0, 2, 4, 5]
    # A 120 x 160 pair: the tiny models see the image at their own input size whatever it is
    # given; the stub computes its maps from the pixels, a quarter of the CPU of a 480 x 640 pair.
    pairs = synthetic.make_pairs(1, "indoor", seed=4, image_size=(120, 160))
    views = [pipeline.depth_view(p, cfg) for p in pairs]
    backend = get_backend(name, cfg)
    swept = pipeline.diffusion_maps_over_t_hats(pairs, views, backend, T_HATS, layers=LAYERS)
    assert sorted(swept) == sorted(T_HATS)
    for t in T_HATS:
        alone = pipeline.diffusion_maps_batch(pairs, views, _alone(backend, cfg, t), layers=LAYERS)
        for (rgb, dep), (rgb_alone, dep_alone) in zip(swept[t], alone):
            for layer in LAYERS:
                np.testing.assert_array_equal(rgb[layer], rgb_alone[layer])
                np.testing.assert_array_equal(dep[layer], dep_alone[layer])
    if name == "tiny":  # not one map copied: both sides move with t_hat
        for side in (0, 1):
            assert not np.array_equal(swept[600][0][side][0], swept[50][0][side][0])
