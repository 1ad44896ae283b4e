"""Backends: tiny diffusion path (layers, schedule, guidance, hooks), SD v1.5 shapes (Table 2),
tiny ZoeDepth, device handling, missing weights, and the pure helpers."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from freereg_lib.config import FreeRegConfig  # noqa: E402
from freereg_lib.models import (
    MissingWeightsError,
    depth_hint,
    depth_to_uint8,
    feature_timestep,
    get_backend,
    n_guided_steps,
    official_resize_hw,
)
from freereg_lib.models import weights as WTS  # noqa: E402
from freereg_lib.models.diffusion import SD15_UNET_CONFIG, DecoderTap, StopForward, guidance

TINY_HW = (128, 192)


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def tiny():
    return get_backend("tiny", FreeRegConfig(), device="cpu", resize_hw=TINY_HW)


@pytest.fixture(scope="module")
def tiny_small():
    return get_backend("tiny", FreeRegConfig(), device="cpu", resize_hw=(64, 128))


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(1)
    return (rng.random((60, 80, 3)) * 255).astype(np.uint8)


@pytest.fixture(scope="module")
def depth():
    v, u = np.mgrid[0:60, 0:80]
    d = 1.0 + 0.03 * u + 0.01 * v
    d[:5, :7] = 0.0
    return d


def expected_index(t_hat, steps):
    # The official rule, written out independently of the library.
    return round((1000 - t_hat) / (1000 / steps))


class CallCounter:
    """Wrap ``module.forward`` and record the timestep of every call."""

    def __init__(self, module):
        self.module = module
        self.orig = module.forward
        self.timesteps: list[int] = []

        def wrapped(sample, timestep, *a, **kw):
            self.timesteps.append(int(torch.as_tensor(timestep).reshape(-1)[0]))
            return self.orig(sample, timestep, *a, **kw)

        module.forward = wrapped

    def restore(self):
        del self.module.forward

    @property
    def n(self):
        return len(self.timesteps)


# ---------------------------------------------------------------------------------------
# Pure helpers.

def test_guidance_formula_on_known_tensors():
    c = torch.tensor([1.0, 2.0, -3.0])
    u = torch.tensor([0.5, -1.0, 1.0])
    out = guidance(c, u, 4.0)
    assert torch.allclose(out, torch.tensor([3.0, 14.0, -19.0]))
    # The official form eps_u + s (eps_c - eps_u) with s = w + 1.
    assert torch.allclose(out, u + 5.0 * (c - u))
    assert np.allclose(guidance(np.array([2.0]), np.array([2.0]), 7.0), [2.0])  # c == u -> c
    assert torch.equal(guidance(c, u, 0.0), c)  # w = 0: no guidance


def test_step_rule_and_feature_timestep():
    assert n_guided_steps(150, 20) == 17 == expected_index(150, 20)
    assert n_guided_steps(150, 5) == 4 == expected_index(150, 5)
    assert feature_timestep(150, 20) == 150
    assert feature_timestep(150, 5) == 200  # the official code forces (steps - index) * 1000/steps
    for steps in (1, 3, 10, 25, 50):
        assert n_guided_steps(150, steps) == expected_index(150, steps)


def test_official_resize_rule():
    assert official_resize_hw(480, 640) == (512, 704)
    assert official_resize_hw(225, 1242) == (512, 1280)  # KITTI, capped at 2.5 x
    assert official_resize_hw(968, 1296) == (512, 704)


def test_depth_hint_percentiles_over_all_pixels_holes_come_out_255():
    """The official normalisation on hand-made maps with holes (values computed by hand).

    4 x 5 map, 4 holes and 16 depths 1, 2, 3, 4 m (4 each): over ALL 20 pixels the 2nd
    percentile is 0 (a hole) and the 85th is 4, so x = 1 - d / 4: holes 255, 1 m -> 191.25 ->
    191, 2 m -> 127, 3 m -> 63, 4 m -> 0. (Over valid pixels only, the old rule, 1 m would be
    255, 2 m 170, holes 0.)"""
    d = np.array([[0, 1, 2, 3, 4],
                  [1, 0, 2, 3, 4],
                  [1, 2, 0, 3, 4],
                  [1, 2, 3, 0, 4]], dtype=np.float64)
    expect = np.array([[255, 191, 127, 63, 0],
                       [191, 255, 127, 63, 0],
                       [191, 127, 255, 63, 0],
                       [191, 127, 63, 255, 0]], dtype=np.uint8)
    got = depth_to_uint8(d)
    assert got.dtype == np.uint8 and np.array_equal(got, expect)
    # One hole among 20: sorted 0, 1, 2 x 15, 5 x 3; d2 = 0.38 * 1 = 0.38 (index 0.38),
    # d85 = 2 + 0.15 * (5 - 2) = 2.45 (index 16.15), span 2.07. The hole: x > 1 -> 255;
    # 1 m: 255 (1 - 0.62 / 2.07) = 178.6 -> 178; 2 m: 255 (1 - 1.62 / 2.07) = 55.4 -> 55; 5 m: 0.
    d = np.array([0.0, 1.0] + [2.0] * 15 + [5.0] * 3).reshape(4, 5)
    expect = np.array([255, 178] + [55] * 15 + [0] * 3, dtype=np.uint8).reshape(4, 5)
    assert np.array_equal(depth_to_uint8(d), expect)
    # The hint: 3 equal channels in [0, 1], the official resize, holes bright.
    hint = depth_hint(np.kron(d, np.ones((16, 16))), (64, 128))
    assert hint.shape == (3, 64, 128) and hint.dtype == np.float32
    assert np.array_equal(hint[0], hint[1]) and np.array_equal(hint[0], hint[2])
    assert hint[0, 0, 0] == 1.0 and 0.0 <= hint.min() and hint.max() <= 1.0


def test_depth_hint_flat_maps_give_no_nan():
    """d85 == d2: x = 1 where d <= d2, 0 above (the limit of the formula), never NaN."""
    assert np.array_equal(depth_to_uint8(np.zeros((3, 4))), np.full((3, 4), 255, np.uint8))
    assert np.array_equal(depth_to_uint8(np.full((3, 4), 2.5)), np.full((3, 4), 255, np.uint8))
    d = np.zeros((10, 10))
    d[0, :5] = 3.0  # 95 % holes: d2 = d85 = 0, the depths lie above
    got = depth_to_uint8(d)
    assert np.all(got[0, :5] == 0) and np.all(got[d == 0] == 255)
    d[1, 1] = np.nan  # non-finite depth is a hole
    assert depth_to_uint8(d)[1, 1] == 255


# ---------------------------------------------------------------------------------------
# Tiny diffusion.

def test_tiny_rgb_nine_layers_at_paper_strides(tiny, image):
    layers = tiny.diffusion_rgb(image)
    h, w = TINY_HW
    assert len(layers) == 9
    sizes = [tuple(x.shape[1:]) for x in layers]
    assert sizes == [(h // 64, w // 64)] * 3 + [(h // 32, w // 32)] * 3 + [(h // 16, w // 16)] * 3
    # Channels mirror SD v1.5's pattern (1280 x 7, 640 x 2) at the tiny widths (64, 32).
    assert [x.shape[0] for x in layers] == [64] * 7 + [32] * 2
    assert all(x.dtype == np.float32 and np.isfinite(x).all() for x in layers)
    again = tiny.diffusion_rgb(image)
    assert all(np.array_equal(a, b) for a, b in zip(layers, again))  # deterministic
    other = tiny.diffusion_rgb(255 - image)
    assert not np.allclose(layers[6], other[6])


def test_tiny_depth_call_count_at_paper_defaults(tiny_small, depth):
    diff = tiny_small.diffusion
    unet, cn = CallCounter(diff.unet), CallCounter(diff.controlnet)
    try:
        layers = tiny_small.diffusion_depth(depth)
    finally:
        unet.restore()
        cn.restore()
    n = expected_index(150, 20)
    assert n == 17
    assert unet.n == 2 * n + 1  # 17 guided steps x (cond + uncond) + 1 feature pass
    assert cn.n == 2 * n + 1  # the depth hint conditions both branches and the feature pass
    # DDIM timesteps 951, 901, ..., 151 (each twice), then the feature pass at t_hat = 150.
    guided = sorted(set(unet.timesteps[:-1]), reverse=True)
    assert guided == [951 - 50 * i for i in range(n)]
    assert unet.timesteps[-1] == 150
    assert [tuple(x.shape[1:]) for x in layers][::3] == [(1, 2), (2, 4), (4, 8)]


def test_tiny_depth_fewer_steps_fewer_calls(depth):
    cfg = FreeRegConfig().override(ddim_steps=5)
    be = get_backend("tiny", cfg, device="cpu", resize_hw=(64, 128))
    diff = be.diffusion
    unet = CallCounter(diff.unet)
    try:
        layers = be.diffusion_depth(depth)
    finally:
        unet.restore()
    n = expected_index(cfg.t_hat, 5)
    assert n == 4
    assert unet.n == 2 * n + 1 == 9
    assert unet.timesteps[-1] == 200
    assert [tuple(x.shape[1:]) for x in layers][::3] == [(1, 2), (2, 4), (4, 8)]


def test_text_embeddings_computed_once(tiny, image):
    diff = tiny.diffusion
    calls = []
    orig = diff.text_encoder.forward

    def wrapped(*a, **kw):
        calls.append(1)
        return orig(*a, **kw)

    diff._text_cache.clear()
    diff.text_encoder.forward = wrapped
    try:
        tiny.diffusion_rgb(image)
        tiny.diffusion_rgb(image)
        cond, uncond = diff.text_embeddings()
    finally:
        del diff.text_encoder.forward
    assert len(calls) == 2  # the conditional and the negative prompt, once each
    assert diff.cond_text == FreeRegConfig().prompt + ", best quality"
    assert cond.shape == uncond.shape == (1, 77, 32)


def test_depth_hint_changes_features(depth):
    cfg = FreeRegConfig().override(ddim_steps=2)
    be = get_backend("tiny", cfg, device="cpu", resize_hw=(64, 128))
    a = be.diffusion_depth(depth)
    b = be.diffusion_depth(depth[:, ::-1].copy())
    c = be.diffusion_depth(depth)
    assert all(np.array_equal(x, y) for x, y in zip(a, c))
    assert not np.allclose(a[0], b[0])


def test_layer0_includes_controlnet_mid_residual(tiny_small):
    """Layer 0 is the INPUT of up_blocks[0]: the mid-block output plus ControlNet's residual."""
    diff = tiny_small.diffusion
    unet = diff.unet
    z = torch.randn(1, 4, 8, 16, generator=torch.Generator().manual_seed(0))
    emb = torch.randn(1, 77, 32, generator=torch.Generator().manual_seed(1))
    t = torch.tensor([150])
    with torch.no_grad():
        down, mid = diff.controlnet(z, t, encoder_hidden_states=emb,
                                    controlnet_cond=torch.rand(1, 3, 64, 128), return_dict=False)
    store = {}
    hooks = [
        unet.mid_block.register_forward_hook(lambda m, a, o: store.__setitem__("mid", o)),
        unet.up_blocks[1].register_forward_hook(lambda m, a, o: store.__setitem__("up1", o)),
        unet.up_blocks[2].attentions[1].register_forward_hook(
            lambda m, a, o: store.__setitem__("up2a1", o[0])),
    ]
    try:
        with torch.no_grad(), DecoderTap(unet) as tap:
            try:
                unet(z, t, encoder_hidden_states=emb, down_block_additional_residuals=down,
                     mid_block_additional_residual=mid)
            except StopForward:
                pass
    finally:
        for h in hooks:
            h.remove()
    layers = tap.layers()[0]  # the one batch item
    assert mid.abs().max() > 0
    assert np.allclose(layers[0], (store["mid"] + mid)[0].numpy(), atol=1e-6)
    assert not np.allclose(layers[0], store["mid"][0].numpy())
    assert np.allclose(layers[6], store["up1"][0].numpy())
    assert np.allclose(layers[8], store["up2a1"][0].numpy())


