"""Mutual nearest-neighbour matching of feature sets, chunked so 20k x 20k fits in memory.

One matrix product per chunk serves both directions: the rows of a chunk of ``A B^T`` give
the nearest ``b`` of each ``a`` of the chunk, and its columns update a running nearest ``a``
of every ``b``. (The first version multiplied twice, ``A B^T`` and ``B A^T``; the products'
entries are bitwise the same, so the matches are too, at half the arithmetic.) On the CPU
the element-wise work and the reductions run in NumPy, single-threaded: torch's OpenMP
element-wise kernels stall on a busy 2-core machine.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch


@dataclass
class Matches:
    """Mutual nearest neighbours: rows ``idx_image`` of the image side, ``idx_depth`` of the depth side."""

    idx_image: np.ndarray
    idx_depth: np.ndarray

    def __len__(self) -> int:
        return len(self.idx_image)


# Below this many columns a chunk's column argmin is one np.argmin(axis=0); above it a
# running minimum over the chunk's rows is faster (NumPy's axis-0 argmin is a strided
# scalar loop, ~6 ns per entry; the row loop is vectorised, ~1.5 ns per entry + ~5 us per row).
_ROW_LOOP_MIN_COLS = 2048


def _torch():
    import torch  # on first use: the geometry and the features' NumPy side load without torch

    return torch


def _both_cpu(ta: torch.Tensor, tb: torch.Tensor, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """``(nearest b of each a, nearest a of each b)`` on the CPU, one product per chunk.

    Distances are the first version's float32 expressions, ``||b||^2 - 2 a.b`` for the rows
    and ``||a||^2 - 2 a.b`` for the columns, and ties go to the lowest index (as argmin).
    """
    torch = _torch()
    N, M = ta.shape[0], tb.shape[0]
    a_sq = (ta * ta).sum(1).numpy()
    b_sq = (tb * tb).sum(1).numpy()
    ab = np.empty(N, dtype=np.int64)
    best = np.full(M, np.inf, dtype=np.float32)  # running column minimum
    ba = np.zeros(M, dtype=np.int64)
    c = min(chunk, N)
    dot_t = torch.empty((c, M), dtype=torch.float32)
    dist = np.empty((c, M), dtype=np.float32)
    mask = np.empty(M, dtype=bool)
    for start in range(0, N, chunk):
        n = min(chunk, N - start)
        dot = torch.mm(ta[start : start + n], tb.T, out=dot_t[:n]).numpy()
        np.multiply(dot, -2.0, out=dot)  # exact: a power of two
        d = dist[:n]
        np.add(dot, b_sq[None, :], out=d)
        ab[start : start + n] = d.argmin(1)
        np.add(dot, a_sq[start : start + n, None], out=d)
        if M >= _ROW_LOOP_MIN_COLS:
            for r in range(n):
                row = d[r]
                np.less(row, best, out=mask)  # strict: an earlier row keeps a tie
                np.copyto(best, row, where=mask)
                np.copyto(ba, start + r, where=mask)
        else:
            arg = d.argmin(0)
            val = d[arg, np.arange(M)]
            np.less(val, best, out=mask)
            np.copyto(best, val, where=mask)
            np.copyto(ba, arg + start, where=mask)
    return ab, ba


def _both_torch(ta: torch.Tensor, tb: torch.Tensor, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
    """As :func:`_both_cpu` with torch operations on ``ta.device`` (CUDA)."""
    torch = _torch()
    N, M = ta.shape[0], tb.shape[0]
    a_sq = (ta * ta).sum(1)
    b_sq = (tb * tb).sum(1)
    ab = torch.empty(N, dtype=torch.long, device=ta.device)
    best = torch.full((M,), float("inf"), dtype=torch.float32, device=ta.device)
    ba = torch.zeros(M, dtype=torch.long, device=ta.device)
    for start in range(0, N, chunk):
        dot = ta[start : start + chunk] @ tb.T
        dot.mul_(-2.0)
        ab[start : start + chunk] = (dot + b_sq[None, :]).argmin(1)
        val, arg = (dot + a_sq[start : start + chunk, None]).min(0)
        better = val < best
        best = torch.where(better, val, best)
        ba = torch.where(better, arg + start, ba)
    return ab, ba


def mutual_nn(
    feats_a: np.ndarray, feats_b: np.ndarray, chunk: int = 2048, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours between ``feats_a (N, C)`` and ``feats_b (M, C)``.

    A pair ``(i, j)`` is kept when ``j`` is the nearest neighbour of ``a_i`` in ``b`` and
    ``i`` the nearest of ``b_j`` in ``a`` (float32 squared Euclidean distances; ties go to
    the lowest index). Memory is ``O(chunk * M)``: two ``(chunk, M)`` float32 buffers
    (160 MB at chunk 2048, M = 10k). ``device``: ``"cpu"`` or a CUDA device.
    Returns ``idx_a (K,) int64`` and ``idx_b (K,) int64``, sorted by ``idx_a``.
    """
    torch = _torch()
    a = np.asarray(feats_a, dtype=np.float32)
    b = np.asarray(feats_b, dtype=np.float32)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"features must be (N, C) and (M, C) with the same C; got {a.shape} and {b.shape}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    for name, x in (("feats_a", a), ("feats_b", b)):
        if not np.isfinite(x).all():
            raise ValueError(f"{name} has non-finite values (NaN or inf): nearest neighbours are undefined")
    chunk = int(chunk)
    ta = torch.from_numpy(np.ascontiguousarray(a)).to(device)
    tb = torch.from_numpy(np.ascontiguousarray(b)).to(device)
    with torch.no_grad():
        if ta.device.type == "cpu":
            ab, ba = _both_cpu(ta, tb, chunk)
        else:
            ab_t, ba_t = _both_torch(ta, tb, chunk)
            ab, ba = ab_t.cpu().numpy(), ba_t.cpu().numpy()
    idx_a = np.arange(len(a))
    mutual = ba[ab] == idx_a
    return idx_a[mutual], ab[mutual]
