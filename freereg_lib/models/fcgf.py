"""FCGF (Choy et al., ICCV 2019) ResUNetBN2C in plain PyTorch, with MinkowskiEngine semantics.

The paper's geometric features are FCGF's 32-d features from the official checkpoints
(3DMatch: ``2019-08-19_06-17-41.pth``, the 2.5 cm model of the paper's footnote, conv1
kernel 7, voxel 0.025 m (FCGF's ``2019-08-16_19-21-47.pth`` is its 5 cm model); KITTI:
``KITTI-v0.3-ResUNetBN2C-conv1-5-nout32.pth``, conv1 kernel 5, voxel 0.3 m; both linked from
the FCGF repository's README). Those are MinkowskiEngine (ME) networks, and ME does not
build on this CPU machine; spconv installs, but its strided convolutions create output sites
that ME's do not (see below), so the checkpoints would not compute the same function. This
module therefore re-implements the few sparse operations ResUNetBN2C needs, with ME's rules,
in ~100 lines of torch (hash look-ups with ``searchsorted`` + ``index_add_``). It runs on the
CPU (a 20k-voxel cloud in about a second) and on CUDA.

ME semantics reproduced (ME 0.5 ``kernel_region::coordinate_at`` and ``CoordinateMap::stride``):

* coordinates are integer voxel indices ``floor(xyz / voxel)``; a tensor at stride ``s``
  lives on multiples of ``s``;
* kernel offsets of a ``k^3`` kernel: flat index ``i = ix + k iy + k^2 iz`` (the FIRST axis
  varies fastest), offset ``(ix - k//2, iy - k//2, iz - k//2) * s_in``;
* convolution (stride 1 or 2): ``out[q] = sum_i in[q + off_i] @ W[i]`` over present inputs;
  a stride-2 convolution's output sites are ``floor(c / 2s) * 2s`` of the input sites
  (spconv would also create the sites ``c + s``);
* transposed convolution (stride 2): output sites are the encoder's sites of the finer
  stride (ME re-uses that coordinate map); ``out[p] = sum_i in[p - off_i] @ W[i]`` with the
  offsets stepping at the output stride (the transpose of the forward kernel map);
* kernel-size-1 stride-1 convolutions are plain matrix products with an ``(in, out)`` kernel;
  ``MinkowskiBatchNorm`` is ``BatchNorm1d`` on the features (eval mode).

State-dict mapping (official checkpoint -> this module): **identity**. Parameter names and
shapes are ME's: ``conv1.kernel (k^3, 1, 32)``, ``norm1.bn.{weight, bias, running_mean,
running_var, num_batches_tracked}``, ``block1.conv1.kernel (27, 32, 32)``, ``block1.norm1.bn.*``,
``block1.conv2.kernel``, ``block1.norm2.bn.*``, ``conv2.kernel (27, 32, 64)`` ... ``conv4``,
``block4``, ``conv4_tr.kernel (27, 256, 128)``, ``norm4_tr``, ``block4_tr``, ``conv3_tr.kernel
(27, 256, 64)``, ..., ``conv2_tr.kernel (27, 128, 64)``, ``conv1_tr.kernel (96, 64)``,
``final.kernel (64, 32)``, ``final.bias (1, 32)``. :func:`load_fcgf` also accepts a
``module.`` prefix, a ``{"state_dict": ...}`` checkpoint and the ``(1, in, out)`` /
``(out,)`` variants of 1x1 kernels and biases of other ME versions.

What could not be checked here: the outputs against ME itself (not installable); the unit
tests check every operation against dense ``torch`` convolutions on voxel grids instead.
"""
from __future__ import annotations

import _compat_pickle
import importlib
import pickle

import numpy as np

from freereg_lib.models.weightcheck import WeightsError, check_safetensors

CHANNELS = (None, 32, 64, 128, 256)
TR_CHANNELS = (None, 64, 64, 64, 128)  # ResUNetBN2C
CHECKPOINTS = {
    # The 2.5 cm model (the paper's footnote); "2019-08-16_19-21-47.pth" is FCGF's 5 cm one.
    "3dmatch": dict(file="2019-08-19_06-17-41.pth", conv1_kernel_size=7, voxel=0.025),
    "kitti": dict(file="KITTI-v0.3-ResUNetBN2C-conv1-5-nout32.pth", conv1_kernel_size=5,
                  voxel=0.3),
}


