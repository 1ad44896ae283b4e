"""The real backend loads what the official code loads: the exact
conditional text, the NON-EMA SD v1.5 UNet, float32 everywhere (CUDA too), the ControlNet
v1.1 depth by default and the fine-tuned single-file checkpoint when given; and the weight
check command runs on the demo layout. Model loading is faked: these tests need no weights."""
from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from freereg_lib.config import FreeRegConfig, config_for  # noqa: E402
from freereg_lib.models import MissingWeightsError, get_backend  # noqa: E402
from freereg_lib.models import weights as W  # noqa: E402
from freereg_lib.models.diffusion import DiffusionFeatures  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
UNET_NON_EMA = "unet/diffusion_pytorch_model.non_ema.safetensors"


# ---------------------------------------------------------------------------------------
# Item 1: the text.

def _cond_text(cfg) -> str:
    return DiffusionFeatures(None, None, None, None, None, cfg, "cpu", torch.float32, (64, 64)).cond_text


def test_conditional_text_is_the_official_prompt_plus_best_quality_once():
    assert _cond_text(FreeRegConfig()) == "a photo of a room, furniture, household items, best quality"
    for name in ("3dmatch", "scannet", "synthetic_indoor"):
        assert _cond_text(config_for(name)) == "a photo of a room, furniture, household items, best quality"
    assert _cond_text(config_for("kitti")) == (
        "a vehicle camera photo of street view, trees, cars, people, house, road, sky, best quality")
    assert _cond_text(FreeRegConfig()).count("best quality") == 1


# ---------------------------------------------------------------------------------------
# Items 2, 3, 11: what the loaders receive (fake diffusers / transformers loaders).

@pytest.fixture()
def weights(tmp_path, monkeypatch):
    """A weights folder with the files the resolver looks for (no real weights) and an empty
    Hugging Face cache."""
    import huggingface_hub.constants as C

    monkeypatch.setattr(C, "HF_HUB_CACHE", str(tmp_path / "hf_cache"))
    monkeypatch.delenv("FREEREG_WEIGHTS", raising=False)
    w = tmp_path / "weights"
    sd = w / "stable-diffusion-v1-5"
    (sd / "unet").mkdir(parents=True)
    (sd / "model_index.json").write_text("{}")
    (sd / "unet" / "config.json").write_text("{}")
    (sd / UNET_NON_EMA).write_bytes(b"non-ema")
    (w / "control_v11f1p_sd15_depth").mkdir()
    (w / "control_v11f1p_sd15_depth" / "config.json").write_text("{}")
    return w


@pytest.fixture()
def fake_loaders(monkeypatch):
    """Record every ``from_pretrained`` / ``from_single_file`` call instead of loading."""
    import diffusers
    import transformers

    calls: list[tuple[str, str, tuple, dict]] = []

    def recorder(kind, method):
        def load(*args, **kw):
            calls.append((kind, method, args, kw))
            return torch.nn.Module()
        return load

    for cls in ("UNet2DConditionModel", "AutoencoderKL", "ControlNetModel"):
        monkeypatch.setattr(getattr(diffusers, cls), "from_pretrained", recorder(cls, "from_pretrained"))
    monkeypatch.setattr(diffusers.ControlNetModel, "from_single_file", recorder("ControlNetModel", "from_single_file"))
    for cls in ("CLIPTextModel", "CLIPTokenizer"):
        monkeypatch.setattr(getattr(transformers, cls), "from_pretrained", recorder(cls, "from_pretrained"))
    return calls


def _only(calls, kind):
    found = [c for c in calls if c[0] == kind]
    assert len(found) == 1, found
    return found[0]


