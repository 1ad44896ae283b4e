"""The micro models: training steps lower the loss, training resumes exactly, the backend
loads the committed weights and runs the real feature code."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from freereg_lib.models.micro import diffusion as M  # noqa: E402
from freereg_lib.training import train_diffusion as T  # noqa: E402


def _views(n: int = 8, seed: int = 0, hw=(32, 32)) -> dict:
    """Smooth, structured stand-in views, much smaller than the real 128 x 192 ones to keep the
    test quick (every model is convolutional; 32 x 32 is an 8 x 8 latent, 1 x 1 at the UNet's
    bottom)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:hw[0], 0:hw[1]] / 16.0
    rgb, hint = [], []
    for _ in range(n):
        f = rng.uniform(0.5, 2.0, 3)
        img = np.stack([np.sin(f[c] * xx + c) * np.cos(f[c] * yy) for c in range(3)])
        rgb.append(((img + 1) * 127.5).astype(np.uint8))
        hint.append(np.repeat((255 * (yy / yy.max()))[None], 3, 0).astype(np.uint8))
    return {"rgb": np.stack(rgb), "hint": np.stack(hint), "depth": np.zeros((n, 120, 160), np.float32)}


def _views_args(folder) -> list[str]:
    np.savez(folder / "views.npz", n_scenes=2, views_per_scene=4, **_views())
    return ["--views", str(folder / "views.npz"), "--scenes", "2", "--views-per-scene", "4", "--threads", "1"]


@pytest.fixture
def views_args(tmp_path) -> list[str]:
    """The arguments every train_diffusion run of these tests shares: :func:`_views` saved as a
    two-scene views file, and one thread."""
    return _views_args(tmp_path)


@pytest.fixture(scope="module")
def first_export(tmp_path_factory):
    """One run of all three stages, two steps each (a checkpoint every two steps, one warm-up
    step), exported: the weights folder that the continued and restarted runs start from, and
    that run's ``training.json``. Run once for the module; the tests only read it."""
    tmp = tmp_path_factory.mktemp("first")
    T.main(_views_args(tmp) + ["--batch", "2", "--checkpoint-every", "2", "--warmup", "1", "--out", str(tmp / "a"),
                               "--steps-vae", "2", "--steps-unet", "2", "--steps-controlnet", "2",
                               "--export", str(tmp / "w")])
    return tmp / "w", json.loads((tmp / "w/training.json").read_text())


def _fit(module, loss_fn, steps: int, lr: float) -> list[float]:
    opt = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=lr)
    losses = []
    for _ in range(steps):
        loss = loss_fn()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


def test_each_stage_lowers_its_loss_on_a_fixed_batch():
    torch.manual_seed(0)
    models = M.build(seed=0)
    T.freeze(models["text_encoder"])
    data = T.Data(_views(), views_per_scene=4)
    args = T.parse_args(["--batch", "4", "--seed", "0"])
    idx, flips = np.arange(2), np.zeros(2, dtype=bool)
    n_pix = float(np.prod(data.rgb.shape[1:]))

    def vae_loss():
        g = torch.Generator().manual_seed(0)
        x = data.rgb[idx]
        post = models["vae"].encode(x).latent_dist
        z = post.mean + post.std * torch.randn(post.mean.shape, generator=g)
        return (models["vae"].decode(z).sample - x).abs().mean() + T.KL_WEIGHT / n_pix * post.kl().mean()

    losses = _fit(models["vae"], vae_loss, 6, 3e-3)
    assert losses[-1] < 0.8 * losses[0], losses

    T.freeze(models["vae"])
    latents = T.encode_latents(models["vae"], data.rgb)
    assert latents[0].shape == (2, 8, 4, 8, 8)  # plain and mirrored, a quarter-size latent
    T.set_scaling_factor(models["vae"], *latents)
    den = T.Denoising(models, data, latents, args)
    no_drop = np.zeros(2, dtype=bool)
    fixed = lambda cn: lambda: den.loss(idx, flips, torch.Generator().manual_seed(1), cn, no_drop)  # noqa: E731
    losses = _fit(models["unet"], fixed(False), 6, 3e-3)
    assert losses[-1] < 0.8 * losses[0], losses

    T.freeze(models["unet"])
    from diffusers import ControlNetModel

    den.controlnet = models["controlnet"] = ControlNetModel.from_unet(
        models["unet"], conditioning_embedding_out_channels=M.CONTROLNET_EMBEDDING)
    with torch.no_grad():
        before, without = fixed(True)().item(), fixed(False)().item()
    assert before == pytest.approx(without, rel=1e-5)  # zero convolutions: no effect yet
    losses = _fit(models["controlnet"], fixed(True), 6, 3e-3)
    assert losses[-1] < losses[0], losses


