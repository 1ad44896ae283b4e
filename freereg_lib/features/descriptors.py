"""Backend-independent feature operations: per-layer PCA, sampling at keypoints, fusion.

Follows the official code (WHU-USI3DV/FreeReg; docs/fidelity.md):

* :func:`pca_reduce`: per chosen layer, each pixel vector L2-normalised over channels, one
  PCA basis fitted on the source and target pixels together (mean-centred covariance, top
  ``dim`` eigenvectors), every reduced layer bilinearly resized to the largest chosen map,
  concatenated (384 channels for layers 0, 4, 6 at 128 each), NOT normalised (the official
  ``merge_feat``: features are normalised only after sampling at keypoints).
* :func:`sample_features`: the maps are (conceptually) bilinearly upsampled with
  ``align_corners=True`` to the original image size and sampled at keypoints, without
  building the full-size map.
* :func:`fuse`: ``[w F_d, (1 - w) F_g]`` with each part L2-normalised first as the official
  ``feature_merge_on_kpts``: ``f / (||f|| + 1e-5)``.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.linalg import eigh

EPS = 1e-5


def l2_normalize(x: np.ndarray, eps: float = EPS, axis: int = -1) -> np.ndarray:
    """``x / (||x|| + eps)`` along ``axis`` (zero vectors stay zero), as the official
    ``feature_merge_on_kpts`` normalises each feature type (not ``F.normalize``'s
    ``max(||x||, eps)``: the two differ by a relative 1e-5 on unit-size vectors)."""
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    n = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / (n + np.asarray(eps, dtype=x.dtype))


def _resize_matrix(n_out: int, n_in: int) -> np.ndarray:
    """``(n_out, n_in)`` linear-interpolation matrix, half-pixel centres
    (``align_corners=False``), border-clamped."""
    R = np.zeros((n_out, n_in))
    if n_in == 1:
        R[:, 0] = 1.0
        return R
    src = (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
    src = np.clip(src, 0, n_in - 1)
    i0 = np.minimum(np.floor(src).astype(int), n_in - 2)
    f = src - i0
    R[np.arange(n_out), i0] += 1 - f
    R[np.arange(n_out), i0 + 1] += f
    return R


def resize_bilinear(fmap: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of ``fmap (C, h, w)`` to ``hw``, as ``F.interpolate(mode="bilinear",
    align_corners=False)`` (no antialiasing)."""
    C, h, w = fmap.shape
    H, W = hw
    if (h, w) == (H, W):
        return fmap
    Rh = _resize_matrix(H, h).astype(fmap.dtype)
    Rw = _resize_matrix(W, w).astype(fmap.dtype)
    return np.einsum("Hh,chw,Ww->cHW", Rh, fmap, Rw, optimize=True)


def _pca_project(X: np.ndarray, k: int) -> np.ndarray:
    """Scores ``(N, k)`` of the mean-centred rows of ``X (N, C)`` on the top-``k`` principal
    axes. Each axis' sign is fixed so its largest-magnitude score is positive; components
    beyond the data's rank (variance < 1e-10 of the largest) are set to zero, not noise."""
    N, C = X.shape
    Xc = X - X.mean(axis=0, keepdims=True)
    if N < C:  # Gram trick: eigenvectors of Xc Xc^T give the scores directly
        lam, U = np.linalg.eigh(Xc @ Xc.T)
        order = np.argsort(lam)[::-1][:k]
        lam = lam[order] / N
        P = U[:, order] * np.sqrt(np.maximum(lam * N, 0.0))
    else:

        lam, V = eigh((Xc.T @ Xc) / N, subset_by_index=[C - k, C - 1], driver="evr")
        order = np.argsort(lam)[::-1]
        lam, V = lam[order], V[:, order]
        P = Xc @ V
    if lam.size:
        P[:, lam < 1e-10 * max(lam[0], 1e-300)] = 0.0
    if P.size:
        idx = np.argmax(np.abs(P), axis=0)
        signs = np.sign(P[idx, np.arange(P.shape[1])])
        signs[signs == 0] = 1.0
        P = P * signs
    return P