def test_real_backend_loads_the_non_ema_unet_in_float32(weights, fake_loaders):
    be = get_backend("real", FreeRegConfig(), device="cpu", weights_dir=weights, load=("diffusion",))
    be.diffusion  # noqa: B018 - loads
    _, _, args, kw = _only(fake_loaders, "UNet2DConditionModel")
    assert kw["variant"] == "non_ema" and kw["subfolder"] == "unet" and kw["local_files_only"] is True
    assert args[0] == str(weights / "stable-diffusion-v1-5")
    for kind in ("UNet2DConditionModel", "AutoencoderKL", "CLIPTextModel", "ControlNetModel"):
        assert _only(fake_loaders, kind)[3]["torch_dtype"] == torch.float32
    # Table 1's ControlNet v1.1 depth, from its diffusers folder.
    _, method, args, _ = _only(fake_loaders, "ControlNetModel")
    assert method == "from_pretrained" and args[0] == str(weights / "control_v11f1p_sd15_depth")
    assert "non-EMA" in be.label and "ControlNet v1.1 depth" in be.label and "float32" in be.label


def test_float32_is_the_default_on_cuda_too(weights, fake_loaders, monkeypatch):
    """CUDA simulated: the device is CUDA, the dtype float32 (float16 was the old default)."""
    from freereg_lib.models.torch_backends import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    dev, dt = resolve_device(None)
    assert dev.type == "cuda" and dt == torch.float32
    be = get_backend("real", FreeRegConfig(), weights_dir=weights, load=("diffusion",))
    assert be.device.type == "cuda" and be.dtype == torch.float32
    be.diffusion  # noqa: B018
    assert {c[3]["torch_dtype"] for c in fake_loaders if "torch_dtype" in c[3]} == {torch.float32}
    # float16 / bfloat16 only when asked for, through the config (or get_backend's dtype=).
    fake_loaders.clear()
    be = get_backend("real", FreeRegConfig(dtype="float16"), weights_dir=weights, load=("diffusion",))
    be.diffusion  # noqa: B018
    assert {c[3]["torch_dtype"] for c in fake_loaders if "torch_dtype" in c[3]} == {torch.float16}
    assert get_backend("real", FreeRegConfig(dtype="float16"), weights_dir=weights, load=("diffusion",),
                       dtype="bfloat16").dtype == torch.bfloat16


def test_dtype_field_on_the_tiny_backend():
    assert get_backend("tiny", FreeRegConfig(), device="cpu").dtype == torch.float32
    assert get_backend("tiny", FreeRegConfig(dtype="bfloat16"), device="cpu").dtype == torch.bfloat16
    with pytest.raises(ValueError, match="unsupported dtype 'float64'"):
        get_backend("tiny", FreeRegConfig(dtype="float64"), device="cpu")


def test_missing_non_ema_files_stop_with_the_files_to_download(weights, fake_loaders):
    (weights / "stable-diffusion-v1-5" / UNET_NON_EMA).unlink()
    (weights / "stable-diffusion-v1-5" / "unet" / "diffusion_pytorch_model.safetensors").write_bytes(b"ema")
    with pytest.raises(MissingWeightsError) as err:
        get_backend("real", FreeRegConfig(), device="cpu", weights_dir=weights, load=("diffusion",))
    msg = str(err.value)
    assert "no non_ema UNet" in msg and "NON-EMA" in msg
    assert "unet/diffusion_pytorch_model.non_ema.safetensors" in msg
    assert "unet/diffusion_pytorch_model.non_ema.bin" in msg
    assert (f'huggingface-cli download stable-diffusion-v1-5/stable-diffusion-v1-5 "unet/config.json" '
            f'"{UNET_NON_EMA}" --local-dir {weights / "stable-diffusion-v1-5"}') in msg
    assert "sd_unet_variant = 'ema'" in msg
    assert not fake_loaders  # stopped before loading anything
    # The explicit opt-in to the EMA weights: diffusers' default files (variant None).
    be = get_backend("real", FreeRegConfig(sd_unet_variant="ema"), device="cpu", weights_dir=weights,
                     load=("diffusion",))
    be.diffusion  # noqa: B018
    assert _only(fake_loaders, "UNet2DConditionModel")[3]["variant"] is None
    assert "EMA UNet" in be.label and "non-EMA" not in be.label
    with pytest.raises(ValueError, match="sd_unet_variant must be one of"):
        get_backend("real", FreeRegConfig(sd_unet_variant="fp16"), device="cpu", weights_dir=weights,
                    load=("diffusion",))