def _torch():
    import torch

    return torch


class SparseTensor:
    """Features ``feats (N, C)`` at integer coordinates ``coords (N, 3)`` of stride ``stride``."""

    def __init__(self, coords, feats, stride: int = 1):
        self.coords = coords
        self.feats = feats
        self.stride = int(stride)

    def replace(self, feats) -> "SparseTensor":
        return SparseTensor(self.coords, feats, self.stride)


class _Lookup:
    """Exact lookup of integer 3D coordinates.

    A dense table over the coordinates' bounding box when it has at most ``DENSE_CELLS`` cells
    (a room at 2.5 cm: a few million), else sorted int64 keys + ``searchsorted``. Both give the
    same rows; the dense one is several times faster.
    """

    MARGIN = 64
    DENSE_CELLS = 1 << 24  # 64 MB of int32 at most

    def __init__(self, coords, lo, span):
        torch = _torch()
        self.lo, self.span = lo, span
        self.table = None
        if len(coords):
            self.cmin = coords.min(0).values
            self.dims = coords.max(0).values - self.cmin + 1
            cells = int(torch.prod(self.dims))
            if cells <= self.DENSE_CELLS:
                self.table = torch.full((cells,), -1, dtype=torch.int32, device=coords.device)
                self.table[self._flat(coords - self.cmin)] = torch.arange(
                    len(coords), dtype=torch.int32, device=coords.device)
                return
        keys = self.key(coords)
        self.sorted, self.order = torch.sort(keys)

    def _flat(self, g):
        return (g[:, 0] * self.dims[1] + g[:, 1]) * self.dims[2] + g[:, 2]

    def key(self, c):
        c = c - self.lo
        return (c[:, 0] * self.span + c[:, 1]) * self.span + c[:, 2]

    def find(self, q):
        """Row of each query coordinate in the table, -1 where absent."""
        torch = _torch()
        if self.table is not None:
            g = q - self.cmin
            inside = ((g >= 0) & (g < self.dims)).all(1)
            rows = self.table[self._flat(torch.where(inside[:, None], g, torch.zeros_like(g)))].long()
            return torch.where(inside, rows, torch.full_like(rows, -1))
        inside = ((q - self.lo) >= 0).all(1) & ((q - self.lo) < self.span).all(1)
        k = self.key(torch.where(inside[:, None], q, torch.full_like(q, self.lo)))
        pos = torch.searchsorted(self.sorted, k).clamp(max=len(self.sorted) - 1)
        hit = inside & (self.sorted[pos] == k)
        return torch.where(hit, self.order[pos], torch.full_like(pos, -1))


def kernel_offsets(kernel_size: int):
    """``(k^3, 3)`` offsets in ME's order (first axis fastest), in units of the stride."""
    torch = _torch()
    r = torch.arange(kernel_size) - kernel_size // 2
    iz, iy, ix = torch.meshgrid(r, r, r, indexing="ij")  # ix varies fastest when flattened
    return torch.stack([ix.reshape(-1), iy.reshape(-1), iz.reshape(-1)], dim=1)


def _nn():
    import torch.nn as nn

    return nn


