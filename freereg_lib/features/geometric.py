"""Geometric features of point clouds and their transfer to pixels.

* :func:`fpfh_features`: Open3D FPFH (33-d) on a voxel-downsampled cloud; works everywhere,
  the default (``cfg.geometric = "fpfh"``).
* :func:`fcgf_features`: the paper's FCGF (32-d, ResUNetBN2C, official checkpoints), run by a
  plain-torch re-implementation of its MinkowskiEngine operations
  (:mod:`freereg_lib.models.fcgf`); needs the checkpoint file (no download).
* :func:`pixel_features`: a pixel takes the feature of its nearest feature point in 3D, or a
  zero vector when that point is farther than ``tau_g`` (0.5 m indoor, 5 m outdoor).
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from freereg_lib.models import fcgf as F
from freereg_lib.models.base import MissingWeightsError
from freereg_lib.models.fcgf import CHECKPOINTS
from freereg_lib.models.weights import default_weights_dir

FPFH_DIM = 33


def fpfh_features(points: np.ndarray, voxel: float, radius_normal: float,
                  radius_feature: float, camera_location=(0.0, 0.0, 0.0),
                  max_nn_normal: int = 30, max_nn_feature: int = 100, at: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray]:
    """FPFH features of a point cloud.

    Args:
        points: ``(N, 3)`` points.
        voxel: voxel size of the downsampling (``<= 0``: no downsampling).
        radius_normal: radius of the normal estimation (hybrid search, ``max_nn_normal``).
        radius_feature: radius of the FPFH histogram (hybrid search, ``max_nn_feature``).
        camera_location: normals are oriented towards this point (FPFH depends on the
            normals' signs, so both clouds of a pair must be oriented the same way: pass each
            cloud in its own camera frame, i.e. the default origin, or the sensor position).
            ``None`` leaves Open3D's arbitrary orientation.
        at: ``(K, 3)`` points (NaN rows ignored) of which only the nearest feature point will
            be used (:func:`pixel_features`). Only those rows of ``feats`` are computed (Open3D's
            ``indices``; the same values) and the others are zero: about half the time for the
            ~1.4k keypoints of a pair.

    Returns:
        ``(down_points (M, 3) float64, feats (M, 33) float32)``.
    """
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros((0, FPFH_DIM), dtype=np.float32)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if voxel and voxel > 0:
        pcd = pcd.voxel_down_sample(float(voxel))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius_normal),
                                                              max_nn=int(max_nn_normal)))
    if camera_location is not None:
        pcd.orient_normals_towards_camera_location(
            np.asarray(camera_location, dtype=np.float64).reshape(3))
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius_feature), max_nn=int(max_nn_feature))
    down = np.asarray(pcd.points)
    if at is None:
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(pcd, param)
        return down, np.asarray(fpfh.data).T.astype(np.float32)

    q = np.asarray(at, dtype=np.float64).reshape(-1, 3)
    q = q[np.all(np.isfinite(q), axis=1)]
    feats = np.zeros((len(down), FPFH_DIM), dtype=np.float32)
    if len(q):
        # Open3D returns the rows of sorted indices (checked: bitwise the full computation's rows).
        rows = np.unique(cKDTree(down).query(q, k=1)[1])
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(pcd, param, rows.tolist())
        feats[rows] = np.asarray(fpfh.data).T
    return down, feats


def pixel_features(points_at_pixels: np.ndarray, feat_points: np.ndarray, feats: np.ndarray,
                   tau_g: float) -> np.ndarray:
    """Geometric features ``(K, C)`` of pixels, given their 3D points ``(K, 3)``.

    Each pixel takes the feature of its nearest point of ``feat_points (M, 3)`` (features
    ``feats (M, C)``); when that point is farther than ``tau_g``, or the pixel's point is not
    finite (no depth), the feature is a zero vector.
    """

    q = np.asarray(points_at_pixels, dtype=np.float64).reshape(-1, 3)
    fp = np.asarray(feat_points, dtype=np.float64).reshape(-1, 3)
    feats = np.asarray(feats)
    if len(fp) != len(feats):
        raise ValueError(f"feat_points ({len(fp)}) and feats ({len(feats)}) differ in length")
    out = np.zeros((len(q), feats.shape[1] if feats.ndim == 2 else 0), dtype=feats.dtype)
    ok = np.all(np.isfinite(q), axis=1)
    if len(fp) == 0 or not ok.any():
        return out
    dist, idx = cKDTree(fp).query(q[ok], k=1, distance_upper_bound=float(tau_g))
    hit = np.isfinite(dist) & (dist <= tau_g)
    rows = np.flatnonzero(ok)[hit]
    out[rows] = feats[idx[hit]]
    return out


def fcgf_checkpoint_path(cfg, checkpoint=None) -> str:
    """The FCGF checkpoint to use: ``checkpoint``, else ``cfg.extra["fcgf_checkpoint"]``, else
    ``<weights_dir>/fcgf/<official file>`` (3DMatch indoor, KITTI for ``cfg.outdoor``; the
    weights folder as for the real backend). Raises
    :class:`~freereg_lib.models.MissingWeightsError` when the file is not there."""

    info = CHECKPOINTS["kitti" if cfg.outdoor else "3dmatch"]
    path = checkpoint or (cfg.extra or {}).get("fcgf_checkpoint")
    if path is None:
        wdir = default_weights_dir(cfg) or Path("weights")
        path = wdir / "fcgf" / info["file"]
    path = Path(path)
    if not path.is_file():
        raise MissingWeightsError(
            f"FCGF checkpoint not found: {path}\n"
            f"The paper uses FCGF ResUNetBN2C {info['file']} (conv1 kernel "
            f"{info['conv1_kernel_size']}, voxel {info['voxel']} m). It is not on the Hugging "
            "Face Hub: download it on a machine with internet from the links in the FCGF "
            f"repository's README (chrischoy/FCGF) into {path.parent}/, or pass "
            "cfg.extra['fcgf_checkpoint'].\n"
            "Without it, use geometric='fpfh' (Open3D, no weights; the default).",
            model_ids=[info["file"]], searched=[str(path)])
    return str(path)


_FCGF_CACHE: dict = {}


def fcgf_features(points: np.ndarray, voxel: float, cfg=None, checkpoint=None, model=None,
                  device=None) -> tuple[np.ndarray, np.ndarray]:
    """FCGF features ``(down_points (M, 3), feats (M, 32) float32)`` (unit norm) of a cloud
    quantised at ``voxel`` (one point per voxel). ``model`` (a loaded ResUNetBN2C) or the
    checkpoint of :func:`fcgf_checkpoint_path` (loaded once and cached)."""

    if model is None:
        if cfg is None and checkpoint is None:
            raise ValueError("give a model, a checkpoint path or a cfg")
        if cfg is not None:
            path = fcgf_checkpoint_path(cfg, checkpoint)
        else:
            path = str(checkpoint)
        key = (path, str(device))
        if key not in _FCGF_CACHE:
            if device is None:
                import torch

                device = "cuda" if torch.cuda.is_available() else "cpu"
            _FCGF_CACHE[key] = F.load_fcgf(path, device=device)
        model = _FCGF_CACHE[key]
    return _recent_features(points, voxel, model, lambda: F.fcgf_features(points, voxel, model))


_RECENT: "OrderedDict[tuple, tuple[np.ndarray, np.ndarray]]" = OrderedDict()
_RECENT_SIZE = 8


def _recent_features(points: np.ndarray, voxel: float, model, compute):
    """FCGF features of a cloud seen in one of the last few calls, from memory: a sweep that
    changes only the image side (notebook 02's depth errors, the fusion weights) asks for the
    same depth-side cloud again, and FCGF on a room costs seconds on a CPU. Keyed by the
    cloud's bytes, the voxel and the network (its object and parameter versions), so a
    changed input or trained network is never served stale features."""

    pts = np.ascontiguousarray(points, dtype=np.float64)
    version = tuple(int(p._version) for p in model.parameters())
    key = (hashlib.blake2b(pts.tobytes(), digest_size=16).digest(), pts.shape, float(voxel), id(model), version)
    if key in _RECENT:
        _RECENT.move_to_end(key)
        down, feats = _RECENT[key]
        return down.copy(), feats.copy()
    down, feats = compute()
    _RECENT[key] = (down.copy(), feats.copy())
    while len(_RECENT) > _RECENT_SIZE:
        _RECENT.popitem(last=False)
    return down, feats


def geometric_features(points: np.ndarray, cfg, method: str | None = None,
                       camera_location=(0.0, 0.0, 0.0), at: np.ndarray | None = None,
                       backend=None, **kw) -> tuple[np.ndarray, np.ndarray]:
    """Features of a cloud with the method of ``cfg.geometric`` (or ``method``).

    ``"fpfh"``: :func:`fpfh_features` with voxel ``cfg.fpfh_voxel`` (``cfg.voxel_size`` when
    the config has no such field), normal radius ``cfg.normal_radius_factor * voxel`` and
    feature radius ``cfg.fpfh_radius_factor * voxel``; ``at``: compute only the features
    :func:`pixel_features` will read for these points (see :func:`fpfh_features`).
    ``"fcgf"``: :func:`fcgf_features` at voxel ``cfg.voxel_size`` (``kw``: ``checkpoint``,
    ``model``, ``device``); a missing checkpoint raises ``MissingWeightsError``. ``backend``:
    its :meth:`~freereg_lib.models.base.Backend.fcgf_model` (the micro backend's trained
    FCGF) is used when no ``model`` is given.
    """
    method = (method or cfg.geometric).lower()
    if method == "fpfh":
        v = getattr(cfg, "fpfh_voxel", None) or cfg.voxel_size
        return fpfh_features(points, v, cfg.normal_radius_factor * v, cfg.fpfh_radius_factor * v,
                             camera_location=camera_location, at=at)
    if method == "fcgf":
        if kw.get("model") is None and backend is not None:
            kw["model"] = getattr(backend, "fcgf_model", lambda: None)()
        return fcgf_features(points, cfg.voxel_size, cfg=cfg, **kw)
    raise ValueError(f"unknown geometric feature {method!r}; use 'fpfh' or 'fcgf'")
