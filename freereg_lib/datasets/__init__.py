"""Data sources that yield :class:`~freereg_lib.pair.Pair` objects.

``icl`` is the embedded real sample (ICL-NUIM living room, shipped in the package);
``common`` holds the file readers every loader uses.
"""

from .pairlists import open_dataset

__all__ = ["open_dataset"]
