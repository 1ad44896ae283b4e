"""Where FreeReg-D loses its matches: the modality gap against the generation.

    python -m freereg_lib.training.diagnose [--pairs 30] [--seed 2026] [--weights DIR]
        [--noise-seed S] [--random-weights] [--out diagnose.json]

The synthetic renderer can also shade the true image the depth camera would have seen
(``make_pair(..., depth_camera_image=True)``), which no real cloud has. On held-out indoor
pairs this runs FreeReg-D (layers 0, 4, 6; PCA; mutual nearest neighbours; IR at
``cfg.tau_c``) four times, with the same image side and keypoints, changing only the decoder
maps of the depth side:

- ``freereg_d``: as the pipeline computes them (ControlNet-guided DDIM from the depth hint,
  then the feature pass at t_hat);
- ``hint_from_frame``: the same, with the hint made from the depth camera's full rendered
  frame (``Pair.depth_frame_gt``, as 3DMatch's sensor depth is used) instead of the
  60,000-point cloud projected and densified: what the sampled cloud's holes cost the hint;
- ``appearance_redrawn``: the same feature pass (ControlNet with the same hint + UNet at t_hat)
  on the forward-noised latent of the true depth-camera image of the same room in another
  colouring: every colour, texture and texture scale drawn afresh from the world's prior
  (``make_pair(..., appearance_seed=...)``), the geometry and lighting kept. It is what an
  ideal depth-conditioned generator could give, one that knows the geometry exactly and
  every object's class from its shape but, as no depth map tells it, not its colours;
- ``generation_oracle``: the same feature pass on the *true* depth-camera image, as if the
  sampling had generated exactly the real image;
- ``same_modality``: the image side's own path (UNet alone) on that true image, i.e.
  image-to-image matching across the two viewpoints, with no modality gap at all.

``same_modality`` bounds what the UNet's features can match across views; the distance from
``generation_oracle`` down to ``freereg_d`` is what generating an image from depth costs (the
paper's Fig. 2-I point: a depth map admits many images), and ``appearance_redrawn`` splits it
into what no generator could recover (the colours) and what the micro ControlNet's samples
lose beyond that. The true-image passes draw their own forward noise, not the image side's.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from freereg_lib.training.evaluate import bootstrap_ci, paired_permutation_p
from freereg_lib.training.splits import guard_eval_seed
from freereg_lib.training.provenance import machine_record

VARIANTS = ("freereg_d", "hint_from_frame", "appearance_redrawn", "generation_oracle", "same_modality")
# The paired tests reported: the hint's cost, the generation's (split at the colours no depth
# map holds), the ControlNet pass's.
COMPARISONS = (("freereg_d", "hint_from_frame"), ("freereg_d", "generation_oracle"),
               ("freereg_d", "appearance_redrawn"), ("appearance_redrawn", "generation_oracle"),
               ("generation_oracle", "same_modality"))


def appearance_seed(seed: int | tuple[int, ...]) -> tuple[int, ...]:
    """The seed of the colouring :func:`render_with_depth_camera_images` redraws for the pair of
    ``seed``: one per pair, never the pair's own stream."""
    return (*np.atleast_1d(seed).tolist(), 0xC010)


def render_with_depth_camera_images(kind: str, seed, overlap=(0.3, 0.8), image_size=None):
    """``synthetic.make_pair(kind, seed, overlap, image_size, depth_camera_image=True)`` with,
    in ``meta["depth_camera_image_redrawn"]``, the depth camera's image of the same room in the
    colouring of :func:`appearance_seed` (``make_pair(..., appearance_seed=...)``)."""
    from freereg_lib.data import synthetic

    pair = synthetic.make_pair(kind, seed=seed, overlap=overlap, image_size=image_size, depth_camera_image=True)
    redrawn = synthetic.make_pair(kind, seed=seed, overlap=overlap, image_size=image_size,
                                  depth_camera_image=True, appearance_seed=appearance_seed(seed))
    pair.meta["depth_camera_image_redrawn"] = redrawn.meta["depth_camera_image"]
    return pair


def _synthetic_indoor_seed(pair):
    """``pair``'s synthetic seed, or a ValueError naming what a real or outdoor pair lacks."""
    meta = pair.meta
    if meta.get("dataset") != "synthetic" or "seed" not in meta:
        raise ValueError(f"pair {pair.name}: only a synthetic pair can be rendered again with its depth camera's "
                         "image or in another colouring; a real cloud has neither")
    if meta["kind"] != "indoor":
        raise ValueError(f"pair {pair.name}: only an indoor room's colours are drawn apart from its geometry; "
                         f"a {meta['kind']} pair has no colouring apart from its geometry")
    return meta["seed"]