def _pca_project_torch(X: np.ndarray, k: int, device: str) -> np.ndarray:
    """:func:`_pca_project` in float32 torch on ``device`` (a GPU's eigensolver instead of the
    host's); the same scores up to float32 rounding, same sign rule, same rank cut (at float32's
    resolution, 1e-6)."""
    import torch

    Xt = torch.from_numpy(np.ascontiguousarray(X, dtype=np.float32)).to(device)
    N, C = Xt.shape
    Xc = Xt - Xt.mean(dim=0, keepdim=True)
    if N < C:
        lam, U = torch.linalg.eigh(Xc @ Xc.T)
        lam, U = lam.flip(0)[:k], U.flip(1)[:, :k]
        P = U * lam.clamp(min=0).sqrt()
        lam = lam / N
    else:
        lam, V = torch.linalg.eigh((Xc.T @ Xc) / N)
        lam, V = lam.flip(0)[:k], V.flip(1)[:, :k]
        P = Xc @ V
    if lam.numel():
        P[:, lam < 1e-6 * lam[0].clamp(min=1e-30)] = 0.0
    if P.numel():
        idx = P.abs().argmax(dim=0)
        signs = torch.sign(P[idx, torch.arange(P.shape[1], device=P.device)])
        signs[signs == 0] = 1.0
        P = P * signs
    return P.double().cpu().numpy()


def pca_reduce(maps_src: Sequence[np.ndarray], maps_tgt: Sequence[np.ndarray],
               layers: Sequence[int] = (0, 4, 6), dim: int = 128,
               normalize: bool = False, device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-layer joint PCA of a pair's decoder maps, resized and concatenated.

    Args:
        maps_src, maps_tgt: the nine decoder layers of each side (lists indexed by layer, or
            dicts ``{layer: map}``), each ``(C, h, w)``.
        layers: the layers to use (the paper: 0, 4, 6).
        dim: PCA components per layer (128). A layer gets ``min(dim, C, N)`` components when
            it has fewer channels ``C`` or fewer pixels ``N`` (source + target together), so
            the output then has fewer than ``dim * len(layers)`` channels.
        normalize: L2-normalise the concatenated map per pixel. Default False, as the
            official ``merge_feat`` (the features are normalised after sampling at the
            keypoints, by :func:`fuse`); True normalises before the upsampling, which mixes
            neighbouring pixels' directions instead of their values (checked against the
            official ``merge_feat`` and ``feature_merge_on_kpts`` by ``python tools/parity.py``).
        device: None (the reference): float64 NumPy on the host. ``"cuda"`` (or ``"cpu"``):
            the PCA in float32 torch on that device, equal up to float32 rounding
            (``cfg.pca_device``, a GPU speed-up).

    Returns:
        ``(F_src, F_tgt)``, each ``(C_total, h, w) float32`` where ``(h, w)`` is that side's
        largest chosen map (32 x 44 at 512 x 704 with layer 6) and ``C_total`` the sum of
        the per-layer component counts.
    """
    red_s, red_t = pca_layers(maps_src, maps_tgt, layers, dim, device)

    def merge(maps):
        hw = (max(m.shape[1] for m in maps), max(m.shape[2] for m in maps))
        out = np.concatenate([resize_bilinear(m, hw) for m in maps], axis=0)
        if normalize:
            out = l2_normalize(out, axis=0)
        return out.astype(np.float32)

    return merge(red_s), merge(red_t)


def pca_layers(maps_src, maps_tgt, layers: Sequence[int] = (0, 4, 6), dim: int = 128,
               device: str | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per chosen layer, the joint PCA of the two sides' maps before any resize (the official
    ``pca_feats``): two lists of ``(k, h, w) float64`` maps, one per layer."""
    if len(layers) == 0:
        raise ValueError("choose at least one layer")
    red_s, red_t = [], []
    for layer in layers:
        S = np.asarray(maps_src[layer], dtype=np.float64)
        T = np.asarray(maps_tgt[layer], dtype=np.float64)
        if S.ndim != 3 or T.ndim != 3 or S.shape[0] != T.shape[0]:
            raise ValueError(f"layer {layer}: maps must be (C, h, w) with equal C, got "
                             f"{S.shape} and {T.shape}")
        C = S.shape[0]
        Xs = S.reshape(C, -1).T
        Xt = T.reshape(C, -1).T
        X = np.concatenate([Xs, Xt], axis=0)
        X = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
        k = int(min(dim, C, X.shape[0]))
        P = _pca_project(X, k) if device is None else _pca_project_torch(X, k, str(device))
        ns = Xs.shape[0]
        red_s.append(P[:ns].T.reshape(k, *S.shape[1:]))
        red_t.append(P[ns:].T.reshape(k, *T.shape[1:]))
    return red_s, red_t