def test_non_ema_variant_reads_the_non_ema_file_for_real(tmp_path):
    """With diffusers itself (no fake): a folder holding both UNets, the EMA one in the default
    files and another in ``*.non_ema.safetensors``; the default setting loads the latter."""
    import diffusers
    import transformers
    from diffusers import UNet2DConditionModel

    from freereg_lib.models.diffusion import TINY_UNET_CONFIG, load_real_diffusion

    sd = tmp_path / "stable-diffusion-v1-5"
    torch.manual_seed(0)
    ema = UNet2DConditionModel(**TINY_UNET_CONFIG)
    non_ema = UNet2DConditionModel(**TINY_UNET_CONFIG)
    ema.save_pretrained(sd / "unet")
    non_ema.save_pretrained(sd / "unet", variant="non_ema")
    assert (sd / UNET_NON_EMA).is_file() and (sd / "unet" / "diffusion_pytorch_model.safetensors").is_file()
    stub = staticmethod(lambda *a, **k: torch.nn.Module())
    with pytest.MonkeyPatch.context() as mp:
        for cls in (diffusers.AutoencoderKL, diffusers.ControlNetModel, transformers.CLIPTextModel,
                    transformers.CLIPTokenizer):
            mp.setattr(cls, "from_pretrained", stub)
        for variant, want in (("non_ema", non_ema), ("ema", ema)):
            diff = load_real_diffusion(str(sd), str(tmp_path), FreeRegConfig(), torch.device("cpu"), torch.float32,
                                       (64, 64), unet_variant=variant)
            got = diff.unet.state_dict()
            assert all(torch.equal(got[k], v) for k, v in want.state_dict().items()), variant
            assert next(diff.unet.parameters()).dtype == torch.float32


def test_readme_download_command_fetches_the_non_ema_unet():
    cmd = W.download_command(W.SD15_ID, Path("weights"))
    assert f'"{UNET_NON_EMA}"' in cmd and '"unet/config.json"' in cmd and '"unet/*"' not in cmd
    page = (ROOT / "docs" / "real_data.md").read_text()
    weights_section = page.split("\n## Weights", 1)[1].split("\n## ", 1)[0]
    assert f'"{UNET_NON_EMA}"' in weights_section and '"unet/*"' not in weights_section


def test_fine_tuned_controlnet_single_file(weights, fake_loaders, tmp_path):
    """FreeReg-Ft: the official fine-tuned checkpoint (original single-file format) goes to
    ``ControlNetModel.from_single_file`` with the v1.1 depth folder as its architecture."""
    ft = tmp_path / "freereg" / W.CONTROLNET_FT_FILE
    ft.parent.mkdir()
    ft.write_bytes(b"ldm controlnet")
    be = get_backend("real", FreeRegConfig(controlnet=str(ft)), device="cpu", weights_dir=weights,
                     load=("diffusion",))
    be.diffusion  # noqa: B018
    _, method, args, kw = _only(fake_loaders, "ControlNetModel")
    assert method == "from_single_file" and args[0] == str(ft)
    assert kw["config"] == str(weights / "control_v11f1p_sd15_depth") and kw["torch_dtype"] == torch.float32
    assert kw["local_files_only"] is True
    assert W.CONTROLNET_FT_FILE in be.label
    # A path relative to weights_dir works too; a missing file says where to get it.
    (weights / W.CONTROLNET_FT_FILE).write_bytes(b"x")
    be = get_backend("real", FreeRegConfig(controlnet=W.CONTROLNET_FT_FILE), device="cpu",
                     weights_dir=weights, load=("diffusion",))
    assert be.paths["controlnet_file"] == str(weights / W.CONTROLNET_FT_FILE)
    with pytest.raises(MissingWeightsError, match="official FreeReg repository's fine-tuned depth ControlNet"):
        get_backend("real", FreeRegConfig(controlnet=str(tmp_path / "nope" / W.CONTROLNET_FT_FILE)),
                    device="cpu", weights_dir=weights, load=("diffusion",))


