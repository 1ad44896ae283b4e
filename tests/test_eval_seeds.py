"""No evaluation seed may reproduce a micro model's training room.

NumPy splits an integer seed into 32-bit little-endian words, so the integer
``TRAIN_ROOMS + k * 2**32`` is the seed sequence ``(TRAIN_ROOMS, k)`` of training room ``k``. The
guard (:func:`freereg_lib.data.synthetic.check_eval_seed`) refuses such integers; the last two tests show
that without it they *would* reproduce the training data, array for array.
"""
import numpy as np
import pytest

from freereg_lib.data import sources, synthetic
from freereg_lib.data.synthetic import pairs as synthetic_pairs
from freereg_lib.data.synthetic.seeds import TRAIN_FCGF_PAIRS, TRAIN_ROOMS, TrainingSeedError, check_eval_seed
from freereg_lib.training import splits, views

K = 3
ROOM_ALIAS = TRAIN_ROOMS + K * 2**32  # the integer NumPy reads as (TRAIN_ROOMS, K)
FCGF_ALIAS = TRAIN_FCGF_PAIRS + K * 2**32


def test_the_training_streams_are_the_ones_training_uses():
    from freereg_lib.training import train_fcgf

    assert views.TRAIN_STREAM == TRAIN_ROOMS == 0xF3EE0001
    assert train_fcgf.TRAIN_STREAM == TRAIN_FCGF_PAIRS == 0xF3EE0002


@pytest.mark.parametrize("seed", [ROOM_ALIAS, FCGF_ALIAS, TRAIN_ROOMS, (TRAIN_ROOMS, K), (TRAIN_FCGF_PAIRS, 0),
                                  np.uint64(ROOM_ALIAS)])
def test_seeds_on_a_training_stream_are_refused(seed):
    with pytest.raises(TrainingSeedError, match="refused for evaluation"):
        check_eval_seed(seed)


def test_make_pair_refuses_the_integer_alias_with_one_line():
    with pytest.raises(TrainingSeedError) as exc:
        synthetic.make_pair("indoor", seed=ROOM_ALIAS)
    msg = str(exc.value)
    assert "\n" not in msg and f"item {K}" in msg and "0xf3ee0001" in msg


def test_iter_pairs_and_the_evaluation_commands_refuse_it():
    # A dataset seed whose first pair seed, s * 1_000_003, has the low word TRAIN_ROOMS.
    s = TRAIN_ROOMS * pow(1_000_003, -1, 2**32) % 2**32
    assert (s * 1_000_003) % 2**32 == TRAIN_ROOMS
    with pytest.raises(TrainingSeedError):
        next(sources.iter_pairs("synthetic_indoor", 1, seed=s))
    with pytest.raises(SystemExit, match=f"--seed {s}, pair 0: seed"):
        splits.guard_eval_seed(s, 1)
    from freereg_lib.training import evaluate

    with pytest.raises(SystemExit, match="refused for evaluation"):
        evaluate.main(["--pairs", "1", "--seed", str(s)])


def test_todays_evaluation_seeds_pass():
    for split in (splits.DEV, splits.TEST):
        for seed in split.pair_seeds(1000):
            check_eval_seed(seed)
    for seed in [*range(1000), *(s * 1_000_003 + k for s in (0, 1, 2, 7, 100, 2026, 4049) for k in range(100))]:
        check_eval_seed(seed)
    # the development and test splits share no pair
    assert not set(splits.DEV.pair_seeds(10_000)) & set(splits.TEST.pair_seeds(10_000))


def test_without_the_guard_the_integer_reproduces_training_room_k(monkeypatch):
    """Not vacuous: NumPy draws the same stream, and the training views of room K come out equal."""
    a = np.random.default_rng(ROOM_ALIAS).integers(0, 2**63, 16)
    b = np.random.default_rng((TRAIN_ROOMS, K)).integers(0, 2**63, 16)
    np.testing.assert_array_equal(a, b)
    trained = views._scene_views((K, 1, "indoor"))
    monkeypatch.setattr(views, "room_rng", lambda k: np.random.default_rng(TRAIN_ROOMS + int(k) * 2**32))
    aliased = views._scene_views((K, 1, "indoor"))
    for key in ("rgb", "hint", "depth"):
        np.testing.assert_array_equal(aliased[key], trained[key])


def test_without_the_guard_the_integer_reproduces_fcgf_training_pair_k(monkeypatch):
    trained = synthetic.make_pair("indoor", seed=(TRAIN_FCGF_PAIRS, K))  # training's own form is allowed
    monkeypatch.setattr(synthetic_pairs, "check_eval_seed", lambda seed: None)
    aliased = synthetic.make_pair("indoor", seed=FCGF_ALIAS)
    np.testing.assert_array_equal(aliased.image, trained.image)
    np.testing.assert_array_equal(aliased.points, trained.points)
    np.testing.assert_array_equal(aliased.T_cam_pc, trained.T_cam_pc)