def with_depth_camera_image(pair):
    """The synthetic indoor ``pair`` made again with its depth camera's true image and that
    image re-coloured (:func:`render_with_depth_camera_images`: the same pair otherwise)."""
    seed = _synthetic_indoor_seed(pair)
    return render_with_depth_camera_images("indoor", seed, pair.meta["overlap_range"], pair.image_size)


def recoloured(pair):
    """The synthetic indoor ``pair`` made again in the colouring of :func:`appearance_seed`:
    the same room, poses and cloud (notebook 01's Fig. 2-I shows its image beside the photo)."""
    from freereg_lib.data import synthetic

    seed = _synthetic_indoor_seed(pair)
    return synthetic.make_pair("indoor", seed=seed, overlap=pair.meta["overlap_range"], image_size=pair.image_size,
                               appearance_seed=appearance_seed(seed), world=pair.meta.get("world", "blocks"))


def depth_side_maps(pair, view, frame_view, backend, layers, maps=None) -> tuple[dict, dict[str, dict]]:
    """The image side's decoder maps and the depth side's under each of :data:`VARIANTS`,
    ``{layer: (C, h, w) float32}``; ``view`` is the pipeline's depth view of ``pair``,
    ``frame_view`` the one made from its full depth frame (:func:`frame_view`);
    ``pair.meta`` must hold the true depth-camera image and its re-coloured version
    (:func:`with_depth_camera_image`). ``maps``: the pipeline's own ``(image, depth)`` maps of
    the pair when the caller has them (they are FreeReg-D's; not computed again)."""
    from freereg_lib import pipeline

    image_b = pair.meta.get("depth_camera_image")
    redrawn = pair.meta.get("depth_camera_image_redrawn")
    if image_b is None or redrawn is None:
        raise ValueError(f"pair {pair.name} holds no depth-camera image and its re-coloured version; make it "
                         "with freereg_lib.training.diagnose.with_depth_camera_image")
    D = backend.diffusion
    maps_image, maps_depth = maps or pipeline.diffusion_maps_batch([pair], [view], backend, layers)[0]
    return maps_image, {
        "freereg_d": maps_depth,
        "hint_from_frame": D.depth_batch([frame_view.dense], layers)[0],
        "appearance_redrawn": D.depth_pass_on_images([redrawn], [view.dense], layers)[0],
        "generation_oracle": D.depth_pass_on_images([image_b], [view.dense], layers)[0],
        "same_modality": D.rgb_batch([image_b], layers, noise_tag="depth-camera-image")[0],
    }


def frame_view(pair, cfg):
    """The depth view the pipeline would make if ``pair``'s depth frame were its sensor depth
    (no projection of the sampled cloud; densified and normalised as the pipeline does)."""
    import dataclasses

    from freereg_lib import pipeline

    if pair.depth_frame_gt is None:
        raise ValueError(f"pair {pair.name} holds no full depth frame (depth_frame_gt); a synthetic pair "
                         "made by synthetic.make_pair has one")
    return pipeline.depth_view(dataclasses.replace(pair, sensor_depth=pair.depth_frame_gt), cfg)


def pair_inlier_ratios(pair, backend, cfg, maps=None) -> dict[str, float]:
    """FreeReg-D's IR (fraction) on ``pair`` under each of :data:`VARIANTS` (``maps``: see
    :func:`depth_side_maps`)."""
    from freereg_lib import pipeline
    from freereg_lib.geometry import metrics

    view = pipeline.depth_view(pair, cfg)
    maps_image, depth_maps = depth_side_maps(pair, view, frame_view(pair, cfg), backend, cfg.layers, maps)
    mono = backend.mono_depth(pair.image, depth_gt=pair.depth_gt)  # only lifts the image side
    out = {}
    for name, maps_depth in depth_maps.items():
        feats = pipeline.compute_features(pair, backend, cfg, geometric=False, view=view,
                                          maps=(maps_image, maps_depth), mono=mono)
        m = pipeline.match(feats, 1.0)
        out[name] = metrics.inlier_stats(*pipeline.correct_matches(pair, feats, m, cfg))[0]
    return out