def _make_modules():
    """Define the nn.Module classes lazily (torch is imported only when FCGF is used)."""
    torch = _torch()
    nn = _nn()

    class MEConv(nn.Module):
        """A MinkowskiConvolution(-Transpose) with ME's parameter layout."""

        def __init__(self, cin, cout, kernel_size, stride=1, bias=False, transpose=False):
            super().__init__()
            self.cin, self.cout = cin, cout
            self.kernel_size, self.stride, self.transpose = kernel_size, stride, transpose
            self.use_mm = kernel_size == 1 and stride == 1
            shape = (cin, cout) if self.use_mm else (kernel_size ** 3, cin, cout)
            self.kernel = nn.Parameter(torch.empty(*shape))
            self.bias = nn.Parameter(torch.zeros(1, cout)) if bias else None
            std = 1.0 / np.sqrt(cin * kernel_size ** 3)
            nn.init.normal_(self.kernel, 0.0, std)

        def forward(self, x: SparseTensor, ctx: dict) -> SparseTensor:
            if self.use_mm:
                out = x.feats @ self.kernel
                if self.bias is not None:
                    out = out + self.bias
                return x.replace(out)
            if self.transpose:
                out_stride = x.stride // self.stride
                out_coords = ctx["maps"][out_stride]
                step = out_stride
                sign = -1
            else:
                out_stride = x.stride * self.stride
                if out_stride in ctx["maps"]:
                    out_coords = ctx["maps"][out_stride]
                else:
                    out_coords = torch.unique(
                        torch.div(x.coords, out_stride, rounding_mode="floor") * out_stride,
                        dim=0)
                    ctx["maps"][out_stride] = out_coords
                step = x.stride
                sign = 1
            # A kernel map depends only on the coordinates at both strides, so the convolutions
            # of one block (and training's backward pass) share it, as ME's kernel-map cache
            # does. It is a gather table: row q lists, per kernel offset, the input row feeding
            # output q (or the zero row appended after the inputs), so the convolution is one
            # gather and one matrix product.
            maps = ctx.setdefault("kernel_maps", {})
            key = (x.stride, out_stride, self.kernel_size, self.transpose)
            if key not in maps:
                table = ctx["lookup"](x.stride, x.coords)
                offs = kernel_offsets(self.kernel_size).to(x.coords.device) * step * sign
                gather = torch.full((len(out_coords), len(offs)), len(x.coords), dtype=torch.long,
                                    device=x.coords.device)
                for i in range(len(offs)):
                    src = table.find(out_coords + offs[i])
                    hit = src >= 0
                    gather[hit, i] = src[hit]
                maps[key] = gather
            gather = maps[key]
            padded = torch.cat([x.feats, x.feats.new_zeros(1, self.cin)])
            out = padded[gather].reshape(len(gather), -1) @ self.kernel.reshape(-1, self.cout)
            if self.bias is not None:
                out = out + self.bias
            return SparseTensor(out_coords, out, out_stride)

    class MEBatchNorm(nn.Module):
        def __init__(self, c, momentum=0.1):
            super().__init__()
            self.bn = nn.BatchNorm1d(c, momentum=momentum)

        def forward(self, x, ctx=None):
            return x.replace(self.bn(x.feats))

    def relu(x):
        return x.replace(torch.relu(x.feats))

    class BasicBlockBN(nn.Module):
        def __init__(self, c, bn_momentum=0.05):
            super().__init__()
            self.conv1 = MEConv(c, c, 3)
            self.norm1 = MEBatchNorm(c, bn_momentum)
            self.conv2 = MEConv(c, c, 3)
            self.norm2 = MEBatchNorm(c, bn_momentum)

        def forward(self, x, ctx):
            out = relu(self.norm1(self.conv1(x, ctx)))
            out = self.norm2(self.conv2(out, ctx))
            return relu(out.replace(out.feats + x.feats))

    class ResUNetBN2C(nn.Module):
        """FCGF's ResUNetBN2C (CHANNELS 32-64-128-256, TR_CHANNELS 64-64-64-128)."""

        def __init__(self, in_channels=1, out_channels=32, conv1_kernel_size=7,
                     normalize_feature=True, bn_momentum=0.05):
            super().__init__()
            C, T = CHANNELS, TR_CHANNELS
            self.normalize_feature = normalize_feature
            self.conv1 = MEConv(in_channels, C[1], conv1_kernel_size)
            self.norm1 = MEBatchNorm(C[1], bn_momentum)
            self.block1 = BasicBlockBN(C[1], bn_momentum)
            self.conv2 = MEConv(C[1], C[2], 3, stride=2)
            self.norm2 = MEBatchNorm(C[2], bn_momentum)
            self.block2 = BasicBlockBN(C[2], bn_momentum)
            self.conv3 = MEConv(C[2], C[3], 3, stride=2)
            self.norm3 = MEBatchNorm(C[3], bn_momentum)
            self.block3 = BasicBlockBN(C[3], bn_momentum)
            self.conv4 = MEConv(C[3], C[4], 3, stride=2)
            self.norm4 = MEBatchNorm(C[4], bn_momentum)
            self.block4 = BasicBlockBN(C[4], bn_momentum)
            self.conv4_tr = MEConv(C[4], T[4], 3, stride=2, transpose=True)
            self.norm4_tr = MEBatchNorm(T[4], bn_momentum)
            self.block4_tr = BasicBlockBN(T[4], bn_momentum)
            self.conv3_tr = MEConv(C[3] + T[4], T[3], 3, stride=2, transpose=True)
            self.norm3_tr = MEBatchNorm(T[3], bn_momentum)
            self.block3_tr = BasicBlockBN(T[3], bn_momentum)
            self.conv2_tr = MEConv(C[2] + T[3], T[2], 3, stride=2, transpose=True)
            self.norm2_tr = MEBatchNorm(T[2], bn_momentum)
            self.block2_tr = BasicBlockBN(T[2], bn_momentum)
            self.conv1_tr = MEConv(C[1] + T[2], T[1], 1)
            self.final = MEConv(T[1], out_channels, 1, bias=True)

        def forward(self, x: SparseTensor) -> SparseTensor:
            c = x.coords
            lo = int(c.min()) - _Lookup.MARGIN
            span = int(c.max()) - lo + _Lookup.MARGIN + 1
            tables: dict = {}

            def lookup(stride, coords):
                if stride not in tables:
                    tables[stride] = _Lookup(coords, lo, span)
                return tables[stride]

            ctx = {"maps": {1: c}, "lookup": lookup}

            def cat(a, b):
                return a.replace(torch.cat([a.feats, b.feats], dim=1))

            s1 = self.block1(self.norm1(self.conv1(x, ctx)), ctx)
            s2 = self.block2(self.norm2(self.conv2(relu(s1), ctx)), ctx)
            s4 = self.block3(self.norm3(self.conv3(relu(s2), ctx)), ctx)
            s8 = self.block4(self.norm4(self.conv4(relu(s4), ctx)), ctx)
            out = relu(self.block4_tr(self.norm4_tr(self.conv4_tr(relu(s8), ctx)), ctx))
            out = relu(self.block3_tr(self.norm3_tr(self.conv3_tr(cat(out, s4), ctx)), ctx))
            out = relu(self.block2_tr(self.norm2_tr(self.conv2_tr(cat(out, s2), ctx)), ctx))
            out = relu(self.conv1_tr(cat(out, s1), ctx))
            out = self.final(out, ctx)
            if self.normalize_feature:
                out = out.replace(torch.nn.functional.normalize(out.feats, dim=1))
            return out

    return MEConv, MEBatchNorm, BasicBlockBN, ResUNetBN2C


