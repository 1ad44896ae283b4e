"""The feature cache knows its weights, committed weights carry checksums, and unusable
checkpoint / weight files give an error naming the file and what was expected.

* the cache key holds the SHA-256 of every weight file (memoised by path, size, inode and change
  time), so weights rewritten with the old size and modification time (``cp -p``, ``rsync -a``,
  ``tar``) are seen; a relative ``weights_dir`` is resolved; ``half`` entries are their own;
* the micro weights' ``SHA256SUMS`` manifests are verified on load: a flipped bit names the file;
* a truncated safetensors file, a ``config.json`` that does not fit the weights, an FCGF
  checkpoint of another model, a text file given as a checkpoint: one ``WeightsError`` each.
"""
import json
import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from freereg_lib.commands.cache import CachedBackend, backend_identity
from freereg_lib.models import weightcheck
from freereg_lib.models.micro import diffusion as M
from freereg_lib.models.weightcheck import MANIFEST, WeightsError

ROOT = Path(__file__).resolve().parent.parent
IMAGE = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)


class Fake:
    """A backend whose outputs are those of its weight file's bytes."""

    name = "fake"

    def __init__(self, **settings):
        self.calls = Counter()
        self.__dict__.update(settings)

    def diffusion_rgb(self, image, ids=None):
        self.calls["rgb"] += 1
        weights = Path(self.weights_dir) / "unet" / "model.safetensors"
        return [np.full((2, 3, 4), float(image.sum()) + weights.read_bytes()[0] / 7.0, np.float32)]

    def diffusion_depth(self, depth, ids=None):
        return [np.zeros((2, 3, 4), np.float32)]

    def mono_depth(self, image, depth_gt=None):
        return np.ones(image.shape[:2])


def _weights(folder: Path, fill: bytes) -> Path:
    f = folder / "unet" / "model.safetensors"
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_bytes(fill * 1000)
    return f


def _rewrite_keeping_size_and_mtime(f: Path, fill: bytes, new_inode: bool) -> None:
    """New bytes, same size, the old modification time put back (as cp -p / rsync -a / tar)."""
    st = f.stat()
    time.sleep(0.05)  # the change time moves on (its clock ticks every few ms)
    if new_inode:  # rsync -a, tar: a new file renamed over the old
        tmp = f.with_suffix(".tmp")
        tmp.write_bytes(fill * 1000)
        os.replace(tmp, f)
    else:  # cp -p onto an existing file: the same inode, rewritten
        with open(f, "r+b") as h:
            h.write(fill * 1000)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert f.stat().st_size == st.st_size and f.stat().st_mtime_ns == st.st_mtime_ns


@pytest.mark.parametrize("new_inode", [False, True], ids=["cp-p-in-place", "rsync-a-rename"])
def test_weights_rewritten_with_the_old_size_and_mtime_are_not_served_stale(tmp_path, new_inode):
    weights = tmp_path / "weights"
    f = _weights(weights, b"a")
    cache = tmp_path / "cache"
    first = Fake(weights_dir=weights)
    before = CachedBackend(first, cache, {}).diffusion_rgb(IMAGE)
    _rewrite_keeping_size_and_mtime(f, b"b", new_inode)
    second = Fake(weights_dir=weights)
    after = CachedBackend(second, cache, {}).diffusion_rgb(IMAGE)
    assert second.calls["rgb"] == 1, "served the features of the old weights"
    assert not np.array_equal(before[0], after[0])
    assert backend_identity(second)["weights"][str(f.resolve())][1] == weightcheck.file_sha256(f)


def test_a_relative_weights_dir_is_resolved_and_fingerprinted(tmp_path, monkeypatch):
    for where, fill in (("a", b"a"), ("b", b"b")):
        _weights(tmp_path / where / "weights", fill)
    cache = tmp_path / "cache"
    monkeypatch.chdir(tmp_path / "a")
    in_a = CachedBackend(Fake(weights_dir="weights"), cache, {})
    identity = in_a.identity
    assert identity["settings"]["weights_dir"] == str((tmp_path / "a" / "weights").resolve())
    assert str((tmp_path / "a" / "weights" / "unet" / "model.safetensors").resolve()) in identity["weights"]
    in_a.diffusion_rgb(IMAGE)
    monkeypatch.chdir(tmp_path / "b")  # the same relative path names other weights
    other = Fake(weights_dir="weights")
    CachedBackend(other, cache, {}).diffusion_rgb(IMAGE)
    assert other.calls["rgb"] == 1
    # and new bytes in the relative folder change the key as well
    _rewrite_keeping_size_and_mtime(tmp_path / "b" / "weights" / "unet" / "model.safetensors", b"c", False)
    again = Fake(weights_dir="weights")
    CachedBackend(again, cache, {}).diffusion_rgb(IMAGE)
    assert again.calls["rgb"] == 1