def diagnose(n_pairs: int = 30, seed: int = 2026, weights_dir=None, random_weights: bool = False,
             noise_seed: int | None = None, progress: bool = True, **changes) -> dict:
    """Per-pair IRs and their means (%, 95 % bootstrap intervals) on the pairs
    :func:`freereg_lib.training.evaluate.evaluate` uses (``make_pairs(n_pairs, seed=seed)``), and
    the paired permutation p between neighbouring variants; ``changes`` override the config
    (e.g. ``ddim_steps``), as :func:`~freereg_lib.training.evaluate.evaluate`'s do."""
    from tqdm.auto import tqdm

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.models import get_backend

    if noise_seed is not None:
        changes = {**changes, "seed": int(noise_seed)}
    cfg = FreeRegConfig().override(**changes) if changes else FreeRegConfig()
    backend = get_backend("micro", cfg, device="cpu", weights_dir=weights_dir, random_weights=random_weights)
    seeds = [seed * 1_000_003 + k for k in range(n_pairs)]
    rows = []
    for s in tqdm(seeds, desc="diagnose", disable=not progress):
        pair = render_with_depth_camera_images("indoor", s)
        rows.append(pair_inlier_ratios(pair, backend, cfg))
    result = {"n_pairs": n_pairs, "seed": seed, "noise_seed": noise_seed, "config_changes": changes,
              "weights": "random" if random_weights else str(weights_dir or "committed")}
    for name in VARIANTS:
        v = np.array([r[name] for r in rows])
        lo, hi = bootstrap_ci(v)
        result[name] = {"IR": 100 * float(v.mean()), "IR_ci": [100 * lo, 100 * hi], "IR_per_pair": v.tolist()}
    for a, b in COMPARISONS:
        result[f"p_{a}_vs_{b}"] = paired_permutation_p(result[a]["IR_per_pair"], result[b]["IR_per_pair"])
    return result


LABELS = {
    "freereg_d": "FreeReg-D (depth side generated from the depth hint)",
    "hint_from_frame": "the same, the hint made from the full depth frame",
    "appearance_redrawn": "the same feature pass on the true image re-coloured",
    "generation_oracle": "the same feature pass on the true depth-camera image",
    "same_modality": "image side's path on the true depth-camera image",
}


SHORT_LABELS = {
    "freereg_d": "generated (FreeReg-D)",
    "hint_from_frame": "generated, hint from the full frame",
    "appearance_redrawn": "true image re-coloured, ControlNet pass",
    "generation_oracle": "true image, ControlNet pass",
    "same_modality": "true image, image path",
}


def report(result: dict) -> str:
    lines = [f"FreeReg-D IR on {result['n_pairs']} synthetic indoor pairs (seed {result['seed']}, "
             f"noise seed {result['noise_seed'] if result['noise_seed'] is not None else 'default'}, "
             f"{result['weights']} weights), the depth side's maps from:"]
    for name in VARIANTS:
        r = result[name]
        lines.append(f"  {LABELS[name]:55s} IR {r['IR']:5.1f} % [{r['IR_ci'][0]:.1f}, {r['IR_ci'][1]:.1f}]")
    hint = result["hint_from_frame"]["IR"] - result["freereg_d"]["IR"]
    gen = result["generation_oracle"]["IR"] - result["freereg_d"]["IR"]
    colour = result["generation_oracle"]["IR"] - result["appearance_redrawn"]["IR"]
    cn = result["same_modality"]["IR"] - result["generation_oracle"]["IR"]
    lines.append(f"  the cloud's projected hint instead of the full frame's: {-hint:+.1f} IR points "
                 f"(p = {result['p_freereg_d_vs_hint_from_frame']:.4f}); "
                 f"the generated image instead of the true one: {-gen:+.1f} IR points "
                 f"(p = {result['p_freereg_d_vs_generation_oracle']:.4f}), of which the colours no depth map "
                 f"holds: {-colour:+.1f} (p = {result['p_appearance_redrawn_vs_generation_oracle']:.4f}); "
                 f"the ControlNet feature pass instead of the image side's UNet pass on the true image: {-cn:+.1f} (p = "
                 f"{result['p_generation_oracle_vs_same_modality']:.4f})")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pairs", type=int, default=30)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--weights", default=None, help="micro weights folder (default: the committed ones)")
    p.add_argument("--noise-seed", type=int, default=None, help="the config's seed (the diffusion noise draws)")
    p.add_argument("--random-weights", action="store_true", help="the same architecture with random weights")
    p.add_argument("--out", default=None, help="write the result as JSON here")
    args = p.parse_args(argv)
    guard_eval_seed(args.seed, args.pairs)  # no pair may draw a training room
    from freereg_lib.training.command_inputs import weights_fault

    if args.weights and (fault := weights_fault(args.weights)):  # SHA256SUMS, whole files: before any pair
        p.error(f"--weights {args.weights}: {fault}")
    result = diagnose(args.pairs, args.seed, args.weights, args.random_weights, args.noise_seed)
    print(report(result))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({**result, "provenance": machine_record()}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
