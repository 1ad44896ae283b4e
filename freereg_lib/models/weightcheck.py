"""Weight files that are what they claim to be: content hashes, checksum manifests, intact files.

* :func:`file_sha256`: the SHA-256 of a file, computed once per version of the file and
  remembered by (resolved path, size, inode, change time, modification time). The change time
  (``st_ctime``) cannot be set back, so a copy that keeps the old modification time
  (``cp -p``, ``rsync -a``, ``tar``) is still seen as new; the feature cache keys on these hashes.
* ``SHA256SUMS`` manifests (``sha256sum`` format: ``<hex>  <file name>``) beside committed weights:
  :func:`write_manifest` writes one for a folder, :func:`verify_manifest` checks it and names
  the file that differs. The micro models' loaders verify their folder; their savers rewrite it.
  Regenerate every manifest under a folder with ``python -m freereg_lib.models.weightcheck write
  freereg_lib/models/micro/weights`` (``verify`` checks them).
* :func:`check_safetensors`: a ``.safetensors`` file whose header or data is cut short.
* :func:`load_pretrained`: ``from_pretrained`` that refuses a ``config.json`` that does not fit
  the weights (transformers would give the missing layers random weights with a warning).

Every problem raises :class:`WeightsError` (also ``freereg_lib.models.WeightsError``), naming the file and
what was expected.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import struct
import sys
import tempfile
from pathlib import Path


class WeightsError(ValueError):
    """A weight file or folder that is there but cannot be used: a checkpoint of another model
    or format, a truncated or damaged file (checksum), a ``config.json`` that does not fit the
    weights. The message names the file and what was expected. (Missing weights raise
    :class:`~freereg_lib.models.MissingWeightsError`.)"""


MANIFEST = "SHA256SUMS"
WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pth", ".pt", ".ckpt")
# The other files of a model folder that change what it computes.
MODEL_FILES = ("config.json", "preprocessor_config.json", "tokenizer.json", "tokenizer_config.json",
               "special_tokens_map.json", "vocab.json", "merges.txt", "scheduler_config.json", "model_index.json")

_MEMO: dict[tuple, str] = {}


def _stamp(path: Path) -> tuple:
    st = path.stat()
    return (str(path), st.st_size, st.st_ino, st.st_ctime_ns, st.st_mtime_ns)


def file_sha256(path: str | os.PathLike, memo_file: str | os.PathLike | None = None) -> str:
    """Hex SHA-256 of the file at ``path``; computed once per (resolved path, size, inode,
    ``st_ctime_ns``, ``st_mtime_ns``) in this process, and across processes when ``memo_file``
    (a JSON file, e.g. in the feature cache's folder) is given."""
    p = Path(path).expanduser().resolve()
    stamp = _stamp(p)
    if stamp in _MEMO:
        return _MEMO[stamp]
    stored = _read_memo(memo_file)
    text = "|".join(map(str, stamp))
    if text in stored:
        _MEMO[stamp] = stored[text]
        return stored[text]
    h = hashlib.sha256()
    with open(p, "rb") as f:
        while block := f.read(1 << 23):
            h.update(block)
    digest = h.hexdigest()
    if _stamp(p) == stamp:  # not rewritten while it was read
        _MEMO[stamp] = digest
        if memo_file is not None:
            _write_memo(memo_file, {**stored, text: digest})
    return digest


def _read_memo(memo_file) -> dict:
    if memo_file is None:
        return {}
    try:
        memo = json.loads(Path(memo_file).read_text())
    except (OSError, ValueError):
        return {}
    return memo if isinstance(memo, dict) else {}


def _write_memo(memo_file, memo: dict) -> None:
    path = Path(memo_file)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            json.dump(memo, f)
        os.replace(tmp, path)
    except OSError:  # a read-only cache folder: the hashes are only remembered in this process
        pass


# --------------------------------------------------------------------------------------
# Manifests.

def model_files(folder: str | os.PathLike) -> list[Path]:
    """The files of ``folder`` (not its sub-folders) a manifest covers: weights and model configs."""
    folder = Path(folder)
    return sorted(f for f in folder.iterdir()
                  if f.is_file() and (f.name.endswith(WEIGHT_SUFFIXES) or f.name in MODEL_FILES))


def write_manifest(folder: str | os.PathLike) -> Path | None:
    """Write ``<folder>/SHA256SUMS`` for the model files of ``folder``; returns its path (None
    when the folder holds none)."""
    folder = Path(folder)
    files = model_files(folder)
    if not files:
        return None
    lines = [f"{file_sha256(f)}  {f.name}\n" for f in files]
    (folder / MANIFEST).write_text("".join(lines))
    return folder / MANIFEST


def read_manifest(folder: str | os.PathLike) -> dict[str, str] | None:
    """``{file name: hex}`` of ``<folder>/SHA256SUMS``, or None when there is none."""
    path = Path(folder) / MANIFEST
    if not path.is_file():
        return None
    out = {}
    for k, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split(None, 1)
        if not line.strip():
            continue
        if len(parts) != 2 or len(parts[0]) != 64:
            raise WeightsError(f"{path} line {k} is not '<sha256>  <file name>': {line!r}; rewrite it with "
                               f"python -m freereg_lib.models.weightcheck write {Path(folder)}")
        out[parts[1].lstrip("*").strip()] = parts[0].lower()
    return out


def verify_manifest(folder: str | os.PathLike) -> list[str]:
    """Check the files ``<folder>/SHA256SUMS`` lists (nothing to check without one); returns the
    names checked. A file whose content differs raises :class:`WeightsError` naming it; a
    listed file that is missing is left to the loader (its own missing-weights message)."""
    folder = Path(folder)
    listed = read_manifest(folder)
    if listed is None:
        return []
    checked = []
    for name, expected in listed.items():
        f = folder / name
        if not f.is_file():
            continue
        got = file_sha256(f)
        if got != expected:
            raise WeightsError(
                f"{f} does not match its checksum in {folder / MANIFEST} (SHA-256 {got[:16]}..., expected "
                f"{expected[:16]}...): the file is damaged or was replaced (a bit flip, a partial copy); restore it "
                f"(git checkout -- {f}), or after retraining on purpose rewrite the manifest: "
                f"python -m freereg_lib.models.weightcheck write {folder}")
        checked.append(name)
    return checked


def write_manifests(root: str | os.PathLike) -> list[Path]:
    """:func:`write_manifest` for ``root`` and every folder under it that holds model files."""
    root = Path(root)
    folders = [root, *sorted(d for d in root.rglob("*") if d.is_dir())]
    return [m for m in map(write_manifest, folders) if m is not None]


# --------------------------------------------------------------------------------------
# Intact files and configs that fit.

def check_safetensors(path: str | os.PathLike) -> None:
    """Raise :class:`WeightsError` unless ``path`` is a whole ``.safetensors`` file: an 8-byte
    header length, a JSON header, and data covering every tensor's offsets."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(8)
        n = struct.unpack("<Q", head)[0] if len(head) == 8 else -1
        if n < 2 or 8 + n > size:
            raise WeightsError(f"{path} is not a whole safetensors file ({size} bytes; the header alone should be "
                               f"{max(n, 0) + 8}): an interrupted copy or download, or another format; copy it again")
        try:
            header = json.loads(f.read(n))
        except ValueError:
            raise WeightsError(f"{path} has no readable safetensors header (JSON): a damaged file; copy it again") from None
    ends = [v["data_offsets"][1] for k, v in header.items() if k != "__metadata__" and isinstance(v, dict)
            and "data_offsets" in v]
    need = 8 + n + max(ends, default=0)
    if size < need:
        raise WeightsError(f"{path} is truncated: {size} bytes, its header describes {need} "
                           "(an interrupted copy or download); copy it again")


def check_folder(folder: str | os.PathLike) -> None:
    """Every ``.safetensors`` file of ``folder`` whole (:func:`check_safetensors`), then its
    manifest (:func:`verify_manifest`)."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    for f in sorted(folder.glob("*.safetensors")):
        check_safetensors(f)
    verify_manifest(folder)


def load_pretrained(cls, folder: str | os.PathLike, what: str, **kw):
    """``cls.from_pretrained(folder, **kw)`` (diffusers or transformers) that raises
    :class:`WeightsError` naming ``folder``'s ``config.json`` and weights when they do not fit:
    an error while loading, or weights missing, unexpected or of another shape (transformers
    would initialise missing layers at random and only warn)."""
    folder = Path(folder)
    check_folder(folder)
    weights = ", ".join(f.name for f in model_files(folder) if f.name.endswith(WEIGHT_SUFFIXES)) or "no weight file"
    where = f"{what} in {folder} (config.json and {weights})"
    try:
        model, info = cls.from_pretrained(str(folder), output_loading_info=True, **kw)
    except WeightsError:
        raise
    except Exception as exc:  # noqa: BLE001 - every library error becomes one that names the files
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]
        raise WeightsError(f"{where} does not load: {type(exc).__name__}: {first} (does config.json "
                           "describe these weights? a file from another model, or an edited config?)") from None
    bad = {k: list(info.get(k) or []) for k in ("missing_keys", "unexpected_keys", "mismatched_keys")}
    if any(bad.values()):
        said = "; ".join(f"{len(v)} {k.replace('_', ' ')} (e.g. {_key_name(v[0])})" for k, v in bad.items() if v)
        raise WeightsError(f"{where}: config.json does not fit the weights: {said}; use the config.json saved "
                           "with these weights")
    return model


