"""A depth_size given as floats is refused in one line by Pair.validate, not by numpy later."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from freereg_lib.data import synthetic


@pytest.mark.parametrize("size", [(480.0, 640.0), (480, 640.0), (True, 640)])
def test_depth_size_as_floats_is_named(size):
    pair = dataclasses.replace(synthetic.make_pair("indoor", seed=3), depth_size=size)
    with pytest.raises(ValueError, match=r"depth_size must be \(H_d, W_d\), two positive integers, got"):
        pair.validate()


def test_numpy_integers_are_integers():
    pair = synthetic.make_pair("indoor", seed=3)
    dataclasses.replace(pair, depth_size=tuple(np.int64(v) for v in pair.depth_size)).validate()