def test_half_and_full_precision_entries_are_distinct(tmp_path):
    weights = tmp_path / "weights"
    _weights(weights, b"a")
    a, b = Fake(weights_dir=weights), Fake(weights_dir=weights)
    half = CachedBackend(a, tmp_path / "cache", {}, half=True)
    full = CachedBackend(b, tmp_path / "cache", {}, half=False)
    assert half.path("diffusion_rgb", (IMAGE, None, None)) != full.path("diffusion_rgb", (IMAGE, None, None))
    half.diffusion_rgb(IMAGE)
    exact = full.diffusion_rgb(IMAGE)
    assert b.calls["rgb"] == 1  # not served the float16 entry
    np.testing.assert_array_equal(exact[0], b.diffusion_rgb(IMAGE)[0])


def test_hashes_are_remembered_by_path_size_inode_and_change_time(tmp_path, monkeypatch):
    f = tmp_path / "w.safetensors"
    f.write_bytes(b"x" * 100)
    memo = tmp_path / "memo.json"
    first = weightcheck.file_sha256(f, memo)
    assert json.loads(memo.read_text()) and first in json.loads(memo.read_text()).values()
    reads = []
    real_open = open
    monkeypatch.setattr("builtins.open", lambda p, *a, **k: (reads.append(str(p)), real_open(p, *a, **k))[1])
    weightcheck._MEMO.clear()
    assert weightcheck.file_sha256(f, memo) == first  # from the memo file: the weights are not read
    assert str(f.resolve()) not in reads


# --------------------------------------------------------------------------------------
# The committed micro weights and their manifests.

