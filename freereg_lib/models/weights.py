"""Where pretrained weights are looked for, and the one error when they are missing.

Nothing here downloads. A model id resolves to a folder in this order:

1. ``weights_dir`` (argument, else ``cfg.extra["weights_dir"]``, else the environment
   variable ``FREEREG_WEIGHTS``): the sub-folders ``<weights_dir>/<name>`` (the id's last
   part, what ``--local-dir <weights_dir>/<name>`` makes) and ``<weights_dir>/<owner>/<name>``;
2. the Hugging Face cache (``HF_HOME`` / ``HF_HUB_CACHE``), offline
   (``local_files_only=True``).

A folder counts when it has ``model_index.json`` or ``config.json`` (or, for Stable
Diffusion, a ``unet/config.json``).
"""
from __future__ import annotations

import os
from pathlib import Path

from freereg_lib.models.base import MissingWeightsError

SD15_ID = "stable-diffusion-v1-5/stable-diffusion-v1-5"
SD15_OLD_IDS = ("runwayml/stable-diffusion-v1-5",)  # the original id, now removed from the Hub
CONTROLNET_DEPTH_ID = "lllyasviel/control_v11f1p_sd15_depth"
ZOEDEPTH_INDOOR_ID = "Intel/zoedepth-nyu"
ZOEDEPTH_OUTDOOR_ID = "Intel/zoedepth-nyu-kitti"

# The official code loads SD v1.5's NON-EMA UNet weights (``v1-5-pruned.ckpt`` with
# ``use_ema: False``); in diffusers they are the ``non_ema`` variant of the ``unet`` folder,
# while its default files hold the EMA weights.
SD_UNET_VARIANTS = ("non_ema", "ema")
SD15_NON_EMA_FILES = ("unet/diffusion_pytorch_model.non_ema.safetensors",
                      "unet/diffusion_pytorch_model.non_ema.bin")
SD15_EMA_FILES = ("unet/diffusion_pytorch_model.safetensors", "unet/diffusion_pytorch_model.bin")
# The fine-tuned depth ControlNet of the official repository (its configs' default since
# 2023-11-23; the paper's FreeReg-Ft rows), an original single-file (ldm) checkpoint.
CONTROLNET_FT_FILE = "control_v11f1p_sd15_depth_ft.pth"
SINGLE_FILE_SUFFIXES = (".pth", ".pt", ".ckpt", ".safetensors", ".bin")

# Only the files the diffusion features use (the full SD repo is tens of GB): of the UNet,
# its config and the non-EMA weights.
_INCLUDE = {
    SD15_ID: '--include "model_index.json" "unet/config.json" '
             '"unet/diffusion_pytorch_model.non_ema.safetensors" "vae/*" "text_encoder/*" '
             '"tokenizer/*" "scheduler/*"',
}


def default_weights_dir(cfg=None, weights_dir: str | os.PathLike | None = None) -> Path | None:
    """``weights_dir`` if given, else ``cfg.extra["weights_dir"]``, else ``$FREEREG_WEIGHTS``."""
    if weights_dir is None and cfg is not None:
        weights_dir = (getattr(cfg, "extra", None) or {}).get("weights_dir")
    if weights_dir is None:
        weights_dir = os.environ.get("FREEREG_WEIGHTS") or None
    return Path(weights_dir).expanduser() if weights_dir else None


def hf_cache_dir() -> str:
    try:
        from huggingface_hub import constants

        return str(constants.HF_HUB_CACHE)
    except Exception:  # pragma: no cover - huggingface_hub is a dependency of diffusers
        return os.path.join(os.path.expanduser("~"), ".cache", "huggingface", "hub")


def _is_model_folder(p: Path) -> bool:
    return p.is_dir() and any(
        (p / f).is_file() for f in ("model_index.json", "config.json", "unet/config.json")
    )


def _candidates(model_id: str, weights_dir: Path | None) -> list[Path]:
    if weights_dir is None:
        return []
    name = model_id.rpartition("/")[2]
    return [weights_dir / name, weights_dir / model_id]


