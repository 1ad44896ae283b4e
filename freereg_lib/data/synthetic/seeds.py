"""The micro models' training streams, and the guard that keeps evaluation seeds off them.

The training data are drawn from two-word NumPy seed sequences: room ``k`` of the diffusion and
depth models from ``numpy.random.default_rng((TRAIN_ROOMS, k))`` (:mod:`freereg_lib.training.views`),
FCGF's training pair ``k`` from ``make_pair("indoor", seed=(TRAIN_FCGF_PAIRS, k))``
(:mod:`freereg_lib.training.train_fcgf`). A two-word sequence is *not* out of reach of an integer
seed: NumPy splits a Python integer into its 32-bit little-endian words, and pads a seed of fewer
than four words with zeros, so the integer ``TRAIN_ROOMS + k * 2**32`` is the entropy
``[TRAIN_ROOMS, k]`` and reproduces training room ``k`` exactly (``TRAIN_ROOMS`` itself is room 0).
:func:`check_eval_seed` refuses every seed whose first 32-bit word is a training stream's tag;
:func:`freereg_lib.data.synthetic.make_pair` applies it to integer seeds, and the evaluation entry points
(``sources.iter_pairs``, ``freereg_lib.training.evaluate*``) to every seed they draw pairs from.
"""
from __future__ import annotations

TRAIN_ROOMS = 0xF3EE_0001  # the diffusion / depth training rooms: default_rng((TRAIN_ROOMS, k))
TRAIN_FCGF_PAIRS = 0xF3EE_0002  # FCGF's training pairs: make_pair("indoor", seed=(TRAIN_FCGF_PAIRS, k))
TRAINING_STREAMS = {TRAIN_ROOMS: "the micro diffusion / depth training rooms",
                    TRAIN_FCGF_PAIRS: "the micro FCGF training pairs"}


class TrainingSeedError(ValueError):
    """An evaluation seed that lands on a training stream."""


def entropy_words(seed) -> list[int]:
    """The 32-bit words NumPy's ``SeedSequence`` takes from ``seed`` (an integer, or a sequence of
    them, flattened): each integer little-endian word first, ``0`` as ``[0]``."""
    if isinstance(seed, (list, tuple)):
        return [w for s in seed for w in entropy_words(s)]
    n = int(seed)
    if n < 0:
        raise ValueError(f"a NumPy seed must be non-negative, got {n}")
    words = []
    while True:
        words.append(n & 0xFFFF_FFFF)
        n >>= 32
        if n == 0:
            return words


def training_alias(seed) -> str | None:
    """What training data ``seed`` would draw (``None`` when it draws none)."""
    words = entropy_words(seed)
    if words and words[0] in TRAINING_STREAMS:
        # NumPy pads a seed of up to four words with zeros: [tag] is [tag, 0], the stream's item 0.
        k = sum(w << (32 * i) for i, w in enumerate(words[1:])) if len(words) <= 4 else None
        which = TRAINING_STREAMS[words[0]]
        return f"{which}, item {k}" if k is not None else which
    return None


def check_eval_seed(seed) -> None:
    """Raise :class:`TrainingSeedError` when ``seed`` (an integer or a seed tuple) reaches a training
    stream, i.e. its first 32-bit word is ``TRAIN_ROOMS`` or ``TRAIN_FCGF_PAIRS``."""
    alias = training_alias(seed)
    if alias is not None:
        words = ", ".join(f"{w:#x}" for w in entropy_words(seed))
        raise TrainingSeedError(
            f"seed {seed!r} is refused for evaluation: NumPy seeds with its 32-bit words [{words}], "
            f"which is {alias}; pick a seed whose low 32 bits are not "
            f"{' or '.join(f'{t:#x}' for t in TRAINING_STREAMS)}")
