"""Other vision backbones reading the depth map as an image: the paper's Table 6 path, and its rerun.

The paper's appendix (Table 6, other vision foundation backbones) projects the point cloud into a
depth map, repeats it to three channels, runs an RGB-trained backbone (Dino-v2, CLIP, ...) on that
depth-as-RGB image and on the input RGB image, matches the two feature maps as FreeReg does (mutual
nearest neighbours) and solves the pose. This module owns:

* :func:`depth_as_rgb`: the depth-as-RGB image, ``(H, W, 3) uint8``;
* :class:`VisionBackbone` / :func:`load_backbone`: a DINOv2 or CLIP vision model (``transformers``'
  ``Dinov2Model``, ``CLIPVisionModel``) as a feature extractor, ``(H, W, 3)`` image in,
  ``(C, h, w)`` map of its patch tokens out; ``backend="real"`` reads pretrained weights from a
  weights folder (:mod:`freereg_lib.models.weights`' rules), ``backend="tiny"`` builds a small
  random model (2 layers) for tests;
* :func:`backbone_features`: a backbone's maps of a pair turned into
  :class:`~freereg_lib.pipeline.PairFeatures` by the pipeline's own code
  (:func:`~freereg_lib.pipeline.compute_features` given the maps: joint PCA, sampling at the
  keypoint grid), so matching and solving are FreeReg's (:func:`~freereg_lib.pipeline.variant_rows`);
* :func:`standin_maps`: on a CPU the stand-in backbone, the micro diffusion UNet's RGB branch on the
  depth-as-RGB image, the path of notebook 01's "SD (depth map fed as image)" row (Table 7's SD
  row): an RGB-trained backbone reading the depth map as an image, the idea of Table 6;
* the evaluation on the micro models' test split (:func:`pair_rows`, :func:`run`,
  :func:`summarize`), a command like :mod:`.evaluate_mono`:

    python -m freereg_lib.training.other_backbones --split test --pairs 100 --rows runs/micro/other_backbones/rows.jsonl
    python -m freereg_lib.training.other_backbones --split test --summarize --rows runs/micro/other_backbones/rows.jsonl
        --out freereg_lib/models/micro/weights/other_backbones_test.json

Per pair (the test split's pairs, noise seed 0, the config's defaults, as :mod:`.evaluate_split`)
the micro backend's RGB and depth-branch maps, monocular depth and FPFH features are computed once;
the rows (:data:`ROWS`) differ only in the depth side's diffusion map and the fusion weight, each
with Kabsch- and PnP-RANSAC. ``standin`` gives the depth-as-RGB image forward noise of its own
(``noise_tag`` :data:`NOISE_TAG`; the image and the depth map of a pair otherwise share a
pixel-aligned draw, which matches pixels by their noise, not their content); ``standin_shared``
keeps the shared draw, as notebook 01's row (``backend.diffusion_rgb``) does. ``--summarize``
writes FMR, IR, RR (%, 95 % bootstrap intervals over pairs), IN, and paired permutation tests of the
stand-in against FreeReg-D and fused FreeReg; :func:`freereg_lib.training.verdicts_appendix.table6`
reads the verdict from it.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freereg_lib.models.base import MissingWeightsError, depth_to_uint8, on_cpu_threads, resize_to
from freereg_lib.training.evaluate_split import (
    _done, _plain, _stat, load_average_range, paired_difference, result_lines, split_command,
)
from freereg_lib.training.splits import SPLITS

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)  # DINOv2's preprocessor
OPENAI_CLIP_MEAN, OPENAI_CLIP_STD = (0.48145466, 0.4578275, 0.40821073), (0.26862954, 0.26130258, 0.27577711)


@dataclass(frozen=True)
class Spec:
    """A backbone kind: its Hugging Face id, patch size, default input short side and normalisation."""

    label: str
    model_id: str
    patch: int
    short_side: int     # the resized input's short side in pixels (rounded to whole patches)
    mean: tuple
    std: tuple
    tiny: dict          # the config of the random model for tests


BACKBONES = {
    "dinov2": Spec("DINOv2", "facebook/dinov2-base", 14, 448, IMAGENET_MEAN, IMAGENET_STD,
                   dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64,
                        patch_size=14, image_size=56)),
    "clip": Spec("CLIP", "openai/clip-vit-base-patch16", 16, 224, OPENAI_CLIP_MEAN, OPENAI_CLIP_STD,
                 dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64,
                      patch_size=16, image_size=64)),
}
TINY_SHORT_SIDE = {"dinov2": 56, "clip": 64}


def depth_as_rgb(depth: np.ndarray) -> np.ndarray:
    """The depth map ``(H, W)`` float (metres, 0 = no depth) as an image ``(H, W, 3) uint8``.

    The paper says only that the depth map is "expanded to three channels"; its values must reach
    0..255 somehow. This uses :func:`freereg_lib.models.depth_to_uint8`, the official normalisation of
    FreeReg's depth side (the ControlNet hint: the 2nd and 85th percentiles of the map mapped to
    255 and 0, near = bright, clipped), also used by notebook 01's "SD (depth map fed as image)" row:
    every backbone that reads a depth map here sees the same image, and a per-map stretch keeps the
    picture's contrast whatever the room's depth range, as a photo's exposure does. The grey level is
    repeated to the three channels.
    """
    return np.repeat(depth_to_uint8(depth)[:, :, None], 3, axis=2)


def input_hw(image_hw: tuple[int, int], patch: int, short_side: int) -> tuple[int, int]:
    """The ``(h, w)`` pixels an ``image_hw = (H, W)`` image is resized to: the short side near
    ``short_side``, both sides whole patches (at least one), the aspect kept up to a patch's
    rounding. The whole image is resized, never cropped, so the patch grid covers it."""
    H, W = int(image_hw[0]), int(image_hw[1])
    s = short_side / min(H, W)
    return max(1, round(H * s / patch)) * patch, max(1, round(W * s / patch)) * patch


class VisionBackbone:
    """A ViT feature extractor: :meth:`feature_map` of an image is its last layer's patch tokens
    (the CLS token dropped), or those of hidden layer ``layer`` (0: the patch embeddings).

    Built by :func:`load_backbone`. ``kind``: ``"dinov2"`` | ``"clip"``; ``short_side``: the
    resized input's short side; ``cfg``: a :class:`~freereg_lib.config.FreeRegConfig` (its
    ``cpu_threads`` bounds torch's threads on the CPU, as every backend's).
    """

    def __init__(self, kind: str, model, cfg, device: str, backend: str, short_side: int,
                 mean=None, std=None, layer: int | None = None):
        self.kind, self.spec, self.model, self.cfg = kind, BACKBONES[kind], model, cfg
        self.device, self.backend, self.short_side, self.layer = device, backend, int(short_side), layer
        self.mean = tuple(mean or self.spec.mean)
        self.std = tuple(std or self.spec.std)
        self.label = f"{self.spec.label} ({backend}{'' if layer is None else f', hidden layer {layer}'})"

    def grid(self, image_hw: tuple[int, int]) -> tuple[int, int]:
        """``(h, w)`` of the feature map of an ``image_hw`` image: the patch grid of :func:`input_hw`."""
        h, w = input_hw(image_hw, self.spec.patch, self.short_side)
        return h // self.spec.patch, w // self.spec.patch

    @on_cpu_threads
    def feature_map(self, image: np.ndarray) -> np.ndarray:
        """``(C, h, w) float32`` patch features of ``image (H, W, 3)`` (uint8 0..255, or float
        0..1): the image resized whole to :func:`input_hw` (no crop), normalised with the
        model's mean and std, the tokens of the patch grid ``(h, w) = self.grid((H, W))``.
        Patch ``(i, j)`` covers the image's rows ``i H / h .. (i + 1) H / h`` and columns likewise."""
        import torch

        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) image, got shape {img.shape}")
        x = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
        hp, wp = input_hw(img.shape[:2], self.spec.patch, self.short_side)
        x = (resize_to(x, (hp, wp)) - np.float32(self.mean)) / np.float32(self.std)
        px = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)[None])).to(self.device)
        extra = {"interpolate_pos_encoding": True} if self.kind == "clip" else {}
        with torch.inference_mode():
            out = self.model(pixel_values=px, output_hidden_states=self.layer is not None, **extra)
        tokens = out.last_hidden_state if self.layer is None else out.hidden_states[self.layer]
        h, w = hp // self.spec.patch, wp // self.spec.patch
        tokens = tokens[0, -h * w:]  # the patch tokens follow the CLS token
        return tokens.float().cpu().numpy().T.reshape(-1, h, w).astype(np.float32)

    __call__ = feature_map

    def __repr__(self) -> str:
        return f"VisionBackbone({self.label})"