def test_a_resumed_stage_ends_where_an_uninterrupted_one_does(tmp_path, views_args):
    common = views_args + ["--stages", "vae", "--batch", "2", "--checkpoint-every", "2"]
    T.main(common + ["--out", str(tmp_path / "a"), "--steps-vae", "4"])
    T.main(common + ["--out", str(tmp_path / "b"), "--steps-vae", "2"])
    T.main(common + ["--out", str(tmp_path / "b"), "--steps-vae", "4"])  # resumes at step 2
    a = torch.load(tmp_path / "a/vae/checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "b/vae/checkpoint.pt", weights_only=False)
    assert a["step"] == b["step"] == 4
    assert a["log"]["loss"] == b["log"]["loss"]
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k


def test_lr_factor_warms_up_then_holds_or_decays_to_zero():
    assert [T.lr_factor(s, 6, 2) for s in range(6)] == [0.5, 1.0, 1.0, 1.0, 1.0, 1.0]
    cos = [T.lr_factor(s, 5, 2, "cosine") for s in range(5)]
    assert cos == pytest.approx([0.5 * 0.5 * (1 + np.cos(0)), 0.5 * (1 + np.cos(np.pi / 4)), 0.5,
                                 0.5 * (1 + np.cos(3 * np.pi / 4)), 0.0])
    assert T.lr_factor(9, 5, 2, "cosine") == 0.0  # past the run's end it stays at 0
    with pytest.raises(ValueError, match="expected 'constant' or 'cosine'"):
        T.lr_factor(0, 5, 2, "linear")


@pytest.mark.parametrize("schedule, last_lr", [("constant", 1e-3), ("cosine", 0.0)])
def test_a_stage_ends_at_its_schedules_learning_rate(tmp_path, schedule, last_lr, views_args):
    T.main(views_args + ["--stages", "vae", "--steps-vae", "3", "--batch", "2", "--warmup", "1",
                         "--lr-vae", "1e-3", "--lr-schedule", schedule, "--out", str(tmp_path / "o")])
    state = torch.load(tmp_path / "o/vae/checkpoint.pt", weights_only=False)
    assert state["optimizer"]["param_groups"][0]["lr"] == pytest.approx(last_lr, abs=1e-12)


def test_export_needs_every_stage(tmp_path, views_args):
    with pytest.raises(SystemExit, match="all three stages"):
        T.main(views_args + ["--stages", "vae", "--steps-vae", "1", "--batch", "2", "--out", str(tmp_path / "o"),
                             "--export", str(tmp_path / "w")])


def test_init_from_continues_one_stage_and_keeps_the_others(tmp_path, views_args, first_export):
    w, first = first_export
    first = first["stages"]
    common = views_args + ["--batch", "2", "--checkpoint-every", "2", "--warmup", "1"]
    T.main(common + ["--out", str(tmp_path / "b"), "--init-from", str(w), "--stages", "controlnet",
                     "--steps-controlnet", "4", "--export", str(tmp_path / "w2")])
    cont = json.loads((tmp_path / "w2/training.json").read_text())["stages"]
    assert cont["vae"] == first["vae"] and cont["unet"] == first["unet"]
    history = json.loads((tmp_path / "w2/training.json").read_text())["history"]
    assert "controlnet from step 2 to 4" in history, history
    assert len(cont["controlnet"]["loss"]) == 4 and cont["controlnet"]["steps"] == 4
    assert cont["controlnet"]["loss"][:2] == first["controlnet"]["loss"]
    assert [v[0] for v in cont["controlnet"]["val"]] == [2, 4]
    a, b = M.load(w), M.load(tmp_path / "w2")
    assert a["vae"].config.scaling_factor == b["vae"].config.scaling_factor
    for part in ("vae", "unet"):
        for (k, v), u in zip(a[part].state_dict().items(), b[part].state_dict().values()):
            assert torch.equal(v, u), (part, k)
    moved = [not torch.equal(v, w) for v, w in zip(a["controlnet"].state_dict().values(),
                                                  b["controlnet"].state_dict().values())]
    assert any(moved)


def test_restart_controlnet_rebuilds_it_from_the_folders_unet(tmp_path, views_args, first_export):
    w, first = first_export
    common = views_args + ["--batch", "2", "--checkpoint-every", "2", "--warmup", "1"]
    T.main(common + ["--out", str(tmp_path / "b"), "--init-from", str(w), "--stages", "controlnet",
                     "--restart-controlnet", "--steps-controlnet", "1", "--export", str(tmp_path / "w2")])
    again = json.loads((tmp_path / "w2/training.json").read_text())
    # Step 0 again, with zero convolutions: the loss is the UNet's on step 0's draws, as in the
    # first run (there the UNet was float32, here its float16 export).
    assert len(again["stages"]["controlnet"]["loss"]) == 1
    assert again["stages"]["controlnet"]["loss"][0] == pytest.approx(first["stages"]["controlnet"]["loss"][0], rel=1e-2)
    assert "controlnet rebuilt from this UNet (ControlNetModel.from_unet) and trained from step 0 to 1" in again["history"]
    with pytest.raises(SystemExit):
        T.parse_args(["--restart-controlnet", "--stages", "controlnet"])


def test_min_snr_weights_keep_the_noisy_steps_and_damp_the_clean_ones():
    w = T.min_snr_weight(torch.tensor([0.5, 5.0, 10.0, 50.0]), 5.0)
    assert w.tolist() == pytest.approx([1.0, 1.0, 0.5, 0.1])


def _denoising(args):
    torch.manual_seed(0)
    models = M.build(seed=0)
    T.freeze(models["text_encoder"])
    data = T.Data(_views(), views_per_scene=4)
    latents = T.encode_latents(T.freeze(models["vae"]), data.rgb)
    return T.Denoising(models, data, latents, T.parse_args(args))


def test_min_snr_loss_is_the_mse_with_weights_at_most_one():
    den = _denoising(["--batch", "4"])
    idx, flips, no = np.arange(4), np.zeros(4, dtype=bool), np.zeros(4, dtype=bool)

    def loss(seed, gamma):
        with torch.no_grad():
            return den.loss(idx, flips, torch.Generator().manual_seed(seed), False, no, gamma).item()

    def clean_steps(seed):
        """How many of the seed's four timesteps have SNR > 5 (drawn after the latent and noise draws)."""
        g = torch.Generator().manual_seed(seed)
        for _ in range(2):
            torch.randn((4, *den.mean.shape[2:]), generator=g)
        return int((den.snr[torch.randint(0, 1000, (4,), generator=g)] > 5).sum())

    counts = {seed: clean_steps(seed) for seed in range(40)}
    noisy, mixed = min(counts, key=counts.get), max(counts, key=counts.get)
    assert counts[noisy] == 0 and counts[mixed] > 0
    assert loss(noisy, 1e12) == pytest.approx(loss(noisy, None), rel=1e-6)
    assert loss(noisy, 5.0) == pytest.approx(loss(noisy, None), rel=1e-6)  # every weight 1
    assert loss(mixed, 5.0) < loss(mixed, None)  # the nearly clean steps damped


def test_a_bf16_autocast_unet_step_lowers_the_loss_on_a_fixed_batch():
    den = _denoising(["--batch", "4"])
    idx, flips, no = np.arange(2), np.zeros(2, dtype=bool), np.zeros(2, dtype=bool)

    def loss():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return den.loss(idx, flips, torch.Generator().manual_seed(1), False, no)

    assert loss().dtype == torch.float32  # mse_loss runs in float32 under autocast
    losses = _fit(den.unet, loss, 6, 3e-3)
    assert losses[-1] < 0.8 * losses[0], losses


def test_mixed_precision_changes_the_arithmetic_not_the_draws(tmp_path, views_args):
    common = views_args + ["--stages", "vae", "--steps-vae", "2", "--batch", "2"]
    T.main(common + ["--out", str(tmp_path / "f32")])
    T.main(common + ["--out", str(tmp_path / "bf16"), "--mixed-precision", "bf16"])
    a = torch.load(tmp_path / "f32/vae/checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "bf16/vae/checkpoint.pt", weights_only=False)
    assert a["log"]["loss"] != b["log"]["loss"]
    # the same crops and noise, rounded differently: the losses agree to bfloat16's precision
    assert b["log"]["loss"] == pytest.approx(a["log"]["loss"], rel=2e-2)
    assert all(v.dtype == torch.float32 for v in b["model"].values())  # float32 master weights


def test_restart_unet_trains_a_fresh_unet_on_the_folders_vae(tmp_path, views_args, first_export):
    w, first = first_export
    common = views_args + ["--batch", "2", "--checkpoint-every", "2", "--warmup", "1"]
    T.main(common + ["--out", str(tmp_path / "b"), "--init-from", str(w), "--stages", "unet",
                     "controlnet", "--restart-unet", "--restart-controlnet", "--steps-unet", "1",
                     "--steps-controlnet", "1", "--snr-gamma", "5", "--export", str(tmp_path / "w2")])
    again = json.loads((tmp_path / "w2/training.json").read_text())
    assert len(again["stages"]["unet"]["loss"]) == 1 and again["stages"]["vae"] == first["stages"]["vae"]
    # step 0 of the same seeded UNet on step 0's draws (the folder's VAE in float16 now; SNR weights <= 1)
    assert again["stages"]["unet"]["loss"][0] <= first["stages"]["unet"]["loss"][0] * 1.01
    assert "unet rebuilt (seeded random weights) and trained from step 0 to 1" in again["history"]
    assert "Min-SNR weighted, gamma 5" in again["history"]
    a, b = M.load(w), M.load(tmp_path / "w2")
    for v, u in zip(a["vae"].state_dict().values(), b["vae"].state_dict().values()):
        assert torch.equal(v, u)
    with pytest.raises(SystemExit):  # the folder's ControlNet belongs to the old UNet
        T.parse_args(["--init-from", "w", "--restart-unet", "--stages", "unet", "controlnet"])
    with pytest.raises(SystemExit):
        T.parse_args(["--snr-gamma", "0"])


# ---------------------------------------------------------------------------- backend

def test_micro_backend_loads_the_committed_weights_and_the_hint_acts():
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.models import get_backend

    assert not M.missing_parts(), "the committed micro weights are incomplete"
    training = json.loads((M.WEIGHTS_DIR / "training.json").read_text())
    assert set(training["stages"]) == {"vae", "unet", "controlnet"}
    cfg = FreeRegConfig().override(ddim_steps=5)  # 4 guided steps: a quick call
    backend = get_backend("micro", cfg, device="cpu")
    assert "trained" in backend.label
    yy = np.mgrid[0:120, 0:160][0]
    near, far = 1.0 + yy / 60.0, 4.0 - yy / 60.0
    a, b = (backend.diffusion_depth_batch([d], layers=(0, 4, 6))[0] for d in (near, far))
    for layer, (h, w) in zip((0, 4, 6), [backend.layer_shapes()[i] for i in (0, 4, 6)]):
        assert a[layer].shape[1:] == (h, w)
        assert not np.allclose(a[layer], b[layer])  # another hint, other features
    rgb = backend.diffusion_rgb_batch([np.full((120, 160, 3), 128, np.uint8)], layers=(6,))[0][6]
    assert rgb.shape[1:] == (16, 24) and np.isfinite(rgb).all()


def test_micro_backend_refuses_missing_weights_and_outdoor(tmp_path):
    from freereg_lib.config import FreeRegConfig, config_for
    from freereg_lib.models import MissingWeightsError, get_backend

    with pytest.raises(MissingWeightsError, match="training.retrain --export"):
        get_backend("micro", FreeRegConfig(), weights_dir=tmp_path)
    with pytest.raises(ValueError, match="indoor"):
        get_backend("micro", config_for("kitti"))


def test_diffusion_card_lists_further_evaluations_with_their_noise_seeds(tmp_path):
    from freereg_lib.training import card

    def run(n, noise, p):
        r = {"n_pairs": n, "IR": 8.5, "IR_ci": [5.8, 11.7], "FMR": 31.0, "FMR_ci": [22, 41], "RR": 4.0, "RR_ci": [1, 8]}
        changes = {} if noise is None else {"seed": noise}
        return {"seed": 2026, "config_changes": changes, "trained": r, "random": {**r, "IR": 2.1},
                "IR_ratio": 8.5 / 2.1, "p_value": p}

    assert card._more_evaluations(tmp_path) == []
    (tmp_path / "eval_100pairs_noise0.json").write_text(json.dumps(run(100, None, 1 / 20001)))
    (tmp_path / "eval_100pairs_noise1.json").write_text(json.dumps(run(100, 1, 0.039)))
    (tmp_path / "eval_sweep.json").write_text(json.dumps({"seed": 2026, "trained": {}}))  # no baseline: skipped
    rows = [line for line in card._more_evaluations(tmp_path) if line.startswith("| 100")]
    assert rows == [
        "| 100 (2026) | 0 | 8.5 [5.8, 11.7] | 31.0 | 4.0 | 2.1 [5.8, 11.7] | 4.05x | < 0.0001 |",
        "| 100 (2026) | 1 | 8.5 [5.8, 11.7] | 31.0 | 4.0 | 2.1 [5.8, 11.7] | 4.05x | = 0.0390 |",
    ]


def test_diffusion_card_puts_each_sweep_beside_the_default_run_of_its_pairs(tmp_path):
    from freereg_lib.training import card

    def trained(n, ir_per_pair):
        return {"n_pairs": n, "IR_per_pair": ir_per_pair, "IR": 100 * sum(ir_per_pair) / n, "IR_ci": [1.0, 2.0],
                "FMR": 50.0, "RR": 0.0}

    assert card._sweeps(tmp_path) == []
    base = {"seed": 2026, "config_changes": {}, "trained": trained(6, [0.1] * 6), "random": trained(6, [0.0] * 6)}
    (tmp_path / "eval.json").write_text(json.dumps(base))
    (tmp_path / "guidance").mkdir()
    (tmp_path / "guidance" / "w1.json").write_text(json.dumps(
        {"seed": 2026, "config_changes": {"guidance_w": 1.0}, "trained": trained(6, [0.2] * 6)}))
    (tmp_path / "guidance" / "w1_noise3.json").write_text(json.dumps(
        {"seed": 2026, "config_changes": {"guidance_w": 1.0, "seed": 3}, "trained": trained(6, [0.2] * 6)}))
    rows = [line for line in card._sweeps(tmp_path) if line.startswith("| guidance_w")]
    # Six equal positive differences: 2 of the 64 sign patterns reach them (p about 2 / 64).
    assert rows[0].startswith("| guidance_w = 1 | 6 (2026) | 0 | 20.0 [1.0, 2.0] | 50.0 | 0.0 | 10.0 | = 0.03")
    assert rows[1].endswith("| - | no default-config run of these pairs |")  # noise seed 3 has no baseline
