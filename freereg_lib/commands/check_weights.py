"""Check the weights before a long benchmark: load every model, say where each came from, and
register the official demo pair.

::

    python -m freereg_lib check-weights --demo PATH/TO/FreeReg/data/demo [--backend real|tiny]
        [--weights-dir DIR] [--device cuda] [--geometric fpfh|fcgf] [--dtype float32]
        [--controlnet ID_OR_FILE] [--sd-unet-variant non_ema|ema] [--ransac-iters N]
        [--ddim-steps N] [--no-hash]

It prints, per model, the model id, the folder or file it was read from, the variant, the dtype
and the SHA-256 of every weight file (``random init`` for the ``tiny`` backend), FCGF's
checkpoint included (the paper's geometric features: ``--geometric`` defaults to ``fcgf`` on the
real backend; ``fpfh`` on ``tiny``, which has no FCGF weights), then runs the official demo pair
(``data/demo/`` of the official repository: ``source_rgb.png``, ``target_pc.ply``,
``just_for_eval/``; see :mod:`freereg_lib.data.datasets.demo`) with FreeReg (fused features) under
both solvers and prints RE, TE, IR, IN, the evaluable matches and whether it registered at the
config's thresholds, (20 deg, 0.5 m). Matches are scored as the official demo scores them: the
depth side with ``just_for_eval/target_dpt.gtd.png`` (dense truth), the image side with
``source_rgb.gtd.png``. The defaults are the paper's (the ScanNet configuration the official
``config/demo.yaml`` uses, FCGF, the official Kabsch-RANSAC with 50k iterations, 20 DDIM steps);
``--ransac-iters`` and ``--ddim-steps`` lower them for a quick look.

What a correct installation gives (:data:`EXPECTED`): the official ``demo.py`` runs FreeReg with
Kabsch ("cz"), and its published ``utils/media/demo.png`` draws most of the matches green (within
0.3 m of the truth); so FreeReg + Kabsch must register the demo (RE < 20 deg, TE < 0.5 m) with
an inlier ratio well above FMR's 5 %. Exit status: 0 when the models loaded and FreeReg + Kabsch
registered the demo; 1 when a model or the demo could not be loaded; 3 when the demo was not
registered (or cannot be scored: no truth files), with the reason (random weights with
``--backend tiny``, which can never register it).
"""
from __future__ import annotations

import argparse
import hashlib
import math
import sys
from pathlib import Path

# Weight files a diffusers / transformers folder is read from, safetensors first (as the
# libraries choose).
_FILES = {
    "vae": ("vae/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.bin"),
    "text_encoder": ("text_encoder/model.safetensors", "text_encoder/pytorch_model.bin"),
    "controlnet": ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin"),
    "zoedepth": ("model.safetensors", "pytorch_model.bin"),
}
VARIANTS = (("FreeReg", "kabsch"), ("FreeReg", "pnp"))
DECIDES = ("FreeReg", "kabsch")  # the official demo.py's default ("cz": fused features, se3 Kabsch)
EXPECTED = ("FreeReg + kabsch registers the demo (RE < {rot:g} deg and TE < {trans:g} m) with most matches "
            "correct (IR well above 0.05; the official demo.png draws most of its matches within {tau:g} m)")
NOT_REGISTERED = 3