def _read_norm(path: Path) -> tuple:
    """``(mean, std)`` of a weights folder's ``preprocessor_config.json`` (None where absent)."""
    f = path / "preprocessor_config.json"
    if not f.is_file():
        return None, None
    d = json.loads(f.read_text())
    return d.get("image_mean"), d.get("image_std")


def load_backbone(kind: str, backend: str = "real", cfg=None, weights_dir=None, device: str | None = "cpu",
                  short_side: int | None = None, layer: int | None = None) -> VisionBackbone:
    """A :class:`VisionBackbone` of ``kind`` (``"dinov2"``, ``"clip"``).

    ``backend="real"``: ``from_pretrained`` of the folder :func:`freereg_lib.models.weights.try_resolve`
    finds for the kind's model id (``<weights_dir>/<name>`` or ``<weights_dir>/<owner>/<name>``,
    ``weights_dir`` else ``cfg.extra["weights_dir"]`` else ``$FREEREG_WEIGHTS``, then the Hugging
    Face cache, offline); a :class:`~freereg_lib.models.MissingWeightsError` of one line when none
    holds it. Its normalisation is the folder's ``preprocessor_config.json`` (else the kind's).
    ``backend="tiny"``: a seeded random model (2 layers, hidden size 32; numbers mean nothing)."""
    import torch
    from transformers import CLIPVisionConfig, CLIPVisionModel, Dinov2Config, Dinov2Model

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.models import weights as W

    if kind not in BACKBONES:
        raise ValueError(f"unknown backbone {kind!r}; expected one of {sorted(BACKBONES)}")
    cfg = cfg or FreeRegConfig()
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    spec = BACKBONES[kind]
    model_cls, config_cls = (Dinov2Model, Dinov2Config) if kind == "dinov2" else (CLIPVisionModel, CLIPVisionConfig)
    mean = std = None
    if backend == "tiny":
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            model = model_cls(config_cls(**spec.tiny))
        short_side = short_side or TINY_SHORT_SIDE[kind]
    elif backend == "real":
        wdir = W.default_weights_dir(cfg, weights_dir)
        path, searched = W.try_resolve(spec.model_id, wdir)
        if path is None:
            raise MissingWeightsError(
                f"{spec.label} weights ({spec.model_id}) not found (looked in: {'; '.join(searched)}); on a machine "
                f"with internet run `{W.download_command(spec.model_id, wdir)}`, then pass weights_dir= (or set "
                "FREEREG_WEIGHTS) to the folder that holds it", [spec.model_id], searched)
        model = model_cls.from_pretrained(path)
        mean, std = _read_norm(Path(path))
    else:
        raise ValueError(f"backend must be 'real' or 'tiny' for a vision backbone, got {backend!r}")
    model = model.to(device).eval()
    return VisionBackbone(kind, model, cfg, device, backend, short_side or spec.short_side, mean, std, layer)