def test_from_single_file_takes_a_local_config_folder():
    """The installed diffusers reads an original-format ControlNet with a local ``config``."""
    import inspect

    from diffusers import ControlNetModel

    assert hasattr(ControlNetModel, "from_single_file")
    doc = inspect.getdoc(ControlNetModel.from_single_file) or ""
    assert "config" in doc and "local_files_only" in doc


def _to_ldm_controlnet(state: dict, layers_per_block: int = 2) -> dict:
    """A diffusers ControlNet state dict in the original ControlNet (ldm) layout, the format of
    ``control_v11f1p_sd15_depth_ft.pth``: ``control_model.input_blocks``, ``zero_convs``,
    ``middle_block``, ``middle_block_out``, ``input_hint_block``, ``time_embed``."""
    import re

    res = [("norm1", "in_layers.0"), ("conv1", "in_layers.2"), ("norm2", "out_layers.0"),
           ("conv2", "out_layers.3"), ("time_emb_proj", "emb_layers.1"), ("conv_shortcut", "skip_connection")]
    fixed = {"time_embedding.linear_1": "time_embed.0", "time_embedding.linear_2": "time_embed.2",
             "conv_in": "input_blocks.0.0", "controlnet_cond_embedding.conv_in": "input_hint_block.0",
             "controlnet_cond_embedding.conv_out": "input_hint_block.14", "controlnet_mid_block": "middle_block_out.0"}

    def resnet(rest: str) -> str:
        for a, z in res:
            rest = rest.replace(a, z) if rest.startswith(a + ".") else rest
        return rest

    out = {}
    for k, v in state.items():
        head, _, leaf = k.rpartition(".")
        if head in fixed:
            new = f"{fixed[head]}.{leaf}"
        elif m := re.match(r"down_blocks\.(\d+)\.resnets\.(\d+)\.(.*)", k):
            b, j = int(m[1]), int(m[2])
            new = f"input_blocks.{b * (layers_per_block + 1) + j + 1}.0.{resnet(m[3])}"
        elif m := re.match(r"down_blocks\.(\d+)\.attentions\.(\d+)\.(.*)", k):
            new = f"input_blocks.{int(m[1]) * (layers_per_block + 1) + int(m[2]) + 1}.1.{m[3]}"
        elif m := re.match(r"down_blocks\.(\d+)\.downsamplers\.0\.conv\.(.*)", k):
            new = f"input_blocks.{int(m[1]) * (layers_per_block + 1) + layers_per_block + 1}.0.op.{m[2]}"
        elif m := re.match(r"controlnet_down_blocks\.(\d+)\.(.*)", k):
            new = f"zero_convs.{m[1]}.0.{m[2]}"
        elif m := re.match(r"mid_block\.resnets\.(\d+)\.(.*)", k):
            new = f"middle_block.{2 * int(m[1])}.{resnet(m[2])}"
        elif m := re.match(r"mid_block\.attentions\.0\.(.*)", k):
            new = f"middle_block.1.{m[1]}"
        elif m := re.match(r"controlnet_cond_embedding\.blocks\.(\d+)\.(.*)", k):
            new = f"input_hint_block.{2 * (int(m[1]) + 1)}.{m[2]}"
        else:
            raise KeyError(k)
        out["control_model." + new] = v.clone()
    return out