def _sample_ac(fmap: np.ndarray, x: np.ndarray, y: np.ndarray, H: int, W: int) -> np.ndarray:
    """Value of ``fmap`` upsampled (align_corners=True) to ``(H, W)`` at integer pixels."""
    C, h, w = fmap.shape
    # Source positions in the map's own precision, as torch computes them for a float32 map
    # (scale = (w - 1) / (W - 1) and scale * x in float32): float64 positions would move a
    # keypoint's sample by up to ~4e-6 of a cell on a 640-pixel image, 5e-6 in the features.
    f32 = np.float32 if fmap.dtype == np.float32 else np.float64
    X = np.asarray(x, f32) * (f32(w - 1) / f32(W - 1)) if W > 1 else np.zeros(len(x), f32)
    Y = np.asarray(y, f32) * (f32(h - 1) / f32(H - 1)) if H > 1 else np.zeros(len(y), f32)
    x0 = np.clip(np.floor(X).astype(int), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(Y).astype(int), 0, max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = np.clip(X - x0.astype(f32), f32(0), f32(1))[:, None]
    fy = np.clip(Y - y0.astype(f32), f32(0), f32(1))[:, None]
    f = fmap.transpose(1, 2, 0)  # (h, w, C) view
    return ((f[y0, x0] * (1 - fx) + f[y0, x1] * fx) * (1 - fy)
            + (f[y1, x0] * (1 - fx) + f[y1, x1] * fx) * fy)


def sample_features(fmap: np.ndarray, uv: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Features ``(N, C)`` of ``fmap (C, h, w)`` at pixels ``uv (N, 2)`` = (u, v) of the
    ORIGINAL image of size ``image_size = (H, W)``.

    Exactly what the official code does (upsample the map bilinearly with
    ``align_corners=True`` to ``(H, W)``, then read it at the keypoints), without the
    full-size map: an integer pixel ``(u, v)`` maps to map coordinates
    ``(u (w-1)/(W-1), v (h-1)/(H-1))``, sampled bilinearly. A non-integer ``uv`` gets the
    bilinear interpolation of the upsampled map (clamped to the image).
    """
    fmap = np.asarray(fmap)
    if not np.issubdtype(fmap.dtype, np.floating):
        fmap = fmap.astype(np.float64)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    H, W = int(image_size[0]), int(image_size[1])
    u = np.clip(uv[:, 0], 0, W - 1)
    v = np.clip(uv[:, 1], 0, H - 1)
    u0, v0 = np.floor(u), np.floor(v)
    du, dv = u - u0, v - v0
    if not (du.any() or dv.any()):
        return _sample_ac(fmap, u0, v0, H, W).astype(fmap.dtype, copy=False)
    u1, v1 = np.minimum(u0 + 1, W - 1), np.minimum(v0 + 1, H - 1)
    du, dv = du[:, None], dv[:, None]
    out = (_sample_ac(fmap, u0, v0, H, W) * (1 - du) * (1 - dv)
           + _sample_ac(fmap, u1, v0, H, W) * du * (1 - dv)
           + _sample_ac(fmap, u0, v1, H, W) * (1 - du) * dv
           + _sample_ac(fmap, u1, v1, H, W) * du * dv)
    return out.astype(fmap.dtype, copy=False)


def fuse(f_d: np.ndarray, f_g: np.ndarray, w: float = 0.5) -> np.ndarray:
    """``[w l2n(f_d), (1 - w) l2n(f_g)]``, ``(N, Cd + Cg)``.

    ``w = 1`` is FreeReg-D and ``w = 0`` FreeReg-G (the other part is then all zeros, so the
    width stays ``Cd + Cg``). A zero row (e.g. a geometric feature beyond ``tau_g``) stays zero.
    """
    f_d = np.asarray(f_d)
    f_g = np.asarray(f_g)
    if f_d.ndim != 2 or f_g.ndim != 2 or len(f_d) != len(f_g):
        raise ValueError(f"f_d {f_d.shape} and f_g {f_g.shape} must be (N, C) with the same N")
    if not 0.0 <= w <= 1.0:
        raise ValueError(f"w must be in [0, 1], got {w}")
    dt = np.result_type(f_d.dtype, f_g.dtype, np.float32)
    return np.concatenate([w * l2_normalize(f_d.astype(dt)),
                           (1.0 - w) * l2_normalize(f_g.astype(dt))], axis=1)