def backbone_maps(pair, view, backbone: VisionBackbone) -> tuple[dict, dict]:
    """``({0: map of the image}, {0: map of the depth-as-RGB image})``, each ``(C, h, w) float32``:
    one "layer" per side, in the shape :func:`~freereg_lib.pipeline.compute_features` takes."""
    return {0: backbone(pair.image)}, {0: backbone(depth_as_rgb(view.dense))}


def backbone_features(pair, maps: tuple[dict, dict], backend, cfg, view=None, mono=None):
    """:class:`~freereg_lib.pipeline.PairFeatures` of a pair whose diffusion maps are ``maps``
    (``({layer: (C, h, w)}, {layer: (C, h, w)})``, e.g. :func:`backbone_maps` or
    :func:`standin_maps`' beside the image's): :func:`~freereg_lib.pipeline.compute_features` with
    those maps and ``cfg.layers`` set to their keys (joint PCA to ``cfg.pca_dim`` per layer,
    bilinear sampling at the keypoint grid), no geometric features. ``backend`` gives the monocular
    depth unless ``mono`` is given."""
    from freereg_lib import pipeline

    layers = tuple(sorted(maps[0]))
    cfg_maps = cfg if tuple(cfg.layers) == layers else cfg.override(layers=layers)
    return pipeline.compute_features(pair, backend, cfg_maps, True, False, view=view, maps=maps, mono=mono)


NOISE_TAG = "depth-as-rgb"


def standin_maps(pair, view, backend, layers=None, own_noise: bool = True) -> dict:
    """The stand-in backbone's decoder ``layers`` ``{layer: (C, h, w) float32}`` of the pair's
    depth map as an image (:func:`depth_as_rgb` of ``view.dense``): the backend's RGB branch, as
    notebook 01's "SD (depth map fed as image)" row. ``own_noise``: the torch backends draw the
    forward noise under :data:`NOISE_TAG` (not the image's pixel-aligned draw); the stub reads the
    depth side's scene hints (its features ignore pixels)."""
    from freereg_lib import pipeline

    image = depth_as_rgb(view.dense)
    if own_noise and hasattr(backend, "diffusion"):
        return backend.diffusion.rgb_batch([image], layers, noise_tag=NOISE_TAG)[0]
    hints = pipeline.scene_hints(pair, view)[1] if getattr(backend, "uses_scene_hints", False) else {}
    return backend.diffusion_rgb_batch([image], [hints], layers)[0]