# The committed micro weights (``freereg_lib.models.micro.diffusion.WEIGHTS_DIR``), named here so that this
# utility, which the model loaders import, does not import them back.
MICRO_WEIGHTS_DIR = Path(__file__).parent / "micro" / "weights"


def _key_name(k) -> str:
    return str(k[0] if isinstance(k, tuple) else k)


def main(argv: list[str] | None = None) -> int:
    """``python -m freereg_lib.models.weightcheck write|verify [ROOT]`` (default: the micro weights)."""
    p = argparse.ArgumentParser(prog="python -m freereg_lib.models.weightcheck", description=__doc__.split("\n")[0])
    p.add_argument("command", choices=("write", "verify"))
    p.add_argument("root", nargs="?", default=str(MICRO_WEIGHTS_DIR))
    args = p.parse_args(argv)
    root = Path(args.root)
    if args.command == "write":
        for path in write_manifests(root):
            print(f"wrote {path}")
        return 0
    status = 0
    for m in sorted([root / MANIFEST] if (root / MANIFEST).is_file() else []) + sorted(root.rglob(f"*/{MANIFEST}")):
        try:
            names = verify_manifest(m.parent)
            print(f"ok {m.parent}: {', '.join(names)}")
        except WeightsError as exc:
            print(f"error: {exc}", file=sys.stderr)
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