def test_sd15_full_config_layer_shapes_table2():
    """Table 2 with the full SD v1.5 UNet + depth ControlNet configs (meta device: shapes
    only, no memory, no weights)."""
    from diffusers import ControlNetModel, UNet2DConditionModel

    with torch.device("meta"):
        unet = UNet2DConditionModel(**SD15_UNET_CONFIG)
        cn_cfg = {k: v for k, v in SD15_UNET_CONFIG.items()
                  if k not in ("out_channels", "up_block_types", "sample_size")}
        cn = ControlNetModel(**cn_cfg)
    assert sum(p.numel() for p in unet.parameters()) == 859_520_964  # SD v1.5's UNet
    for (H, W) in [(512, 704), (512, 1280)]:
        z = torch.empty(1, 4, H // 8, W // 8, device="meta")
        emb = torch.empty(1, 77, 768, device="meta")
        hint = torch.empty(1, 3, H, W, device="meta")
        t = torch.tensor([150], device="meta")
        with torch.no_grad():
            down, mid = cn(z, t, encoder_hidden_states=emb, controlnet_cond=hint,
                           return_dict=False)
            with DecoderTap(unet) as tap:
                try:
                    unet(z, t, encoder_hidden_states=emb, down_block_additional_residuals=down,
                         mid_block_additional_residual=mid)
                except StopForward:
                    pass
        shapes = [tuple(tap.maps[i].shape[1:]) for i in range(9)]
        a, b, c = (H // 64, W // 64), (H // 32, W // 32), (H // 16, W // 16)
        assert shapes == [(1280, *a)] * 3 + [(1280, *b)] * 3 + [(1280, *c)] + [(640, *c)] * 2
        assert len(down) == 12  # + the mid residual = the 13 ControlNet residuals
    # 512 x 704: 1280x8x11, 1280x16x22, 1280x32x44, 640x32x44 as in the paper.


# ---------------------------------------------------------------------------------------
# ZoeDepth, devices, weights.

def test_tiny_zoedepth_returns_input_size(tiny, image):
    rng = np.random.default_rng(3)
    for H, W in [(48, 64), (75, 50)]:
        img = (rng.random((H, W, 3)) * 255).astype(np.uint8)
        d = tiny.mono_depth(img)
        assert d.shape == (H, W) and d.dtype == np.float64
        assert np.isfinite(d).all() and (d >= 0).all() and d.max() > 0
        assert d.std() > 1e-4  # a depth map, not one constant
    # It depends on the image (a random-init ZoeDepth can collapse to a constant).
    assert np.abs(tiny.mono_depth(image) - tiny.mono_depth(255 - image)).max() > 1e-3


def test_cuda_request_without_cuda_is_a_clear_error():
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    with pytest.raises(RuntimeError, match="CUDA is not available"):
        get_backend("tiny", FreeRegConfig(), device="cuda")


def test_device_defaults():
    from freereg_lib.models.torch_backends import resolve_device

    dev, dt = resolve_device("cpu")
    assert dev.type == "cpu" and dt == torch.float32
    if torch.cuda.is_available():
        dev, dt = resolve_device(None)
        assert dev.type == "cuda" and dt == torch.float32  # the official precision, on CUDA too


def test_unknown_backend_name():
    with pytest.raises(ValueError, match="unknown backend"):
        get_backend("nope", FreeRegConfig())


@pytest.fixture()
def empty_hf_cache(tmp_path, monkeypatch):
    import huggingface_hub.constants as C

    monkeypatch.setattr(C, "HF_HUB_CACHE", str(tmp_path / "hf_cache"))
    monkeypatch.delenv("FREEREG_WEIGHTS", raising=False)
    return tmp_path


def test_missing_weights_message(empty_hf_cache):
    wdir = empty_hf_cache / "weights"
    wdir.mkdir()
    with pytest.raises(MissingWeightsError) as info:
        get_backend("real", FreeRegConfig(), device="cpu", weights_dir=str(wdir))
    msg = str(info.value)
    for mid in (WTS.SD15_ID, WTS.CONTROLNET_DEPTH_ID, WTS.ZOEDEPTH_INDOOR_ID):
        assert mid in msg
        assert f"huggingface-cli download {mid}" in msg
    assert str(wdir) in msg and "hf_cache" in msg
    assert 'backend="stub"' in msg
    assert set(info.value.model_ids) == {WTS.SD15_ID, WTS.CONTROLNET_DEPTH_ID,
                                         WTS.ZOEDEPTH_INDOOR_ID}
    assert isinstance(info.value, FileNotFoundError)


def test_missing_weights_outdoor_and_partial(empty_hf_cache):
    from freereg_lib.config import config_for

    wdir = empty_hf_cache / "weights"
    (wdir / "zoedepth-nyu-kitti").mkdir(parents=True)
    (wdir / "zoedepth-nyu-kitti" / "config.json").write_text("{}")
    # Only ZoeDepth is needed and present: no error at construction.
    be = get_backend("real", config_for("kitti"), device="cpu", weights_dir=str(wdir),
                     load=("mono",))
    assert be.paths["zoe"] == str(wdir / "zoedepth-nyu-kitti")
    with pytest.raises(MissingWeightsError) as info:
        get_backend("real", config_for("kitti"), device="cpu", weights_dir=str(wdir))
    assert WTS.ZOEDEPTH_OUTDOOR_ID not in info.value.model_ids
    assert WTS.CONTROLNET_DEPTH_ID in info.value.model_ids
    # A broken folder fails on loading with the same error class.
    with pytest.raises(MissingWeightsError, match="Loading failed"):
        be.mono_depth(np.zeros((8, 8, 3), np.uint8))


def test_batched_guidance_same_features_half_the_calls(depth):
    results, calls = {}, {}
    for batched in (False, True):
        cfg = FreeRegConfig().override(ddim_steps=5, batched_guidance=batched)
        be = get_backend("tiny", cfg, device="cpu", resize_hw=(64, 128))
        unet = CallCounter(be.diffusion.unet)
        try:
            results[batched] = be.diffusion_depth(depth)
        finally:
            unet.restore()
        calls[batched] = unet.n
    assert calls[False] == 9 and calls[True] == 5  # 4 guided steps x 2 (or x 1 batched) + 1
    for a, b in zip(results[False], results[True]):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4)


def test_controlnet_scale_weights_the_hint_and_zero_silences_it(depth):
    other = np.flipud(depth).copy()
    feats = {}
    for scale in (1.0, 0.0, 2.0):  # 1: the official weight
        cfg = FreeRegConfig().override(ddim_steps=5, controlnet_scale=scale)
        be = get_backend("tiny", cfg, device="cpu", resize_hw=(64, 128))
        feats[scale] = [be.diffusion_depth(d) for d in (depth, other)]
    official, silent, doubled = feats[1.0], feats[0.0], feats[2.0]
    assert not np.allclose(official[0][0], official[1][0])  # the hint steers the features
    for a, b in zip(*silent):  # scale 0: the ControlNet adds nothing, so any hint gives the same features
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(doubled[0][0], official[0][0])
    assert not np.allclose(silent[0][0], official[0][0])