def download_command(model_id: str, weights_dir: Path | None) -> str:
    local = (weights_dir or Path("weights")) / model_id.rpartition("/")[2]
    extra = _INCLUDE.get(model_id, "")
    return f"huggingface-cli download {model_id} {extra} --local-dir {local}".replace("  ", " ")


def try_resolve(model_id: str, weights_dir: Path | None = None,
                alt_ids: tuple[str, ...] = ()) -> tuple[str | None, list[str]]:
    """The local folder of ``model_id`` (or one of ``alt_ids``) and every place searched."""
    searched: list[str] = []
    for mid in (model_id, *alt_ids):
        for cand in _candidates(mid, weights_dir):
            searched.append(str(cand))
            if _is_model_folder(cand):
                return str(cand), searched
    cache = hf_cache_dir()
    for mid in (model_id, *alt_ids):
        searched.append(f"Hugging Face cache {cache} (repo {mid})")
        try:
            from huggingface_hub import snapshot_download

            path = snapshot_download(mid, local_files_only=True)
        except Exception:
            continue
        if _is_model_folder(Path(path)):
            return path, searched
    # Keep the list short and unique, in order.
    seen: list[str] = []
    for s in searched:
        if s not in seen:
            seen.append(s)
    return None, seen


def missing_weights_error(missing: list[tuple[str, list[str]]], weights_dir: Path | None,
                          reason: str | None = None) -> MissingWeightsError:
    """One :class:`MissingWeightsError` for every ``(model_id, searched)`` in ``missing``."""
    lines = ["Pretrained weights are missing for the real backend (nothing is downloaded "
             "at run time)."]
    for mid, searched in missing:
        lines.append(f"\n* model id {mid!r}; looked in:")
        lines += [f"    - {s}" + (" (exists, but holds no model_index.json or config.json: an incomplete "
                                  "download, or another model?)" if reason is None and Path(s).is_dir() else "")
                  for s in searched]
        lines.append("  On a machine with internet, run:")
        lines.append(f"    {download_command(mid, weights_dir)}")
    if reason:
        lines.append(f"\nLoading failed with: {reason}")
    if weights_dir is not None and not weights_dir.is_dir():
        lines.append(f"\nNote: weights_dir {weights_dir} does not exist (a typo, or a path relative to "
                     f"another working directory? this one is {Path.cwd()}).")
    elif weights_dir is not None and _is_model_folder(weights_dir):
        lines.append(f"\nNote: weights_dir {weights_dir} is itself a model folder; weights_dir is the folder "
                     f"that holds the model folders: pass weights_dir={str(weights_dir.parent)!r}.")
    lines.append(
        "\nThen copy the folder(s) here and pass weights_dir=... to get_backend (or set "
        "FREEREG_WEIGHTS, or cfg.extra['weights_dir']); a filled Hugging Face cache works "
        "too (`hf download` is the newer name of the same command).\n"
        'To run without weights, use backend="stub" (synthetic scenes; instant) or '
        'backend="tiny" (the real code path with random weights; numbers mean nothing).'
    )
    return MissingWeightsError(
        "\n".join(lines),
        model_ids=[m for m, _ in missing],
        searched=[s for _, ss in missing for s in ss],
    )


def resolve_all(specs: dict[str, tuple[str, tuple[str, ...]]],
                weights_dir: Path | None) -> dict[str, str]:
    """Resolve ``{key: (model_id, alt_ids)}``; raise one error naming all missing ones."""
    found: dict[str, str] = {}
    missing: list[tuple[str, list[str]]] = []
    for key, (mid, alts) in specs.items():
        path, searched = try_resolve(mid, weights_dir, alts)
        if path is None:
            missing.append((mid, searched))
        else:
            found[key] = path
    if missing:
        raise missing_weights_error(missing, weights_dir)
    return found


