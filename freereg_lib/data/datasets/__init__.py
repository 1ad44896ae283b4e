"""Data sources that yield :class:`~freereg_lib.data.pair.Pair` objects.

``icl`` is the embedded real sample (ICL-NUIM living room, shipped in the package);
``common`` holds the file readers every loader uses, ``pairlists`` the pair lists and the
loaders' base class; ``registry`` names the loaders (:func:`open_dataset`).
"""

from freereg_lib.data.datasets.registry import open_dataset

__all__ = ["open_dataset"]