_MODULES = None


def modules():
    """``(MEConv, MEBatchNorm, BasicBlockBN, ResUNetBN2C)`` classes."""
    global _MODULES
    if _MODULES is None:
        _MODULES = _make_modules()
    return _MODULES


def ResUNetBN2C(**kw):
    """Build the network (random weights); see :func:`load_fcgf` for checkpoints."""
    return modules()[3](**kw)


class CheckpointRefused(WeightsError):
    """A checkpoint file that is not a plain state-dict checkpoint (it pickles something
    other than tensors, containers and the known config objects); nothing in it was run.
    A :class:`~freereg_lib.models.weightcheck.WeightsError` (a ``ValueError``), as every unusable
    checkpoint."""


class _Loose(dict):
    """Inert stand-in for the config objects FCGF checkpoints pickle (``easydict.EasyDict``,
    ``argparse.Namespace``): their items and attributes become dict entries."""

    def __setstate__(self, state):
        if isinstance(state, tuple) and len(state) == 2:  # (state, slotstate)
            state = {**(state[0] or {}), **(state[1] or {})}
        if isinstance(state, dict):
            self.update(state)


# What a plain checkpoint may pickle: tensors (torch's rebuild functions; storages are
# resolved by torch itself), ordered dicts, numpy scalars / arrays and the two config types
# FCGF's trainer saves (read as inert dicts). Anything else is refused BEFORE it is called.
_ALLOWED_GLOBALS = {
    ("collections", "OrderedDict"), ("torch._utils", "_rebuild_tensor"), ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"), ("torch._utils", "_rebuild_parameter_with_state"),
    ("torch", "Size"), ("torch", "device"), ("builtins", "set"), ("builtins", "frozenset"),
    ("_codecs", "encode"), ("numpy", "dtype"), ("numpy", "ndarray"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
}
_CONFIG_GLOBALS = {("easydict", "EasyDict"), ("argparse", "Namespace")}


def _restricted_pickle_module():

    class Unpickler(pickle.Unpickler):
        def find_class(self, module, name):
            # Protocol 2 (torch.save's) writes Python 2 names, e.g. __builtin__.
            if (module, name) in _compat_pickle.NAME_MAPPING:
                module, name = _compat_pickle.NAME_MAPPING[(module, name)]
            module = _compat_pickle.IMPORT_MAPPING.get(module, module)
            if (module, name) in _CONFIG_GLOBALS:
                return _Loose
            if (module, name) in _ALLOWED_GLOBALS:
                if module.startswith("numpy.core"):  # NumPy 2 renamed numpy.core to numpy._core
                    module = "numpy._core" + module[len("numpy.core"):]
                return getattr(importlib.import_module(module), name)
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed")

    class Module:
        __name__ = "freereg_restricted_pickle"
        UnpicklingError = pickle.UnpicklingError

        @staticmethod
        def load(file, **kw):
            return Unpickler(file, **kw).load()

    Module.Unpickler = Unpickler
    return Module


def _load_checkpoint_file(path):
    """The dict of an FCGF checkpoint file, never running code from it.

    First ``torch.load(weights_only=True)``; FCGF's own checkpoints also pickle their training
    config (an ``easydict.EasyDict``), which that refuses, so a second, equally restricted
    reading allows exactly the globals a plain checkpoint needs plus those config types (read
    as inert dicts). A file that pickles anything else raises :class:`CheckpointRefused` naming
    the file; nothing it references is called.
    """

    torch = _torch()
    if str(path).endswith(".safetensors"):  # the micro FCGF (float16 on disk; loaded as float32)
        from safetensors.torch import load_file

        check_safetensors(path)
        return {k: v.float() if v.is_floating_point() else v for k, v in load_file(str(path)).items()}
    _check_checkpoint_format(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        pass
    except (RuntimeError, EOFError, ValueError, KeyError) as exc:
        raise _unreadable(path, exc) from None
    try:
        return torch.load(path, map_location="cpu", weights_only=False, pickle_module=_restricted_pickle_module())
    except (RuntimeError, EOFError, ValueError, KeyError) as exc:
        raise _unreadable(path, exc) from None
    except pickle.UnpicklingError as exc:
        raise CheckpointRefused(
            f"{path} is not a plain state-dict checkpoint ({exc}); it was not loaded, since unpickling it "
            "could run arbitrary code. An FCGF checkpoint holds tensors, a state_dict and a config "
            "(easydict / argparse). If you trust the file, convert it once to a plain one: python -c "
            "\"import torch; c = torch.load('IN.pth', weights_only=False); torch.save({'state_dict': "
            "c['state_dict']}, 'OUT.pth')\""
        ) from None


def load_fcgf(checkpoint, conv1_kernel_size: int | None = None, device="cpu"):
    """ResUNetBN2C with the weights of an official FCGF checkpoint (a path or a state dict),
    or of a ``.safetensors`` state dict such as the micro FCGF's.

    ``conv1_kernel_size`` (7 for 3DMatch, 5 for KITTI) defaults to the cube root of
    ``conv1.kernel``'s first dimension; in / out channels come from the kernels' shapes.
    A file that is not such a checkpoint (another model's keys, a text file, a cut file) raises
    :class:`~freereg_lib.models.weightcheck.WeightsError` naming it and what was expected.
    """
    name = "the state dict given" if isinstance(checkpoint, dict) else str(checkpoint)
    ckpt = _load_checkpoint_file(checkpoint) if not isinstance(checkpoint, dict) else checkpoint
    state = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(state, dict) or not all(k in _strip(state) for k in _FCGF_KEYS):
        found = sorted(map(str, _strip(state))) if isinstance(state, dict) else [type(ckpt).__name__]
        shown = ", ".join(found[:6]) + (f", ... ({len(found)} keys)" if len(found) > 6 else "")
        raise WeightsError(
            f"{name} is not an FCGF (ResUNetBN2C) checkpoint: expected a state dict with "
            f"{' and '.join(_FCGF_KEYS)} (at the top or under 'state_dict'), found {shown or 'nothing'}; "
            "give the official 3DMatch / KITTI checkpoint (ResUNetBN2C-16feat-3conv.pth, KITTI-v0.3-ResUNetBN2C-"
            "conv1-5-nout32.pth) or a micro FCGF's fcgf_micro.safetensors")
    state = _strip(state)
    if conv1_kernel_size is None:
        conv1_kernel_size = int(round(state["conv1.kernel"].shape[0] ** (1 / 3)))
    out_channels = state["final.kernel"].shape[-1]
    in_channels = state["conv1.kernel"].shape[-2]
    net = ResUNetBN2C(in_channels=in_channels, out_channels=out_channels,
                      conv1_kernel_size=conv1_kernel_size)
    own = net.state_dict()
    fixed = {}
    for k, v in state.items():
        if k in own and own[k].shape != v.shape and own[k].numel() == v.numel():
            v = v.reshape(own[k].shape)
        fixed[k] = v
    try:
        net.load_state_dict(fixed, strict=True)
    except RuntimeError as exc:
        detail = " ".join(str(exc).split())[:300]
        raise WeightsError(f"{name} does not fit FCGF's ResUNetBN2C (conv1 kernel {conv1_kernel_size}, "
                           f"{in_channels} -> {out_channels} channels): {detail}") from None
    return net.to(device).eval()


_FCGF_KEYS = ("conv1.kernel", "final.kernel")


def _strip(state) -> dict:
    """``state`` without DataParallel's ``module.`` prefixes."""
    if not isinstance(state, dict):
        return {}
    return {k[len("module."):] if isinstance(k, str) and k.startswith("module.") else k: v for k, v in state.items()}


def _check_checkpoint_format(path) -> None:
    """Refuse, naming ``path``, a file that is neither a torch zip checkpoint nor a pickle (a
    text file, an HTML page saved by a browser, an empty file)."""
    with open(path, "rb") as f:
        head = f.read(4)
    if head[:2] == b"PK" or head[:1] == b"\x80":  # torch.save's zip, or a legacy pickle
        return
    kind = "an empty file" if not head else ("a text file" if _looks_like_text(path) else "not a torch checkpoint")
    raise WeightsError(f"{path} is {kind}: expected an FCGF checkpoint saved by torch.save (a zip or pickle "
                       "file: .pth), e.g. the official ResUNetBN2C-16feat-3conv.pth; a failed download saves an "
                       "HTML page or an error message under the checkpoint's name")


def _looks_like_text(path) -> bool:
    with open(path, "rb") as f:
        block = f.read(4096)
    try:
        block.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.start >= len(block) - 3  # only a character cut by the 4 kB read
    return True


def _unreadable(path, exc: Exception) -> WeightsError:
    detail = " ".join(str(exc).split())[:200] or type(exc).__name__
    return WeightsError(f"{path} cannot be read as a torch checkpoint ({type(exc).__name__}: {detail}): a truncated "
                        "or damaged file (an interrupted copy or download?); copy it again")


def voxelize(points: np.ndarray, voxel: float):
    """``(coords (M, 3) int64, sel (M,))``: one point per voxel ``floor(xyz / voxel)`` (the
    first point of each voxel in input order), as the official ``sparse_quantize``."""
    c = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)
    _, sel = np.unique(c, axis=0, return_index=True)
    sel = np.sort(sel)
    return c[sel], sel


def fcgf_features(points: np.ndarray, voxel: float, model, device=None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """FCGF features of a cloud: ``(down_points (M, 3), feats (M, C) float32)``, unit norm."""
    torch = _torch()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    out_c = model.final.cout
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros((0, out_c), np.float32)
    coords, sel = voxelize(pts, voxel)
    dev = device or next(model.parameters()).device
    x = SparseTensor(torch.from_numpy(coords).to(dev),
                     torch.ones(len(coords), model.conv1.cin, device=dev))
    with torch.inference_mode():
        f = model(x).feats
        f = torch.nn.functional.normalize(f, dim=1)
    return pts[sel], f.float().cpu().numpy()