def test_fine_tuned_controlnet_file_loads_bit_for_bit(tmp_path):
    """The real loader (no fakes) reads an original-format ControlNet file, offline, with the
    architecture of a local diffusers folder: every weight equal to the model it came from."""
    from diffusers import ControlNetModel

    from freereg_lib.models.diffusion import TINY_CONTROLNET_EXTRA, TINY_UNET_CONFIG, load_real_diffusion

    torch.manual_seed(0)
    cn_cfg = {k: v for k, v in TINY_UNET_CONFIG.items() if k not in ("out_channels", "up_block_types", "sample_size")}
    ref = ControlNetModel(**cn_cfg, **TINY_CONTROLNET_EXTRA)
    folder = tmp_path / "control_v11f1p_sd15_depth"
    ref.save_pretrained(folder)
    ft = tmp_path / W.CONTROLNET_FT_FILE
    # As a training run saves it: a state_dict holding the ControlNet (and, here, a UNet key).
    ldm = _to_ldm_controlnet(ref.state_dict())
    ldm["model.diffusion_model.out.2.bias"] = torch.zeros(4)
    torch.save({"state_dict": ldm}, ft)
    import diffusers
    import transformers

    # Only the ControlNet is real here; SD's parts are not needed to check the file.
    stub = staticmethod(lambda *a, **k: torch.nn.Module())
    with pytest.MonkeyPatch.context() as mp:
        for cls in (diffusers.UNet2DConditionModel, diffusers.AutoencoderKL, transformers.CLIPTextModel,
                    transformers.CLIPTokenizer):
            mp.setattr(cls, "from_pretrained", stub)
        diff = load_real_diffusion("unused", str(ft), FreeRegConfig(), torch.device("cpu"), torch.float32,
                                   (64, 64), controlnet_config=str(folder))
        got = diff.controlnet.state_dict()
        assert set(got) == set(ref.state_dict())
        assert all(torch.equal(got[k], v) for k, v in ref.state_dict().items())
        # A file of another model is refused with the path in the message.
        torch.save({"state_dict": {"control_model.time_embed.0.weight": torch.zeros(1)}}, tmp_path / "bad.pth")
        with pytest.raises(ValueError, match="bad.pth"):
            load_real_diffusion("unused", str(tmp_path / "bad.pth"), FreeRegConfig(), torch.device("cpu"),
                                torch.float32, (64, 64), controlnet_config=str(folder))


def test_model_choices_key_the_feature_cache():
    from freereg_lib.commands.cache import feature_params

    base = feature_params(FreeRegConfig())
    for change in (dict(controlnet="x/control_v11f1p_sd15_depth_ft.pth"), dict(sd_unet_variant="ema"),
                   dict(dtype="float16")):
        assert feature_params(FreeRegConfig(**change)) != base


def test_table1_grid_offers_the_freereg_ft_job():
    grid = (ROOT / "freereg_lib" / "data" / "grids" / "table1.yaml").read_text()
    assert "control_v11f1p_sd15_depth_ft.pth" in grid and "FreeReg-Ft" in grid


# ---------------------------------------------------------------------------------------
# The weight check command, on the demo layout the loader tests write (tiny backend: it must
# run and print, not register).

def test_check_weights_runs_the_demo_with_the_tiny_backend(tmp_path, capsys):
    """The chain runs and prints, scored with the demo's truth files; random weights cannot
    register the demo, so the command exits 3 and says why."""
    from test_loaders import POSES, make_demo, render, write_depth

    from freereg_lib.commands.check_weights import main

    demo, _, K_dpt, _ = make_demo(tmp_path / "demo", rgb_size=(120, 160), dpt_size=(60, 80))
    write_depth(demo / "just_for_eval" / "target_dpt.gtd.png", render(K_dpt, POSES[1], (60, 80)))
    rc = main(["--demo", str(demo), "--backend", "tiny", "--device", "cpu", "--ransac-iters", "200",
               "--ddim-steps", "2"])
    captured = capsys.readouterr()
    out, err = captured.out, captured.err
    assert rc == 3, out + err
    assert "backend: tiny backend" in out and "dtype: float32" in out
    assert "random init (seed 0)" in out and "FPFH (Open3D): no weights" in out
    assert f"demo pair: {demo}" in out and "RANSAC iterations 200, DDIM steps 2" in out
    assert "Kabsch scoring 'official'" in out
    assert "scored with: depth side just_for_eval/target_dpt.gtd.png (dense truth)" in out
    header = next(ln for ln in out.splitlines() if ln.startswith("method"))
    for field in ("IR", "IN", "RE (deg)", "TE (m)", "registered at (20 deg, 0.5 m)", "evaluable"):
        assert field in header
    rows = [ln.split() for ln in out.splitlines() if ln.startswith("FreeReg ")]
    assert [r[1] for r in rows] == ["kabsch", "pnp"]
    for r in rows:
        assert int(r[2]) > 0  # features were extracted and matched (the chain ran)
        float(r[3]), float(r[5]), float(r[6])  # IR, RE, TE print as numbers (nan when failed)
        assert r[7] in ("yes", "no")
    assert rows[0][7] == "no"
    assert "a correct installation: FreeReg + kabsch registers the demo (RE < 20 deg and TE < 0.5 m)" in out
    assert "NOT REGISTERED: FreeReg + kabsch did not register the demo" in err
    assert "random weights, which cannot register it" in err