def test_every_committed_weight_file_is_in_a_manifest_that_verifies():
    folders = [d for d in M.WEIGHTS_DIR.iterdir() if d.is_dir() and weightcheck.model_files(d)]
    assert {d.name for d in folders} >= {"vae", "unet", "controlnet", "text_encoder", "tokenizer", "depth"}
    for d in folders:
        assert (d / MANIFEST).is_file(), f"{d} has no {MANIFEST}: python -m freereg_lib.models.weightcheck write"
        assert sorted(weightcheck.verify_manifest(d)) == sorted(f.name for f in weightcheck.model_files(d))
    done = subprocess.run([sys.executable, "-m", "freereg_lib.models.weightcheck", "verify"], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def _copy(part: str, tmp_path: Path) -> Path:
    dst = tmp_path / "weights" / part
    shutil.copytree(M.WEIGHTS_DIR / part, dst)
    return dst


def _flip_a_bit(f: Path) -> None:
    data = bytearray(f.read_bytes())
    data[len(data) * 2 // 3] ^= 0x10
    f.write_bytes(bytes(data))


def test_bit_flipped_micro_weights_are_refused_naming_the_file(tmp_path):
    pytest.importorskip("diffusers")
    vae = _copy("vae", tmp_path)
    M.load(tmp_path / "weights", parts=("vae",))  # the intact copy loads
    _flip_a_bit(vae / "diffusion_pytorch_model.safetensors")
    with pytest.raises(WeightsError, match=r"vae/diffusion_pytorch_model\.safetensors does not match its checksum"):
        M.load(tmp_path / "weights", parts=("vae",))


def test_bit_flipped_micro_depth_weights_are_refused_naming_the_file(tmp_path):
    pytest.importorskip("transformers")
    from freereg_lib.models.micro import depth as MD

    depth = _copy("depth", tmp_path)
    _flip_a_bit(depth / "model.safetensors")
    with pytest.raises(WeightsError, match=r"depth/model\.safetensors does not match its checksum"):
        MD.load(depth)


def test_manifests_are_regenerated_by_the_savers_and_the_script(tmp_path):
    vae = _copy("vae", tmp_path)
    _flip_a_bit(vae / "diffusion_pytorch_model.safetensors")  # "retrained on purpose"
    assert weightcheck.main(["verify", str(tmp_path / "weights")]) == 1
    assert weightcheck.main(["write", str(tmp_path / "weights")]) == 0
    assert weightcheck.main(["verify", str(tmp_path / "weights")]) == 0
    models = M.load(M.WEIGHTS_DIR, parts=("vae", "tokenizer"))
    M.save(models, tmp_path / "saved", parts=("vae", "tokenizer"))
    assert "diffusion_pytorch_model.safetensors" in weightcheck.read_manifest(tmp_path / "saved" / "vae")
    assert weightcheck.verify_manifest(tmp_path / "saved" / "tokenizer")


# --------------------------------------------------------------------------------------
# Truncated files and configs that do not fit.

def test_a_truncated_depth_safetensors_file_is_named(tmp_path):
    pytest.importorskip("transformers")
    from freereg_lib.models.micro import depth as MD

    depth = _copy("depth", tmp_path)
    (depth / MANIFEST).unlink()  # the file check itself, not the checksum
    f = depth / "model.safetensors"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    with pytest.raises(WeightsError, match=r"depth/model\.safetensors is truncated: \d+ bytes, its header describes"):
        MD.load(depth)
    f.write_bytes(b"\x05")
    with pytest.raises(WeightsError, match="is not a whole safetensors file"):
        MD.load(depth)


def test_a_micro_config_that_does_not_fit_the_weights_is_named(tmp_path):
    pytest.importorskip("diffusers")
    for part, change in (("text_encoder", {"num_hidden_layers": 3}),      # transformers: random layers
                         ("unet", {"block_out_channels": [32, 64, 128, 256]})):  # diffusers: a shape error
        folder = _copy(part, tmp_path)
        (folder / MANIFEST).unlink()  # an exported folder has its own; here the config is the fault
        config = json.loads((folder / "config.json").read_text())
        (folder / "config.json").write_text(json.dumps({**config, **change}))
        with pytest.raises(WeightsError, match=rf"micro {part} in .*{part} \(config\.json and .*safetensors\)") as err:
            M.load(tmp_path / "weights", parts=(part,))
        assert "\n" not in str(err.value)


def test_a_micro_config_that_is_not_json_is_named(tmp_path):
    pytest.importorskip("transformers")
    from freereg_lib.models.micro import depth as MD

    depth = _copy("depth", tmp_path)
    (depth / MANIFEST).unlink()
    (depth / "config.json").write_text("{not json")
    with pytest.raises(WeightsError, match=r"micro ZoeDepth in .*depth \(config\.json and model\.safetensors\) "
                                           "does not load"):
        MD.load(depth)


# --------------------------------------------------------------------------------------
# FCGF checkpoints.

def test_an_fcgf_checkpoint_of_another_model_is_named(tmp_path):
    torch = pytest.importorskip("torch")
    from freereg_lib.models.fcgf import load_fcgf

    path = tmp_path / "other.pth"
    torch.save({"state_dict": {"encoder.weight": torch.zeros(3)}}, path)
    with pytest.raises(WeightsError, match=r"other\.pth is not an FCGF \(ResUNetBN2C\) checkpoint: expected a state "
                                           r"dict with conv1\.kernel and final\.kernel .*found encoder\.weight"):
        load_fcgf(str(path))
    with pytest.raises(WeightsError, match="not an FCGF"):
        load_fcgf({"model": {}})


def test_a_text_file_an_empty_file_and_a_cut_file_given_as_a_checkpoint_are_named(tmp_path):
    torch = pytest.importorskip("torch")
    from freereg_lib.models.fcgf import CheckpointRefused, load_fcgf

    text = tmp_path / "ckpt.pth"
    text.write_text("<html><body>404 Not Found</body></html>\n")
    with pytest.raises(WeightsError, match=r"ckpt\.pth is a text file: expected an FCGF checkpoint saved by torch\.save"):
        load_fcgf(str(text))
    empty = tmp_path / "empty.pth"
    empty.write_bytes(b"")
    with pytest.raises(WeightsError, match=r"empty\.pth is an empty file"):
        load_fcgf(str(empty))
    cut = tmp_path / "cut.pth"
    torch.save({"state_dict": {"conv1.kernel": torch.zeros(343, 1, 32)}}, cut)
    cut.write_bytes(cut.read_bytes()[:200])
    with pytest.raises(WeightsError, match=r"cut\.pth cannot be read as a torch checkpoint .* truncated or damaged"):
        load_fcgf(str(cut))
    assert issubclass(CheckpointRefused, WeightsError) and issubclass(WeightsError, ValueError)


def test_a_micro_fcgf_whose_weights_do_not_fit_is_named(tmp_path):
    pytest.importorskip("torch")
    from safetensors.torch import save_file

    from freereg_lib.models.micro import fcgf as MF

    net = MF.build(0)
    state = {k: v.contiguous() for k, v in net.state_dict().items() if not k.startswith("block1")}
    save_file(state, tmp_path / MF.WEIGHTS_FILE)
    with pytest.raises(WeightsError, match=r"fcgf_micro\.safetensors does not fit FCGF's ResUNetBN2C .*Missing key"):
        MF.load(tmp_path)
