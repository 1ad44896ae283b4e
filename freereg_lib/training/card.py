"""The micro models' model card, written from what training and evaluation recorded.

    python -m freereg_lib.training.card [--weights freereg_lib/models/micro/weights]

Reads ``training.json`` (from ``train_diffusion --export``), ``eval.json`` (from
``evaluate --out``) and ``test_split.json`` / ``dev_split.json`` (from ``evaluate_split
--summarize --out``) in the weights folder and writes ``loss_curves.png`` and
``MODEL_CARD.md`` beside them, so every number in the card is one a run printed; the same for
the micro FCGF in ``fcgf/`` (``train_fcgf --export``, ``evaluate_fcgf --out``).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from freereg_lib.models.micro import diffusion as M

# Measured, not computed: the wall times `retrain` printed (README, "Retrain and re-measure").
RETRAIN_MEASURED = (
    "Retraining from scratch (`python -m freereg_lib.training.retrain`), measured on a 2-core AMD EPYC with"
    " nothing else running while the schedule still trained a ControlNet in every phase: rendering and"
    " phases 1-2 (rounds 2 and 4) in one run of 125.4 min (2026-12-03: rendering 17.0, phase 1 59.6,"
    " phase 2 48.8 min), phase 3 (round 5) as its own training run of 46.1 min the same day; 171.5 min in"
    " all. Since round 6 the schedule trains the ControlNet once, on the final UNet: the same steps of"
    " every stage (VAE 700, UNet 6,000, ControlNet 2,600), renders and encodes, moved, not timed end to end"
    " (round 6's 2,600 ControlNet steps took 35.3 min on the 2-core AMD EPYC of 2026-12-04)."
)


def plot_losses(training: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = training["stages"]
    fig, axes = plt.subplots(1, len(stages), figsize=(4.0 * len(stages), 3.0), dpi=100)
    for ax, (name, log) in zip(np.atleast_1d(axes), stages.items()):
        loss = np.asarray(log["loss"])
        k = max(1, len(loss) // 50)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.plot(np.arange(len(loss)) + 1, loss, color="0.8", lw=0.5, label="training (per step)")
        ax.plot(np.arange(len(smooth)) + k, smooth, color="C0", label=f"training ({k}-step mean)")
        if log["val"]:
            v = np.asarray(log["val"])
            ax.plot(v[:, 0], v[:, 1], "o-", color="C3", ms=3, label="validation rooms")
        ax.set_title(f"{name}: {log['steps']} steps, {log['seconds'] / 60:.0f} min")
        ax.set_xlabel("step")
        ax.set_ylabel("L1 + KL" if name == "vae" else "noise MSE")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _row(name: str, r: dict) -> str:
    return (f"| {name} | {r['IR']:.1f} [{r['IR_ci'][0]:.1f}, {r['IR_ci'][1]:.1f}] | "
            f"{r['FMR']:.1f} [{r['FMR_ci'][0]:.1f}, {r['FMR_ci'][1]:.1f}] | "
            f"{r['RR']:.1f} [{r['RR_ci'][0]:.1f}, {r['RR_ci'][1]:.1f}] |")


def _p_text(p: float) -> str:
    """A permutation p-value (:func:`.evaluate.paired_permutation_p`), as a bound when no
    permutation reached the observed difference."""
    from freereg_lib.training.evaluate import PERMUTATIONS

    return f"< {1 / PERMUTATIONS:.4f}" if p <= 1.0 / (PERMUTATIONS + 1) + 1e-12 else f"= {p:.4f}"


def _noise_seed(run: dict) -> int:
    """The diffusion features' noise seed of an ``evaluate`` result (the config's when unchanged)."""
    from freereg_lib.config import FreeRegConfig

    return run["config_changes"].get("seed", FreeRegConfig().seed)


def _swept(run: dict) -> dict:
    """The config fields an ``evaluate`` result changed, the noise seed left out."""
    return {k: v for k, v in run["config_changes"].items() if k != "seed"}


def _more_evaluations(folder: Path) -> list[str]:
    """Rows of the further held-out runs (``eval_*.json``: more pairs, other noise seeds)."""
    runs = [json.loads(f.read_text()) for f in sorted(folder.glob("eval_*.json"))]
    runs = [r for r in runs if "trained" in r and "random" in r]
    if not runs:
        return []
    lines = [
        "### More pairs and noise seeds",
        "",
        "The same comparison on more pairs of the development seed (`evaluate --pairs N --noise-seed S`; the",
        "first 30 of them are the development set; the noise seed sets the diffusion features' forward noise",
        "and DDIM draws, the pairs stay those of the seed):",
        "",
        "| pairs (seed) | noise seed | trained IR % | trained FMR % | trained RR % | random IR % | trained / random | p |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        t, rnd = r["trained"], r["random"]
        lines.append(
            f"| {t['n_pairs']} ({r['seed']}) | {_noise_seed(r)} | {t['IR']:.1f} [{t['IR_ci'][0]:.1f}, {t['IR_ci'][1]:.1f}] | "
            f"{t['FMR']:.1f} | {t['RR']:.1f} | {rnd['IR']:.1f} [{rnd['IR_ci'][0]:.1f}, {rnd['IR_ci'][1]:.1f}] | "
            f"{r['IR_ratio']:.2f}x | {_p_text(r['p_value'])} |")
    return lines + [""]


def _diagnoses(folder: Path) -> list[str]:
    """Rows of the FreeReg-D decompositions (``diagnose_*.json``, :mod:`.diagnose`)."""
    from freereg_lib.training.diagnose import COMPARISONS, VARIANTS

    runs = [json.loads(f.read_text()) for f in sorted(folder.glob("diagnose_*.json"))]
    if not runs:
        return []
    lines = [
        "### Where FreeReg-D loses its matches",
        "",
        "FreeReg-D's IR with the same image side, the depth side's decoder maps taken from (1) the",
        "pipeline (ControlNet-guided DDIM from the depth hint), (1b) the same with the hint made from the",
        "depth camera's full rendered frame instead of the sampled cloud's projection, (2) the same",
        "ControlNet + UNet feature pass on the forward-noised latent of the *true* image the depth camera",
        "would have seen, (2a) the same on that true image of the room re-coloured (every colour and",
        "texture drawn afresh from the world's prior: what a generator that knows the geometry exactly,",
        "but not the colours no depth map holds, could give), (3) the image side's own path (UNet alone)",
        "on the true image (`python -m freereg_lib.training.diagnose`; '-': a run made before the column",
        "existed):",
        "",
        "| pairs (seed) | noise seed | weights | (1) FreeReg-D IR % | (1b) hint from the full frame % | "
        "(2a) true image re-coloured, ControlNet pass % | (2) true image, ControlNet pass % | "
        "(3) true image, image path % | p (1) vs (1b) | p (1) vs (2) | p (1) vs (2a) | p (2a) vs (2) | "
        "p (2) vs (3) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        cells = [f"{r[v]['IR']:.1f} [{r[v]['IR_ci'][0]:.1f}, {r[v]['IR_ci'][1]:.1f}]" if v in r else "-"
                 for v in VARIANTS]
        ps = [_p_text(r[f"p_{a}_vs_{b}"]) if f"p_{a}_vs_{b}" in r else "-" for a, b in COMPARISONS]
        noise = r["noise_seed"] if r["noise_seed"] is not None else "default"
        lines.append(f"| {r['n_pairs']} ({r['seed']}) | {noise} | {r['weights']} | " + " | ".join(cells + ps) + " |")
    return lines + [""]


SWEEP_FOLDERS = ("t_hat", "guidance", "sampler", "controlnet_scale")


def _sweeps(folder: Path) -> list[str]:
    """Rows of the trained-only sweeps (``t_hat/``, ``guidance/``, ``sampler/``,
    ``controlnet_scale/``: ``evaluate --trained-only`` with one config field changed), each
    beside the default-config run of the same pairs, pair seed and noise seed (``eval.json``,
    ``eval_*.json``) with a paired p."""
    from freereg_lib.training.evaluate import paired_permutation_p

    baselines = {}
    for f in [folder / "eval.json", *sorted(folder.glob("eval_*.json"))]:
        if f.exists():
            r = json.loads(f.read_text())
            if "trained" in r and set(r["config_changes"]) <= {"seed"}:
                baselines[(r["trained"]["n_pairs"], r["seed"], _noise_seed(r))] = r["trained"]
    rows = []
    for sub in SWEEP_FOLDERS:
        runs = [json.loads(f.read_text()) for f in (folder / sub).glob("*.json")]
        runs.sort(key=lambda r: (r["trained"]["n_pairs"], _noise_seed(r), sorted(_swept(r).items())))
        for r in runs:
            t, noise = r["trained"], _noise_seed(r)
            base = baselines.get((t["n_pairs"], r["seed"], noise))
            if base is None:
                versus = "| - | no default-config run of these pairs |"
            else:
                versus = (f"| {base['IR']:.1f} | {_p_text(paired_permutation_p(t['IR_per_pair'], base['IR_per_pair']))} |")
            setting = ", ".join(f"{k} = {v:g}" for k, v in _swept(r).items())
            rows.append(f"| {setting} | {t['n_pairs']} ({r['seed']}) | {noise} | "
                        f"{t['IR']:.1f} [{t['IR_ci'][0]:.1f}, {t['IR_ci'][1]:.1f}] | {t['FMR']:.1f} | {t['RR']:.1f} " + versus)
    if not rows:
        return []
    return [
        "### Sweeps of one setting",
        "",
        "The trained weights with one config field changed (`evaluate --trained-only --t-hat T`, `--guidance-w W`,",
        "`--ddim-eta E`, `--ddim-steps N`, `--controlnet-scale S`), against the default config (the official",
        "t_hat 150, w 4, DDIM eta 1, 20 steps, ControlNet scale 1) on the same pairs and noise seed; p: paired",
        "permutation test on the per-pair IR:",
        "",
        "| setting | pairs (seed) | noise seed | IR % | FMR % | RR % | default config's IR % | p |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]


def _ci(s: dict) -> str:
    return f"{s['mean']:.1f} [{s['ci'][0]:.1f}, {s['ci'][1]:.1f}]"


def _split(path: Path, title: str) -> list[str]:
    """A split's table (``evaluate_split --summarize --out``): every method and solver on the same
    pairs and noise draws, and the fused-against-each-half tests; nothing when the file is absent."""
    if not path.exists():
        return []
    r = json.loads(path.read_text())
    what = ("test-only seeds, evaluated once with the committed models and never used for a choice"
            if r["split"] == "test" else "the pairs every choice of the micro models was made on")
    lines = [
        title,
        "",
        f"{r['n_pairs']} synthetic indoor pairs of the {r['split']} split (pair seeds {r['pair_seeds']}; {what}),",
        f"noise seed {r['noise_seed']} for every method, {r['backend']}; decoder layers "
        f"{', '.join(map(str, r['config']['layers']))}, w = {r['config']['fusion_w']:g} for the fused features,",
        f"{r['config']['ransac_iters']:,} RANSAC iterations; % with 95 % bootstrap intervals over pairs (IR is one set",
        "of matches per method, so it is the same for both solvers):",
        "",
        "| method | solver | IR % | FMR % | RR % |",
        "|---|---|---|---|---|",
    ]
    for key, v in r["results"].items():
        method, solver = key.rsplit(" ", 1)
        lines.append(f"| {method} | {'Kabsch' if solver == 'kabsch' else 'PnP'} | {_ci(v['IR'])} | {_ci(v['FMR'])} | "
                     f"{_ci(v['RR'])} |")
    lines += ["", "Paired permutation tests over pairs (fused against each half, Kabsch against PnP): " + "; ".join(
        f"{k} {t['diff']:+.1f} points (p {_p_text(t['p'])})" for k, t in r["tests"].items()) + ".",
        "The paper on 3DMatch (Table 1): FreeReg-D IR 39.6 %, FreeReg-G 31.4 %, FreeReg 47.0 %; FreeReg RR 63.8 %.",
        "", "Made by: " + "; ".join(f"`{c}`" for c in r["commands"]) + f" (`{path.name}`).", ""]
    return lines


def write_card(folder: Path = M.WEIGHTS_DIR) -> Path:
    training = json.loads((folder / "training.json").read_text())
    plot_losses(training, folder / "loss_curves.png")
    a = training["arguments"]
    st = training["stages"]
    size_mb = sum(f.stat().st_size for part in M.PARTS for f in (folder / part).glob("*.safetensors")) / 1e6
    lines = [
        "# Micro diffusion models: model card",
        "",
        "Miniature Stable Diffusion v1.5 + depth ControlNet, trained from scratch on this repository's",
        "synthetic indoor rooms by `python -m freereg_lib.training.train_diffusion` (architectures:",
        "`freereg_lib/models/micro/diffusion.py`; `python -m freereg_lib.training.retrain` reruns the whole schedule, the",
        "history below, from scratch). They let a CPU run FreeReg's diffusion branch with *learned*",
        "weights (`get_backend(\"micro\")`). They are not Stable Diffusion: a few million parameters, one",
        "synthetic world, two texts. Numbers measured with them are a miniature of the paper's experiment,",
        "not a reproduction of its values.",
        "",
        *_split(folder / "test_split.json", "## Test split (the headline numbers)"),
        "## Training",
        "",
        f"- Data (of the last run; the history below says which run saw how many): {a['scenes']} rooms x "
        f"{a['views_per_scene']} views rendered at 480 x 640, reduced to",
        "  128 x 192 by the official resize rule; rooms drawn from `numpy.random.default_rng((0xF3EE0001, k))`;",
        "  NumPy reads the integer 0xF3EE0001 + k * 2**32 as the same sequence, so evaluation refuses such",
        "  seeds (`synthetic.check_eval_seed`, tests/test_eval_seeds.py). The last "
        f"{training['validation_rooms']} rooms are held out for the validation losses.",
        "- Hints: made as the pipeline makes them at inference (the camera's depth back-projected,",
        "  subsampled to the synthetic cloud size, projected, densified with `fill_in_fast`, normalised",
        "  by the official 2nd / 85th-percentile rule), `freereg_lib/training/views.py`.",
        f"- Seed {a['seed']}, batch {a['batch']}, AdamW (weight decay 0.01), {a['warmup']}-step warm-up,",
        "  gradient norm clipped at 1, horizontal flips.",
        f"- VAE (`AutoencoderKL`, {training['parameters_millions']['vae']} M): {st['vae']['steps']} steps,"
        f" lr {a['lr_vae']:g}, L1 + KL (weight 1e-6 per summed pixel, SD's); scaling factor"
        f" {training['scaling_factor']:.4f} (1 / latent std, as SD's 0.18215).",
        f"- UNet (`UNet2DConditionModel`, {training['parameters_millions']['unet']} M): {st['unet']['steps']}"
        f" steps, lr {a['lr_unet']:g}, epsilon prediction, SD v1.5's schedule, the text replaced by the",
        "  negative prompt 10 % of the time.",
        f"- ControlNet (`ControlNetModel.from_unet`, {training['parameters_millions']['controlnet']} M):"
        f" {st['controlnet']['steps']} steps, lr {a['lr_controlnet']:g}, UNet frozen.",
        f"- Text encoder: `CLIPTextModel` ({training['parameters_millions']['text_encoder']} M), random and frozen,",
        "  character-level tokenizer.",
        f"- Time on the 2-core CPUs of the sessions that trained them (shared with other work while it ran): "
        f"{training['step_seconds'] / 60:.0f} min of training steps (VAE {st['vae']['seconds'] / 60:.0f}, UNet {st['unet']['seconds'] / 60:.0f}, "
        f"ControlNet {st['controlnet']['seconds'] / 60:.0f} min), plus rendering the views (1.4-2 rooms a second on 2 cores) and"
        " encoding the latents. `benchmarks/bench_micro_training.py` prices the whole schedule on the machine"
        " at hand (benchmarks/README.md). " + RETRAIN_MEASURED + " Weights: "
        f"{size_mb:.1f} MB of float16 safetensors.",
        *([f"- History: {training['history'].rstrip('.')}."] if training.get("history") else []),
        "",
        "![loss curves](loss_curves.png)",
        "",
        "Final validation losses: " + ", ".join(
            f"{k} {v['val'][-1][1]:.4f}" for k, v in st.items() if v["val"]) + ".",
        "",
    ]
    ev_path = folder / "eval.json"
    if ev_path.exists():
        ev = json.loads(ev_path.read_text())
        lines += [
            "## Development set: FreeReg-D against random weights",
            "",
            f"FreeReg-D (layers 0, 4, 6; PnP-RANSAC) on the {ev['trained']['n_pairs']} synthetic indoor pairs of the",
            f"development set (`sources.iter_pairs(\"synthetic_indoor\", {ev['trained']['n_pairs']}, seed={ev['seed']})`,",
            "noise seed 0: every training round, recipe and sweep below was judged on them, so they are not",
            "held out from those choices; the test split above is), "
            "trained weights against the same architecture with random weights;",
            "% with 95 % bootstrap intervals over pairs (`python -m freereg_lib.training.evaluate`). As in the",
            "official evaluation, depth-side keypoints are lifted with the depth frame's true depth",
            "(`Pair.depth_frame_gt`), so every match is scored; runs before commit 0b95832 lifted them with",
            "the projected cloud, which left about 80 % of the matches unevaluable (README).",
            "",
            "| weights | IR % | FMR % | RR % |",
            "|---|---|---|---|",
            _row("trained", ev["trained"]),
            _row("random", ev["random"]),
            "",
            f"Trained / random mean IR: {ev['IR_ratio']:.2f}x (paired permutation p {_p_text(ev['p_value'])}: "
            f"{'a significant' if ev['p_value'] < 0.05 else 'not a significant'} difference at the 5 % level"
            f" over {ev['trained']['n_pairs']} pairs).",
            "The paper's FreeReg-D on 3DMatch (Table 1): IR 39.6 %, FMR 91.9 %.",
            "",
        ]
    lines += _split(folder / "dev_split.json", "## Development set: the whole chain")
    lines += _more_evaluations(folder)
    lines += _sweeps(folder)
    lines += _diagnoses(folder)
    lines += [
        "## Limits",
        "",
        "- Indoor only; the backend refuses outdoor configurations.",
        "- The decoder layers are 4 x 6, 8 x 12 and 16 x 24 (the VAE halves twice, not three times).",
        "- The `micro` backend's monocular depth and FCGF have their own cards (`depth/`, `fcgf/`).",
        "",
    ]
    path = folder / "MODEL_CARD.md"
    path.write_text("\n".join(lines))
    return path


IMAGE_SIDE_TEXT = {
    "cloud": "the cloud's view from the image camera (projected, densified), the depth side's kind",
    "mix": "the image's depth or the cloud's view from the image camera, drawn per step",
}


def plot_fcgf_training(training: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loss = np.asarray(training["loss"])
    k = max(1, len(loss) // 25)
    smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
    fig, (a, b) = plt.subplots(1, 2, figsize=(8.0, 3.0), dpi=100)
    a.plot(np.arange(len(loss)) + 1, loss, color="0.8", lw=0.5, label="training (per step)")
    a.plot(np.arange(len(smooth)) + k, smooth, color="C0", label=f"training ({k}-step mean)")
    steps = [v[0] for v in training["val"]]
    a.plot(steps, [v[1]["loss"] for v in training["val"]], "o-", color="C3", ms=3, label="validation crops")
    a.set_xlabel("step")
    a.set_ylabel("hardest-contrastive loss")
    a.legend(fontsize=7)
    b.plot(steps, [100 * v[1]["hit_ratio"] for v in training["val"]], "o-", color="C2", ms=3)
    b.set_xlabel("step")
    b.set_ylabel("hit ratio at 10 cm (%)")
    b.set_title("validation crops")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _cell(s: dict) -> str:
    return f"{s['mean']:.1f} [{s['ci'][0]:.1f}, {s['ci'][1]:.1f}]"


def write_fcgf_card(folder: Path = M.WEIGHTS_DIR / "fcgf") -> Path:
    """``MODEL_CARD.md`` and ``training.png`` of the micro FCGF from its ``training.json`` and
    ``eval.json`` (:mod:`.train_fcgf`, :mod:`.evaluate_fcgf`)."""
    tr = json.loads((folder / "training.json").read_text())
    plot_fcgf_training(tr, folder / "training.png")
    a = tr["arguments"]
    size_mb = sum(f.stat().st_size for f in folder.glob("*.safetensors")) / 1e6
    last = tr["val"][-1][1]
    lines = [
        "# Micro FCGF: model card",
        "",
        "FCGF's ResUNetBN2C (Choy et al., ICCV 2019) at the paper's 3DMatch settings (conv1 kernel 7,",
        "32-d unit-norm features, 2.5 cm voxels), trained from scratch on this repository's synthetic rooms",
        "by `python -m freereg_lib.training.train_fcgf`. The network is `freereg_lib/models/fcgf.py`'s, and",
        "these weights load with `load_fcgf`, the official checkpoints' loader. The `micro` backend hands it",
        "to the pipeline when `cfg.geometric = \"fcgf\"`. It is not FCGF's 3DMatch model: one synthetic",
        "world, a few hundred steps.",
        "",
        "## Training",
        "",
        f"- Data: {a['pairs']} synthetic indoor pairs, `{tr['train_stream']}`, a seed sequence no integer",
        f"  evaluation seed reproduces; validation: {tr['validation_pairs']}. Per pair the two clouds the",
        "  pipeline gives FCGF: the image's true depth (range-limited, edge-filtered) back-projected, and",
        "  the densified depth view of the cloud back-projected, each in its own camera's frame; one point",
        f"  per 2.5 cm voxel (mean {tr['voxels_per_cloud_mean']} voxels a cloud).",
        *([f"- Image side: {IMAGE_SIDE_TEXT[a['image_side']]}."] if a.get("image_side", "depth") != "depth" else []),
        f"- Each step: a ball of {a['crop_radius']:g} m around a random overlapping point from both clouds,",
        ("  each rotated uniformly in SO(3)," if a.get("rotations") == "so3" else
         "  each in the frame the pipeline gives it (its own camera's),")
        + f" the image side scaled by U({1 - a['scale_aug']:g}, {1 + a['scale_aug']:g}),",
        "  re-voxelised, one sparse batch. FCGF's hardest-contrastive loss (thresholds 0.1 on the squared",
        "  positive distance and 1.4 on the negative one, 1024 positives within 1.5 voxels, 256",
        "  hardest-negative candidates a side).",
        f"- {tr['steps']} steps, AdamW lr {a['lr']:g} (weight decay 0.01, {a['warmup']}-step warm-up, gradient",
        f"  norm clipped at 1), seed {a['seed']}; {tr['parameters_millions']} M parameters,"
        f" {size_mb:.1f} MB of float16 safetensors.",
        f"- Time on this 2-core CPU (shared with other training while it ran): {tr['step_seconds'] / 60:.0f} min"
        " of steps, plus rendering the pairs.",
        f"- Last validation: loss {last['loss']:.3f}, hit ratio at 10 cm {100 * last['hit_ratio']:.1f} %"
        + (f" (on the same crops FPFH {100 * tr['val_baselines']['']['fpfh']:.1f} %, random features"
           f" {100 * tr['val_baselines']['']['chance']:.1f} %)." if tr.get("val_baselines") else "."),
        "",
        "![training](training.png)",
        "",
    ]
    ev_path = folder / "eval.json"
    if ev_path.exists():
        ev = json.loads(ev_path.read_text())
        fa = ev.get("features")
        if fa:
            lines += [
                "## Held-out quality: the features alone",
                "",
                f"{ev['n_pairs']} synthetic indoor pairs (`make_pairs({ev['n_pairs']}, \"indoor\", "
                f"seed={ev['seed']})`), the image side on its *true* depth so only the descriptors differ;",
                "the pipeline's keypoints, mutual nearest neighbours; % with 95 % bootstrap intervals over",
                "pairs (`python -m freereg_lib.training.evaluate_fcgf`). FMR: share of pairs with IR > 5 %.",
                "",
                "| features | IR at 10 cm | FMR at 10 cm | IR at 0.3 m | FMR at 0.3 m |",
                "|---|---|---|---|---|",
            ]
            for name in ("micro FCGF", "FPFH", "random FCGF"):
                r = fa[name]
                lines.append(f"| {name} | {_cell(r['IR@10cm'])} | {_cell(r['FMR@10cm'])} | "
                             f"{_cell(r['IR@0.3m'])} | {_cell(r['FMR@0.3m'])} |")
            lines += ["", f"Micro FCGF vs FPFH, IR at 10 cm: paired permutation p = {fa['p_fcgf_vs_fpfh']:.4f}.", ""]
        ch = ev.get("chain")
        if ch:
            lines += [
                "## Held-out quality: the chain",
                "",
                f"The same pairs end to end through the micro backend ({ch['micro (FCGF) label']}):",
                "",
                "| setup | variant | IR % | FMR % | RR % |",
                "|---|---|---|---|---|",
            ]
            for name in ("micro (FCGF)", "micro (FPFH)", "random weights (FCGF)"):
                for variant, r in ch[name].items():
                    lines.append(f"| {name} | {variant} | {_cell(r['IR'])} | {_cell(r['FMR'])} | {_cell(r['RR'])} |")
            from freereg_lib.training.evaluate_fcgf import VERDICT, ladder_order

            lo = ladder_order(ch["micro (FCGF)"])
            lines += [
                "",
                f"FreeReg-G (Kabsch) IR, trained / random weights: {ch['IR_ratio_trained_random']:.2f}x "
                f"(paired permutation p = {ch['p_trained_vs_random']:.4f}). The paper's FreeReg-G on 3DMatch"
                " (Table 1): IR 31.4 %, FMR 90.7 %, RR 50.4 %.",
                "",
            ]
            if lo.get("holds") is not None:
                lines += [
                    f"Table 9's ladder (fused FreeReg): at {lo['tight']} PnP {lo['pnp_tight']:.1f} % vs Kabsch "
                    f"{lo['kabsch_tight']:.1f} %; at {lo['loose']} PnP {lo['pnp_loose']:.1f} % vs Kabsch "
                    f"{lo['kabsch_loose']:.1f} %: the paper's ordering (PnP ahead at the tight rung, Kabsch at the"
                    f" loose one) {VERDICT[lo['holds']]}.",
                    "",
                ]
    lines += [
        "## Limits",
        "",
        "- Indoor only (2.5 cm voxels, rooms); KITTI's 30 cm model has no micro counterpart.",
        "- Trained on crops, not whole fragments: a 2-core CPU affords a few thousand voxels a step.",
        "",
    ]
    path = folder / "MODEL_CARD.md"
    path.write_text("\n".join(lines))
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--weights", default=str(M.WEIGHTS_DIR))
    args = p.parse_args(argv)
    folder = Path(args.weights)
    print(f"wrote {write_card(folder)}")
    if (folder / "fcgf" / "training.json").exists():
        print(f"wrote {write_fcgf_card(folder / 'fcgf')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