# ---------------------------------------------------------------------------------------------
# The evaluation on a split.

ROWS = {"standin": "stand-in backbone on depth-as-RGB (micro SD UNet)",
        "standin_shared": "stand-in, the image's noise draw shared (notebook 01's row)",
        "freereg_d": "FreeReg-D (ControlNet)",
        "freereg": "FreeReg (fused, w = 0.5)"}
SOLVERS = ("kabsch", "pnp")
ROW_KEYS = ("row", "solver", "n_matches", "IR", "IN", "RE", "TE", "registered", "n_evaluable", "error")
TESTS = (("standin", "freereg_d"), ("standin", "freereg"), ("standin", "standin_shared"))


def pair_rows(pair, backend, cfg, rows=tuple(ROWS), solvers=SOLVERS) -> tuple[list[dict], dict[str, float]]:
    """The rows of one pair (``rows`` of :data:`ROWS` times ``solvers``) and the seconds of its
    parts; a failure becomes rows with ``error`` set, as :func:`~freereg_lib.pipeline.run_pair`."""
    from freereg_lib import pipeline

    sec, feats = {}, {}
    need_depth = "freereg_d" in rows or "freereg" in rows  # the ControlNet branch (DDIM) only for them
    try:
        t0 = time.perf_counter()
        view = pipeline.depth_view(pair, cfg)
        if need_depth:
            rgb, dep = pipeline.diffusion_maps_batch([pair], [view], backend, cfg.layers)[0]
        else:
            hint = pipeline.scene_hints(pair, view)[0] if getattr(backend, "uses_scene_hints", False) else {}
            rgb = backend.diffusion_rgb_batch([pair.image], [hint], cfg.layers)[0]
        sec["image and depth diffusion" if need_depth else "image diffusion"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        mono = backend.mono_depth(pair.image, depth_gt=pair.depth_gt)
        if need_depth:
            full = pipeline.compute_features(pair, backend, cfg, True, "freereg" in rows, view=view, maps=(rgb, dep),
                                             mono=mono)
            feats["freereg_d"] = feats["freereg"] = full
        sec["monocular depth, FPFH"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for name, own in (("standin", True), ("standin_shared", False)):
            if name in rows:
                feats[name] = backbone_features(pair, (rgb, standin_maps(pair, view, backend, cfg.layers, own)),
                                                backend, cfg, view=view, mono=mono)
        sec["stand-in diffusion"] = time.perf_counter() - t0
    except Exception as exc:  # scored as run_pair scores a failed pair
        feats = {name: exc for name in ROWS}
    out = []
    for name in rows:
        t0 = time.perf_counter()
        method = "FreeReg" if name == "freereg" else "FreeReg-D"
        for r in pipeline.variant_rows(pair, feats[name], cfg, [(method, s) for s in solvers]):
            out.append({"row": name, **{k: _plain(r.get(k)) for k in ROW_KEYS if k != "row"}})
        sec[f"{name} matching, solving"] = time.perf_counter() - t0
    return out, {k: round(v, 3) for k, v in sec.items()}


def run(split_name: str, n_pairs: int, rows_path: Path, backend_name: str = "micro", progress: bool = True,
        **changes) -> None:
    """Append the rows of the split's pairs ``k < n_pairs`` not yet in ``rows_path`` (resumable);
    ``changes`` override the config (the tests' fewer RANSAC iterations)."""
    from tqdm import tqdm

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    cfg = cfg.override(**changes) if changes else cfg
    backend = get_backend(backend_name, cfg, device="cpu")
    done = _done(rows_path)
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    for k in tqdm([k for k in range(n_pairs) if k not in done], desc=f"other backbones, {split.name} split",
                  disable=not progress):
        seed = split.pair_seeds(k + 1)[k]
        synthetic.check_eval_seed(seed)
        t0 = time.perf_counter()
        pair = synthetic.make_pair("indoor", seed=seed, world=split.world)
        rows, sec = pair_rows(pair, backend, cfg)
        rec = {"k": k, "pair_seed": seed, "pair": pair.name, "label": backend.label, "config_changes": changes,
               "load_average": round(os.getloadavg()[0], 2), "seconds": round(time.perf_counter() - t0, 1),
               "seconds_parts": sec, "rows": rows}
        with open(rows_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def _median(v) -> float | None:
    v = [x for x in v if x is not None]
    return float(np.median(v)) if v else None


def summarize(recs: list[dict], split_name: str) -> dict:
    """Per row and solver: FMR, IR, RR (%, 95 % bootstrap intervals), IN (mean count), median RE /
    TE, failures; paired tests of :data:`TESTS` (IR; RR with each solver)."""
    from freereg_lib.config import FreeRegConfig

    split = SPLITS[split_name]
    cfg = FreeRegConfig(seed=split.noise_seed)
    per = {}
    for name in ROWS:
        for s in SOLVERS:
            rows = [next(r for r in rec["rows"] if r["row"] == name and r["solver"] == s) for rec in recs]
            ir = [r["IR"] or 0.0 for r in rows]
            reg = [int(bool(r["registered"])) for r in rows]
            per[f"{name} {s}"] = {"label": ROWS[name], "FMR": _stat(np.asarray(ir) > cfg.fmr_ratio), "IR": _stat(ir),
                                  "RR": _stat(reg), "IN": float(np.mean([r["IN"] or 0 for r in rows])),
                                  "RE_median": _median([r["RE"] for r in rows]),
                                  "TE_median": _median([r["TE"] for r in rows]),
                                  "errors": sum(1 for r in rows if r["error"]), "n_rows": len(rows),
                                  "IR_per_pair": ir, "registered_per_pair": reg}
    tests = {}
    for a, b in TESTS:
        tests[f"IR: {a} - {b}"] = paired_difference(per[f"{a} kabsch"]["IR_per_pair"], per[f"{b} kabsch"]["IR_per_pair"])
        for s in SOLVERS:
            tests[f"RR {s}: {a} - {b}"] = paired_difference(per[f"{a} {s}"]["registered_per_pair"],
                                                per[f"{b} {s}"]["registered_per_pair"])
    parts = sorted({k for r in recs for k in r.get("seconds_parts", {})})
    return {"split": split.name, "dataset_seed": split.seed, "noise_seed": split.noise_seed, "n_pairs": len(recs),
            "pair_seeds": f"{split.seed} * 1_000_003 + k for k in 0..{len(recs) - 1}",
            "backend": recs[0]["label"] if recs else None,
            "config_changes": recs[0].get("config_changes", {}) if recs else {},
            "config": {"fusion_w": cfg.fusion_w, "layers": list(cfg.layers), "geometric": cfg.geometric,
                       "ransac_iters": cfg.ransac_iters, "fmr_ratio": cfg.fmr_ratio, "tau_c": cfg.tau_c,
                       "rr_rot_deg": cfg.rr_rot_deg, "rr_trans_m": cfg.rr_trans_m},
            "rows": ROWS, "results": per, "tests": tests,
            "seconds_per_pair": _median([r["seconds"] for r in recs]),
            "seconds_parts": {p: _median([r["seconds_parts"].get(p) for r in recs]) for p in parts},
            "load_average": load_average_range(recs),
            "note": "The micro SD UNet's RGB branch on the depth map as an image (depth_to_uint8, three channels) "
                    "stands in for the paper's DINOv2 / CLIP: an RGB-trained backbone reading the depth map as an "
                    "image. All rows share the pair's image maps, keypoints and monocular depth; standin, "
                    "standin_shared and freereg_d match diffusion features only (w = 1), freereg fuses them with "
                    "FPFH (w = 0.5). IR / FMR / RR in %, IN a count; intervals: 95 % percentile "
                    "bootstrap over pairs; p: two-sided paired sign-flip permutation test; errors: rows whose features "
                    "or pose failed, scored not registered; seconds: medians of the CPU's wall clock."}


def report(res: dict) -> str:
    lines = [f"Other backbones on the {res['split']} split: {res['n_pairs']} synthetic indoor pairs "
             f"({res['pair_seeds']}), {res['backend']}", "  row solver            FMR    IR     IN      RR  [95 % interval]"]
    return "\n".join(lines + result_lines(res, 22))


def main(argv=None) -> int:
    from freereg_lib.training.command_inputs import exit_on_bad_rows

    exit_on_bad_rows(argv, "other_backbones", "row")  # one line, exit 2, before any pair runs
    return split_command("freereg_lib.training.other_backbones", __doc__, run, summarize, report, argv)


if __name__ == "__main__":
    raise SystemExit(main())