def check_sd_unet_variant(variant: str) -> str:
    """``variant`` if it is one of ``SD_UNET_VARIANTS``, else a ``ValueError``."""
    if variant not in SD_UNET_VARIANTS:
        raise ValueError(f"sd_unet_variant must be one of {SD_UNET_VARIANTS} ('non_ema': the official "
                         f"weights; 'ema': diffusers' default files), got {variant!r}")
    return variant


def sd_unet_weight_file(sd_path: str | os.PathLike, variant: str = "non_ema") -> Path | None:
    """The UNet weight file diffusers will load from the SD folder ``sd_path`` for
    ``variant`` (safetensors first, as diffusers), or None when there is none."""
    files = SD15_NON_EMA_FILES if check_sd_unet_variant(variant) == "non_ema" else SD15_EMA_FILES
    for f in files:
        if (Path(sd_path) / f).is_file():
            return Path(sd_path) / f
    return None


def require_sd_unet_variant(sd_path: str | os.PathLike, variant: str) -> Path:
    """The UNet weight file of ``variant`` in ``sd_path``; a :class:`MissingWeightsError`
    naming the files to download (and the EMA opt-in) when the folder has none."""
    found = sd_unet_weight_file(sd_path, variant)
    if found is not None:
        return found
    files = SD15_NON_EMA_FILES if variant == "non_ema" else SD15_EMA_FILES
    what = ("the NON-EMA UNet weights the official code uses (v1-5-pruned.ckpt with use_ema: False)"
            if variant == "non_ema" else "the EMA UNet weights (diffusers' default files)")
    lines = [
        f"Stable Diffusion v1.5 folder {sd_path} has no {variant} UNet: {what} are missing.",
        "Expected one of:",
        *[f"    - {Path(sd_path) / f}" for f in files],
        "On a machine with internet, run:",
        f'    huggingface-cli download {SD15_ID} "unet/config.json" "{files[0]}"'
        + ("" if "snapshots" in Path(sd_path).parts else f" --local-dir {sd_path}"),
        "(or re-run the download command of docs/real_data.md, which fetches them).",
    ]
    if variant == "non_ema":
        lines.append("To use the EMA weights instead (not the official setting; features differ), set "
                     "cfg.sd_unet_variant = 'ema' (config_for(..., sd_unet_variant='ema')).")
    raise MissingWeightsError("\n".join(lines), model_ids=[SD15_ID],
                              searched=[str(Path(sd_path) / f) for f in files])


def is_single_file(spec: str | os.PathLike) -> bool:
    """Whether a ``controlnet`` setting names a single checkpoint file (``.pth``, ``.ckpt``,
    ``.safetensors``, ...) rather than a model id or a diffusers folder."""
    p = Path(str(spec)).expanduser()
    return p.is_file() or str(spec).lower().endswith(SINGLE_FILE_SUFFIXES)


def resolve_single_file(spec: str | os.PathLike, weights_dir: Path | None = None) -> str:
    """The path of a single-file checkpoint: ``spec`` as given (absolute, or relative to the
    working directory), else ``<weights_dir>/<spec>``; a :class:`MissingWeightsError` naming
    every place tried otherwise."""
    p = Path(str(spec)).expanduser()
    tried = [p]
    if weights_dir is not None and not p.is_absolute():
        tried.append(weights_dir / p)
    for cand in tried:
        if cand.is_file():
            return str(cand)
    ft = p.name == CONTROLNET_FT_FILE
    lines = [f"ControlNet checkpoint file {spec} not found; looked at:",
             *[f"    - {c}" for c in tried]]
    if ft:
        lines.append(
            f"{CONTROLNET_FT_FILE} is the official FreeReg repository's fine-tuned depth ControlNet "
            "(the paper's FreeReg-Ft rows): download it from the link in that repository's README "
            "(WHU-USI3DV/FreeReg, 'ckpt-ft', a Google Drive file) and give its path.")
    lines.append(f"Table 1 (training-free) uses {CONTROLNET_DEPTH_ID}: the default cfg.controlnet.")
    raise MissingWeightsError("\n".join(lines), model_ids=[str(spec)], searched=[str(c) for c in tried])
