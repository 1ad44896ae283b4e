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

from .base import MissingWeightsError

SD15_ID = "stable-diffusion-v1-5/stable-diffusion-v1-5"
SD15_OLD_IDS = ("runwayml/stable-diffusion-v1-5",)  # the original id, now removed from the Hub
CONTROLNET_DEPTH_ID = "lllyasviel/control_v11f1p_sd15_depth"
ZOEDEPTH_INDOOR_ID = "Intel/zoedepth-nyu"
ZOEDEPTH_OUTDOOR_ID = "Intel/zoedepth-nyu-kitti"

# Only the sub-folders the diffusion features use (the full SD repo is tens of GB).
_INCLUDE = {
    SD15_ID: '--include "model_index.json" "unet/*" "vae/*" "text_encoder/*" "tokenizer/*" '
             '"scheduler/*"',
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
