"""Data: what a pair is, and where pairs come from (layer 2, imports :mod:`freereg_lib.geometry` and
:mod:`freereg_lib.config`).

* :mod:`.pair`: :class:`~.pair.Pair`, one image and one point cloud with their cameras;
* :mod:`.synthetic`: the seeded synthetic rooms and streets (the default runs);
* :mod:`.datasets`: loaders for 3DMatch, ScanNet, KITTI-DC, the official demo and the embedded
  ICL-NUIM sample, and the readers of their files;
* :mod:`.sources`: a dataset name to an iterator of pairs; :mod:`.shards` splits them;
* :mod:`.paper`: the paper's tables
  (``paper_tables/*.csv``).

The folders ``icl_livingroom/``, ``paper_tables/`` and ``grids/`` are package data.
"""