def sha256(path: str | Path, chunk: int = 1 << 23) -> str:
    """Hex SHA-256 of a file (the hash the Hugging Face Hub lists for LFS files)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _first(folder: str | Path, names) -> list[Path]:
    for n in names:
        if (Path(folder) / n).is_file():
            return [Path(folder) / n]
    return []


def model_sources(backend, cfg) -> list[dict]:
    """One dict per model the backend (and the geometric features) use: ``model``, ``source``
    (model id / folder / file, or ``random init``), ``variant``, ``dtype``, ``files``."""
    from freereg_lib.models import weights as W

    dt = str(getattr(backend, "dtype", "")).replace("torch.", "") or "n/a"
    out: list[dict] = []
    if backend.name == "real":
        paths = backend.paths
        if "sd" in paths:
            sd = paths["sd"]
            unet = W.sd_unet_weight_file(sd, backend.unet_variant)
            out.append(dict(model="Stable Diffusion v1.5 UNet", source=f"{W.SD15_ID} at {sd}",
                            variant=backend.unet_variant, dtype=dt, files=[unet] if unet else []))
            out.append(dict(model="Stable Diffusion v1.5 VAE", source=f"{W.SD15_ID} at {sd}", variant="default",
                            dtype=dt, files=_first(sd, _FILES["vae"])))
            out.append(dict(model="CLIP text encoder", source=f"{W.SD15_ID} at {sd}", variant="default",
                            dtype=dt, files=_first(sd, _FILES["text_encoder"])))
            if "controlnet_file" in paths:
                out.append(dict(model="depth ControlNet (single file)", source=paths["controlnet_file"],
                                variant=f"architecture of {backend.controlnet_id} at {paths['controlnet']}",
                                dtype=dt, files=[Path(paths["controlnet_file"])]))
            else:
                out.append(dict(model="depth ControlNet", source=f"{backend.controlnet_id} at {paths['controlnet']}",
                                variant="default", dtype=dt, files=_first(paths["controlnet"], _FILES["controlnet"])))
        if "zoe" in paths:
            out.append(dict(model="ZoeDepth", source=f"{backend.zoe_id} at {paths['zoe']}", variant="default",
                            dtype="float32", files=_first(paths["zoe"], _FILES["zoedepth"])))
    else:
        seed = getattr(backend, "seed", cfg.seed)
        for m in ("UNet", "ControlNet", "VAE", "CLIP text encoder", "ZoeDepth"):
            out.append(dict(model=f"{m} ({backend.name})", source=f"random init (seed {seed})",
                            variant="n/a", dtype="float32" if m == "ZoeDepth" else dt, files=[]))
    if cfg.geometric == "fcgf":
        from freereg_lib.features.geometric import fcgf_checkpoint_path

        path = fcgf_checkpoint_path(cfg)
        out.append(dict(model="FCGF ResUNetBN2C", source=path, variant="n/a", dtype="float32", files=[Path(path)]))
    else:
        out.append(dict(model="FPFH (Open3D)", source="no weights", variant="n/a", dtype="float64", files=[]))
    return out


def load_models(backend, cfg) -> None:
    """Build every model now (the backends load lazily), so a broken file fails here."""
    if hasattr(backend, "diffusion"):
        backend.diffusion  # noqa: B018 - the property loads the models
    if hasattr(backend, "zoe"):
        backend.zoe  # noqa: B018
    if cfg.geometric == "fcgf":
        from freereg_lib.features.geometric import fcgf_checkpoint_path
        from freereg_lib.models.fcgf import load_fcgf

        load_fcgf(fcgf_checkpoint_path(cfg))


def _fmt(v, spec: str) -> str:
    return "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="freereg check-weights", description=__doc__.split("\n\n")[0])
    p.add_argument("--demo", required=True, help="the official repository's data/demo folder")
    p.add_argument("--backend", default="real", choices=("real", "tiny"))
    p.add_argument("--weights-dir", default=None, help="folder of the model folders (default: $FREEREG_WEIGHTS, "
                                                       "then the Hugging Face cache)")
    p.add_argument("--device", default=None, help="cuda, cuda:N or cpu (default: CUDA when present)")
    p.add_argument("--geometric", default=None, choices=("fpfh", "fcgf"),
                   help="default: fcgf (the paper's) on the real backend, fpfh on tiny (no FCGF weights)")
    p.add_argument("--dtype", default=None, help="float32 (default, official), float16, bfloat16")
    p.add_argument("--controlnet", default=None, help="ControlNet model id or single-file checkpoint "
                                                      "(default: lllyasviel/control_v11f1p_sd15_depth)")
    p.add_argument("--sd-unet-variant", default=None, choices=("non_ema", "ema"))
    p.add_argument("--ransac-iters", type=int, default=None, help="default: the paper's 50000")
    p.add_argument("--ddim-steps", type=int, default=None, help="default: the paper's 20 (5: its fast setting)")
    p.add_argument("--no-hash", action="store_true", help="skip the SHA-256 of the weight files")
    args = p.parse_args(argv)

    from freereg_lib import pipeline
    from freereg_lib.config import config_for
    from freereg_lib.data.datasets.demo import load_demo_pair
    from freereg_lib.models import MissingWeightsError, get_backend

    geometric = args.geometric or ("fcgf" if args.backend == "real" else "fpfh")
    changes = {k: v for k, v in dict(geometric=geometric, dtype=args.dtype, controlnet=args.controlnet,
                                     sd_unet_variant=args.sd_unet_variant,
                                     ransac_iters=args.ransac_iters, ddim_steps=args.ddim_steps).items()
               if v is not None}
    extra = {"weights_dir": args.weights_dir} if args.weights_dir else {}
    # The official config/demo.yaml: ScanNet's settings (densify 'fast', depth mask 15 m).
    cfg = config_for("demo", extra=extra, **changes)
    try:
        backend = get_backend(args.backend, cfg, device=args.device)
        print(f"backend: {backend.label}")
        print(f"device: {backend.device}, dtype: {str(backend.dtype).replace('torch.', '')}")
        load_models(backend, cfg)
        sources = model_sources(backend, cfg)
    except (MissingWeightsError, OSError, ValueError, RuntimeError) as exc:
        print(f"\nFAILED to load the models:\n{exc}", file=sys.stderr)
        return 1
    print("models:")
    for s in sources:
        print(f"  {s['model']}: {s['source']}; variant {s['variant']}; dtype {s['dtype']}")
        for f in s["files"]:
            print(f"      {f}  sha256 {'(skipped)' if args.no_hash else sha256(f)}")
    try:
        pair = load_demo_pair(args.demo)
    except (OSError, ValueError) as exc:
        print(f"\nFAILED to load the demo pair:\n{exc}", file=sys.stderr)
        return 1
    print(f"demo pair: {args.demo} (image {pair.image_size[1]} x {pair.image_size[0]}, "
          f"{len(pair.points)} points); RANSAC iterations {cfg.ransac_iters}, DDIM steps {cfg.ddim_steps}; "
          f"geometric features {cfg.geometric}, Kabsch scoring {cfg.kabsch_scoring!r}")
    truth = Path(args.demo) / "just_for_eval"
    print("scored with: depth side " + ("just_for_eval/target_dpt.gtd.png (dense truth)" if pair.depth_frame_gt is not None
                                        else "the densified projection (no target_dpt.gtd.png)")
          + "; image side " + ("just_for_eval/source_rgb.gtd.png" if pair.depth_gt is not None
                               else f"nothing (no {truth / 'source_rgb.gtd.png'})"))
    if pair.depth_gt is None:
        print(f"\nNOT CHECKED: the demo has no {truth / 'source_rgb.gtd.png'}, so its matches cannot be scored",
              file=sys.stderr)
        return NOT_REGISTERED
    rows = pipeline.run_pair(pair, backend, cfg, VARIANTS)
    thr = f"({cfg.rr_rot_deg:g} deg, {cfg.rr_trans_m:g} m)"
    print(f"{'method':<8} {'solver':<7} {'matches':>7} {'IR':>6} {'IN':>5} {'RE (deg)':>9} {'TE (m)':>7}  "
          f"registered at {thr}  evaluable")
    for r in rows:
        print(f"{r['method']:<8} {r['solver']:<7} {r['n_matches']:>7} {_fmt(r['IR'], '.3f'):>6} {r['IN']:>5} "
              f"{_fmt(r['RE'], '.2f'):>9} {_fmt(r['TE'], '.3f'):>7}  {'yes' if r['registered'] else 'no'}"
              f"  {r.get('n_evaluable', -1)}" + (f"  ({r['error']})" if r["error"] else ""))
    print("a correct installation: " + EXPECTED.format(rot=cfg.rr_rot_deg, trans=cfg.rr_trans_m, tau=cfg.tau_c))
    return verdict(rows, backend.name, cfg)


def verdict(rows: list[dict], backend_name: str, cfg) -> int:
    """Print whether the deciding row (:data:`DECIDES`) registered the demo, and why not; the exit status."""
    row = next((r for r in rows if (r["method"], r["solver"]) == DECIDES), None)
    if row is not None and row["registered"]:
        print(f"OK: {DECIDES[0]} + {DECIDES[1]} registered the demo (RE {row['RE']:.2f} deg, TE {row['TE']:.3f} m, "
              f"IR {row['IR']:.3f})")
        return 0
    if row is None or row["error"]:
        why = f"it failed: {row['error']}" if row is not None else "it did not run"
    else:
        why = (f"RE {_fmt(row['RE'], '.2f')} deg, TE {_fmt(row['TE'], '.3f')} m against ({cfg.rr_rot_deg:g} deg, "
               f"{cfg.rr_trans_m:g} m), IR {_fmt(row['IR'], '.3f')} from {row['n_matches']} matches")
    if backend_name != "real":
        cause = (f"the {backend_name} backend has random weights, which cannot register it (this run checks that "
                 "the chain runs, not the weights)")
    else:
        cause = ("with the paper's weights it should; check the files and hashes above (the non-EMA SD v1.5 UNet, "
                 "ControlNet v1.1 depth, ZoeDepth NYU, FCGF 3DMatch), --dtype float32 and the default settings")
    print(f"\nNOT REGISTERED: {DECIDES[0]} + {DECIDES[1]} did not register the demo: {why}; {cause}", file=sys.stderr)
    return NOT_REGISTERED


if __name__ == "__main__":
    sys.exit(main())