def test_check_weights_defaults_to_fcgf_on_the_real_backend():
    import inspect

    from freereg_lib.commands import check_weights

    src = inspect.getsource(check_weights.main)
    assert 'args.geometric or ("fcgf" if args.backend == "real" else "fpfh")' in src


def test_check_weights_prints_hashes_of_real_files(weights, fake_loaders, monkeypatch, tmp_path, capsys):
    """The real backend's report: every model's id, folder, variant, dtype and file SHA-256
    (the loaders are faked; the demo then fails to load and the command says so)."""
    import hashlib

    from freereg_lib.commands import check_weights

    (weights / "stable-diffusion-v1-5" / "vae").mkdir()
    (weights / "stable-diffusion-v1-5" / "vae" / "diffusion_pytorch_model.safetensors").write_bytes(b"vae")
    (weights / "zoedepth-nyu").mkdir()
    (weights / "zoedepth-nyu" / "config.json").write_text("{}")
    (weights / "zoedepth-nyu" / "model.safetensors").write_bytes(b"zoe")
    monkeypatch.setattr("freereg_lib.models.zoedepth.load_real_zoedepth", lambda path, device: object())
    # FCGF is checked too (the paper's geometric features, the default on the real backend).
    rc = check_weights.main(["--demo", str(tmp_path / "no_demo"), "--weights-dir", str(weights), "--device", "cpu"])
    out = capsys.readouterr()
    assert rc == 1 and "FCGF checkpoint not found" in out.err and "2019-08-19_06-17-41.pth" in out.err
    (weights / "fcgf").mkdir()
    (weights / "fcgf" / "2019-08-19_06-17-41.pth").write_bytes(b"fcgf")
    monkeypatch.setattr("freereg_lib.models.fcgf.load_fcgf", lambda path, *a, **k: object())
    rc = check_weights.main(["--demo", str(tmp_path / "no_demo"), "--weights-dir", str(weights), "--device", "cpu"])
    out = capsys.readouterr()
    assert rc == 1 and "FAILED to load the demo pair" in out.err
    text = out.out
    assert f"FCGF ResUNetBN2C: {weights / 'fcgf' / '2019-08-19_06-17-41.pth'}" in text
    assert hashlib.sha256(b"fcgf").hexdigest() in text
    assert "Stable Diffusion v1.5 UNet: stable-diffusion-v1-5/stable-diffusion-v1-5 at" in text
    assert "variant non_ema; dtype float32" in text
    assert f"{weights / 'stable-diffusion-v1-5' / UNET_NON_EMA}  sha256 {hashlib.sha256(b'non-ema').hexdigest()}" in text
    assert hashlib.sha256(b"vae").hexdigest() in text and hashlib.sha256(b"zoe").hexdigest() in text
    assert "depth ControlNet: lllyasviel/control_v11f1p_sd15_depth at" in text
    assert "ZoeDepth: Intel/zoedepth-nyu at" in text
