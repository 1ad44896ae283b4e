"""Mutual nearest-neighbour matching of feature sets, chunked so 20k x 20k fits in memory."""
from __future__ import annotations

import numpy as np
import torch


def _nearest(query: torch.Tensor, base: torch.Tensor, chunk: int) -> torch.Tensor:
    """Index of the nearest row of ``base`` for every row of ``query`` (Euclidean)."""
    base_sq = (base * base).sum(1)
    out = torch.empty(query.shape[0], dtype=torch.long, device=query.device)
    for start in range(0, query.shape[0], chunk):
        q = query[start : start + chunk]
        # ||q - b||^2 up to the per-row constant ||q||^2, which does not move the argmin.
        d = base_sq[None, :] - 2.0 * (q @ base.T)
        out[start : start + chunk] = d.argmin(1)
    return out


def mutual_nn(
    feats_a: np.ndarray, feats_b: np.ndarray, chunk: int = 2048, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours between ``feats_a (N, C)`` and ``feats_b (M, C)``.

    A pair ``(i, j)`` is kept when ``j`` is the nearest neighbour of ``a_i`` in ``b`` and
    ``i`` the nearest of ``b_j`` in ``a``. Memory is ``O(chunk * max(N, M))``.
    Returns ``idx_a (K,) int64`` and ``idx_b (K,) int64``, sorted by ``idx_a``.
    """
    a = np.asarray(feats_a, dtype=np.float32)
    b = np.asarray(feats_b, dtype=np.float32)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"features must be (N, C) and (M, C) with the same C; got {a.shape} and {b.shape}")
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ta = torch.from_numpy(a).to(device)
    tb = torch.from_numpy(b).to(device)
    with torch.no_grad():
        ab = _nearest(ta, tb, chunk)
        ba = _nearest(tb, ta, chunk)
        idx_a = torch.arange(len(a), device=ta.device)
        mutual = ba[ab] == idx_a
    idx_a = idx_a[mutual].cpu().numpy()
    return idx_a, ab[mutual].cpu().numpy()
