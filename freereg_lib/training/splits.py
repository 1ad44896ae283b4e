"""The micro models' evaluation splits: the development set and the test split, in one place.

* :data:`DEV`, the **development set**: the 30 synthetic indoor pairs of seed 2026
  (``sources.iter_pairs("synthetic_indoor", 30, seed=2026)``, pair seeds ``2026 * 1_000_003 + k``)
  at noise seed 0. Every training round, recipe and sweep of the micro models (t_hat, w, DDIM
  eta and steps, keypoint grid, hint source, ControlNet scale, ...) was judged on it, and the
  100-pair runs of seed 2026 contain it: its numbers are development numbers, not held-out ones.
* :data:`TEST`, the **test split**: pairs of seed 4049 (pair seeds ``4049 * 1_000_003 + k =
  4_049_012_147 + k``, a range no other run of the repository uses), noise seed 0. Test-only:
  it is evaluated once per committed model (:mod:`.evaluate_split`) and never for a choice;
  choices are made on :data:`DEV`.

:data:`ROOMS_DEV` and :data:`ROOMS_TEST` are the same for the calibrated ``rooms`` world (seeds 5150
and 8837), for models trained in it.

Every method of a split runs on the same pairs with the same noise seed (the config's ``seed``:
the diffusion features' noise draws and the RANSAC draws), whatever the pair seed.
Neither split's seeds reproduce a training room: :func:`freereg_lib.data.synthetic.check_eval_seed`.
"""
from __future__ import annotations

from dataclasses import dataclass

from freereg_lib.data.synthetic import TrainingSeedError, check_eval_seed


@dataclass(frozen=True)
class Split:
    name: str
    seed: int  # the dataset seed of sources.iter_pairs: pair k is make_pair(seed * 1_000_003 + k)
    n_pairs: int
    noise_seed: int  # the config's seed for every method
    use: str
    world: str = "blocks"  # the synthetic indoor world of its pairs (make_pair's ``world``)

    def pair_seeds(self, n_pairs: int | None = None) -> list[int]:
        n = self.n_pairs if n_pairs is None else n_pairs
        return [self.seed * 1_000_003 + k for k in range(n)]


DEV = Split("development", 2026, 30, 0, "every choice of the micro models was made on it")
TEST = Split("test", 4049, 100, 0, "test-only: evaluated once per committed model, never for a choice")
def guard_eval_seed(seed: int, n_pairs: int) -> None:
    """Stop an evaluation command (one line) when a pair seed ``seed * 1_000_003 + k``, ``k < n_pairs``
    (``make_pairs`` / ``iter_pairs``), would draw a training room or pair."""
    for k in range(n_pairs):
        try:
            check_eval_seed(seed * 1_000_003 + k)
        except TrainingSeedError as exc:
            raise SystemExit(f"--seed {seed}, pair {k}: {exc}") from None


# The calibrated world's own splits (docs/world.md): its development seed 5150 is one the world itself
# was built on; its test seed range is used by no other run.
ROOMS_DEV = Split("rooms development", 5150, 30, 0, "choices of models trained in the rooms world", "rooms")
ROOMS_TEST = Split("rooms test", 8837, 100, 0, "test-only: evaluated once per model trained in the rooms world, "
                   "never for a choice", "rooms")
SPLITS = {"dev": DEV, "development": DEV, "test": TEST, "rooms-dev": ROOMS_DEV, "rooms-test": ROOMS_TEST}

for _split in (DEV, TEST, ROOMS_DEV, ROOMS_TEST):
    for _s in _split.pair_seeds(1000):
        check_eval_seed(_s)
