"""The micro FCGF: FCGF's ResUNetBN2C at the paper's 3DMatch settings, trained on the synthetic rooms.

The network is :mod:`freereg_lib.models.fcgf`'s (conv1 kernel 7, 32-d unit-norm output,
2.5 cm voxels), so its weights load with :func:`~freereg_lib.models.fcgf.load_fcgf`, the
loader of the official checkpoints. They live in ``weights/fcgf/`` as a float16 safetensors
state dict (loaded as float32) with ``config.json``, ``training.json``, ``eval.json`` and a
model card; ``freereg_lib.training.train_fcgf`` retrains them, ``freereg_lib.training.evaluate_fcgf`` measures them.
"""
from __future__ import annotations

import json
from pathlib import Path

from freereg_lib.models.base import MissingWeightsError
from freereg_lib.models.fcgf import ResUNetBN2C, load_fcgf
from freereg_lib.models.micro.diffusion import WEIGHTS_DIR
from freereg_lib.models.weightcheck import check_folder, write_manifest

VOXEL = 0.025
CONV1_KERNEL = 7
WEIGHTS_FILE = "fcgf_micro.safetensors"


def folder_of(weights_dir: str | Path | None = None) -> Path:
    """The micro FCGF folder of a micro weights folder (``<weights_dir>/fcgf``), falling back
    to the committed one when ``weights_dir`` has none."""
    own = Path(weights_dir) / "fcgf" if weights_dir else None
    return own if own is not None and (own / WEIGHTS_FILE).is_file() else WEIGHTS_DIR / "fcgf"


def build(seed: int = 0):
    """A ResUNetBN2C at the paper's 3DMatch settings with seeded random weights (train mode)."""
    import torch

    torch.manual_seed(seed)
    return ResUNetBN2C(in_channels=1, out_channels=32, conv1_kernel_size=CONV1_KERNEL)


def save(net, folder: str | Path, facts: dict | None = None) -> Path:
    """The state dict as float16 safetensors (BatchNorm counters stay integers), its
    ``config.json`` and, given ``facts``, ``training.json``."""
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: (v.half() if v.is_floating_point() else v).contiguous() for k, v in net.state_dict().items()}
    save_file(state, folder / WEIGHTS_FILE)
    config = {"architecture": "ResUNetBN2C", "in_channels": 1, "out_channels": 32,
              "conv1_kernel_size": CONV1_KERNEL, "voxel": VOXEL}
    (folder / "config.json").write_text(json.dumps(config, indent=1) + "\n")
    if facts is not None:
        (folder / "training.json").write_text(json.dumps(facts) + "\n")
    write_manifest(folder)
    return folder / WEIGHTS_FILE


def load(folder: str | Path, device="cpu"):
    """The trained network (eval mode) from ``folder``; a missing file raises
    :class:`~freereg_lib.models.MissingWeightsError` with the command that retrains it."""

    path = Path(folder) / WEIGHTS_FILE
    if not path.is_file():
        raise MissingWeightsError(
            f"micro FCGF weights not found: {path}; retrain them with "
            f"`python -m freereg_lib.training.train_fcgf --export {Path(folder)}`",
            model_ids=[WEIGHTS_FILE], searched=[str(path)])
    check_folder(folder)  # whole safetensors, SHA256SUMS where there is one
    return load_fcgf(str(path), conv1_kernel_size=CONV1_KERNEL, device=device)
