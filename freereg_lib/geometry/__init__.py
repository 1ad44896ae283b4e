"""Geometry: the camera model and every computation on points and poses (layer 1, imports nothing above).

* :mod:`.cameras`: SE(3), intrinsics, projection and back-projection; the conventions of the
  whole library are stated there once;
* :mod:`.projection`: a point cloud as a depth map seen from a camera, and the official
  keypoint clouds;
* :mod:`.densify`: IP-Basic's ``fill_in_fast`` (sparse depth to a dense map);
* :mod:`.keypoints`: the keypoint grid;
* :mod:`.pose`: Kabsch- and PnP-RANSAC, as the official code runs them;
* :mod:`.metrics`: FMR, IR, IN, RE / TE and registration recall.

Imports: NumPy, SciPy, OpenCV, Open3D; nothing from other ``freereg_lib`` packages.
"""
