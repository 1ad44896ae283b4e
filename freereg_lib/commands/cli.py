"""The ``freereg`` command (installed with the package; also ``python -m freereg_lib``).

::

    freereg register IMAGE CLOUD --K fx fy cx cy [options]     # your own image and point cloud
    freereg register --demo FOLDER [options]                   # the official demo layout
    freereg batch run GRID.yaml [options]                      # a grid of notebooks (resumable)
    freereg check-weights [--demo FOLDER]                      # are the real weights in place
    freereg reproduce [--out runs/reproduce]                   # what ``make reproduce`` runs

``batch``, ``check-weights`` and ``reproduce`` are the modules of :mod:`freereg_lib.commands` with
their own options (``freereg batch --help``). See ``freereg register --help`` and :mod:`freereg_lib.pipeline.register`. Bad input stops with one line
naming it (exit status 2); a run that finds no plausible pose still writes its outputs and exits 0
with a ``FAILED: ...`` result line (``--strict`` makes that exit status 3).
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path


# The other user-facing commands, each with its own parser: ``freereg batch ...`` runs
# ``freereg_lib.commands.batch.main(...)``.
OTHER_COMMANDS = {"batch": ("freereg_lib.commands.batch", "run or merge a grid of notebooks (resumable, shardable)"),
                  "check-weights": ("freereg_lib.commands.check_weights", "check that the real weights are in place"),
                  "reproduce": ("freereg_lib.commands.reproduce", "run every notebook into a folder, then the site")}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="freereg", description="FreeReg companion commands.")
    sub = p.add_subparsers(dest="command", required=True)
    for name, (_, help_text) in OTHER_COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    r = sub.add_parser(
        "register", help="register an image to a point cloud",
        description="Register an image to a point cloud with FreeReg and write the pose (T_cam_pc maps the cloud "
                    "into the image camera; T_pc_cam is the camera's pose in the cloud's frame), the matches and the "
                    "cloud drawn on the image.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    r.add_argument("image", nargs="?", help="the image (PNG / JPEG)")
    r.add_argument("cloud", nargs="?", help="the point cloud (.ply, .pcd, .npy, .xyz / .txt / .pts), in metres")
    r.add_argument("--demo", metavar="FOLDER", help="the official demo layout (source_rgb.png, target_pc.ply, "
                   "intrinsics.json, just_for_eval/) instead of IMAGE CLOUD")
    g = r.add_argument_group("cameras")
    g.add_argument("--K", nargs=4, type=float, metavar=("FX", "FY", "CX", "CY"), help="image intrinsics in pixels")
    g.add_argument("--intrinsics", metavar="FILE", help="image intrinsics from a file: fx fy cx cy, a 3 x 3 matrix, "
                   "or JSON (fx/fy/cx/cy, K, rgb_intrinsic)")
    g.add_argument("--depth-pose", metavar="FILE", help="the depth sensor's pose in the cloud's frame (T_pc_sensor, "
                   "4 x 4 text), or 'identity' when the cloud is in its sensor's frame; without it virtual depth "
                   "cameras are tried")
    g.add_argument("--depth-K", nargs=4, type=float, metavar=("FX", "FY", "CX", "CY"),
                   help="the depth camera's intrinsics (default: the image's)")
    g.add_argument("--depth-size", nargs=2, type=int, metavar=("W", "H"), help="the depth camera's image size")
    g.add_argument("--virtual", action="store_true", help="try virtual depth cameras even when one is given")
    g.add_argument("--rough-pose", metavar="FILE", help="a rough pose of the image camera in the cloud's frame "
                   "(T_pc_cam, 4 x 4 text): one more virtual camera candidate")
    g.add_argument("--up", default="auto", help="the cloud's up axis for the virtual cameras: x, y, z, -x, -y, -z "
                   "(--up -y and --up=-y both work)")
    g.add_argument("--views", type=int, default=8, help="virtual camera directions around the up axis (>= 1)")
    g.add_argument("--no-refine", action="store_true", help="do not re-render from the estimated pose")
    m = r.add_argument_group("method")
    m.add_argument("--backend", default="real", choices=("stub", "tiny", "real"),
                   help="real: SD v1.5 + ControlNet + ZoeDepth (weights, a GPU); tiny: random weights (a smoke test); "
                        "stub: no model, needs --image-depth")
    m.add_argument("--weights-dir", help="folder of the model folders (default: $FREEREG_WEIGHTS)")
    m.add_argument("--device", help="cuda, cuda:N or cpu (default: CUDA when present)")
    m.add_argument("--method", choices=("FreeReg", "FreeReg-D", "FreeReg-G"),
                   help="default FreeReg (FreeReg-G with the stub)")
    m.add_argument("--geometric", default="fpfh", choices=("fpfh", "fcgf"),
                   help="geometric features: fpfh (Open3D, no weights) or fcgf (the official FCGF checkpoint, "
                        "<weights-dir>/fcgf/ or --fcgf-checkpoint)")
    m.add_argument("--fcgf-checkpoint", metavar="FILE", help="the FCGF checkpoint for --geometric fcgf")
    m.add_argument("--solver", default="kabsch", choices=("kabsch", "pnp"))
    m.add_argument("--ransac-iters", type=int, default=50_000, help="the paper's 50000")
    m.add_argument("--kabsch-scoring", default="official", choices=("official", "open3d"),
                   help="official: open3d 0.12's algorithm, as the paper ran it (about 1 s at 50k); "
                        "open3d: the installed Open3D's call (>= 0.15 scores by cloud fitness; minutes on a CPU)")
    m.add_argument("--outdoor", action="store_true", help="the paper's outdoor (KITTI) setting")
    m.add_argument("--seed", type=int, default=0)
    d = r.add_argument_group("data")
    d.add_argument("--cloud-scale", type=float, default=1.0, help="multiply the cloud by this (0.001: mm -> m)")
    d.add_argument("--gt-T-cam-pc", metavar="FILE", help="ground truth, cloud -> camera (4 x 4 text)")
    d.add_argument("--gt-T-pc-cam", metavar="FILE", help="ground truth, the camera's pose in the cloud's frame "
                   "(the official demo's rgb2pc.gt.pose.txt)")
    d.add_argument("--image-depth", metavar="FILE", help="the image's true depth (16-bit PNG), for IR / IN and "
                   "the stub's monocular depth")
    d.add_argument("--depth-scale", type=float, default=1000.0, help="depth PNG value per metre")
    r.add_argument("--out", metavar="DIR", help="output folder (default: freereg_out/<image>-<cloud>)")
    r.add_argument("--strict", action="store_true", help="exit status 3 when the result is FAILED")
    return p


# Options whose value may start with "-" (argparse reads "--up -y" as a missing value followed
# by an unknown option -y): "--up -y" is rewritten to "--up=-y" before parsing.
_SIGNED_VALUE_OPTIONS = ("--up",)


def _join_signed_values(argv: list[str]) -> list[str]:
    out: list[str] = []
    it = iter(range(len(argv)))
    for i in it:
        tok = argv[i]
        if tok in _SIGNED_VALUE_OPTIONS and i + 1 < len(argv) and argv[i + 1][:1] == "-" and argv[i + 1] != "--":
            out.append(f"{tok}={argv[i + 1]}")
            next(it, None)
        else:
            out.append(tok)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in OTHER_COMMANDS:
        return importlib.import_module(OTHER_COMMANDS[argv[0]][0]).main(argv[1:])
    args = _parser().parse_args(_join_signed_values(argv))
    if args.command == "register":
        return register_command(args)
    return 2  # pragma: no cover (argparse requires a command)


# The library's messages speak Python (get_backend's keywords, cfg fields); the command's own
# flags replace them here, so that what the user reads is what the user can type.
_FLAG_WORDS = (
    (r"pass weights_dir=\.\.\. to get_backend \(or set FREEREG_WEIGHTS, or cfg\.extra\['weights_dir'\]\)",
     "pass --weights-dir FOLDER (or set FREEREG_WEIGHTS)"),
    (r"pass weights_dir=(['\"])(.*?)\1", r"pass --weights-dir \2"),
    (r"pass `?weights_dir=`?", "pass --weights-dir "),
    (r"\bweights_dir\b", "--weights-dir"),
    (r"cfg\.extra\['fcgf_checkpoint'\]", "--fcgf-checkpoint FILE"),
    (r"geometric=(['\"])fpfh\1", "--geometric fpfh"),
    (r"backend=(['\"])(stub|tiny|real|micro)\1", r"--backend \2"),
    (r"\bdevice=(['\"])(cpu|cuda[:\d]*)\1", r"--device \2"),
    (r"\bdevice=None\b", "no --device"),
    (r"cfg\.kabsch_scoring", "--kabsch-scoring"),
    (r"cfg\.ransac_iters|\bransac_iters\b", "--ransac-iters"),
    (r"cfg\.geometric", "--geometric"),
)


def in_flags(message: str) -> str:
    """``message`` with the library's Python spellings (``weights_dir=``, ``backend="stub"``,
    ``cfg.extra['fcgf_checkpoint']``, ...) replaced by this command's flags."""
    import re

    for pattern, repl in _FLAG_WORDS:
        message = re.sub(pattern, repl, message)
    return message


def _fail(msg: str) -> int:
    print(f"freereg register: error: {msg}", file=sys.stderr)
    return 2


def register_command(args) -> int:
    import numpy as np

    from freereg_lib.config import config_for
    from freereg_lib.geometry import cameras
    from freereg_lib.commands import user_inputs as UI
    from freereg_lib.pipeline import register as R
    from freereg_lib.report.registration import write_outputs

    try:
        if args.views < 1:
            return _fail(f"--views must be >= 1 (virtual camera directions around the up axis), got {args.views}")
        if args.demo:
            if args.image or args.cloud:
                return _fail("give either --demo FOLDER or IMAGE CLOUD, not both")
            pair = UI.load_demo(args.demo)
        else:
            if not (args.image and args.cloud):
                return _fail("give IMAGE CLOUD (and --K fx fy cx cy), or --demo FOLDER")
            if args.K is not None and args.intrinsics:
                return _fail("give the image intrinsics once: --K or --intrinsics")
            K = args.K if args.K is not None else (UI.read_intrinsics(args.intrinsics) if args.intrinsics else None)
            if args.gt_T_cam_pc and args.gt_T_pc_cam:
                return _fail("give the ground truth once: --gt-T-cam-pc or --gt-T-pc-cam")
            gt = UI.read_pose(args.gt_T_cam_pc, "--gt-T-cam-pc")
            if args.gt_T_pc_cam:
                gt = cameras.invert(UI.read_pose(args.gt_T_pc_cam, "--gt-T-pc-cam"))
            size = (args.depth_size[1], args.depth_size[0]) if args.depth_size else None
            pair = UI.load_inputs(args.image, args.cloud, K, args.depth_K, size, UI.read_pose(args.depth_pose,
                                 "--depth-pose"), gt, args.image_depth, args.depth_scale, args.cloud_scale,
                                 args.outdoor)
        rough = UI.read_pose(args.rough_pose, "--rough-pose")
        if args.ransac_iters < 1:
            return _fail(f"--ransac-iters must be >= 1, got {args.ransac_iters}")
        if args.fcgf_checkpoint and args.geometric != "fcgf":
            return _fail("--fcgf-checkpoint is for --geometric fcgf")
        name = "kitti" if args.outdoor else "demo"  # indoor: the official config/demo.yaml (ScanNet's)
        extra = {"weights_dir": args.weights_dir} if args.weights_dir else {}
        if args.fcgf_checkpoint:
            extra["fcgf_checkpoint"] = args.fcgf_checkpoint
        try:
            cfg = config_for(name, seed=args.seed, ransac_iters=args.ransac_iters,
                             kabsch_scoring=args.kabsch_scoring, geometric=args.geometric, extra=extra)
        except (ValueError, TypeError) as exc:
            return _fail(in_flags(UI._one_line(exc)))
    except R.InputError as exc:
        return _fail(str(exc))

    from freereg_lib.models import MissingWeightsError, get_backend

    try:
        backend = get_backend(args.backend, cfg, device=args.device)
        if args.geometric == "fcgf":
            from freereg_lib.features.geometric import fcgf_checkpoint_path

            fcgf_checkpoint_path(cfg)  # a missing checkpoint stops here, before any model runs
    except (MissingWeightsError, ValueError, RuntimeError) as exc:
        print(f"freereg register: cannot load the {args.backend} backend:\n{in_flags(str(exc))}", file=sys.stderr)
        return 1
    print(f"image {pair.meta.get('image_path')} ({pair.image_size[1]} x {pair.image_size[0]}), cloud "
          f"{pair.meta.get('cloud_path')} ({len(pair.points)} points)")
    try:
        reg = R.register(pair, backend, cfg, method=args.method, solver=args.solver,
                         depth_cameras="virtual" if args.virtual else None, refine=not args.no_refine,
                         rough_T_pc_cam=rough, up=args.up, n_yaw=args.views)
    except R.InputError as exc:
        return _fail(str(exc))
    out = Path(args.out) if args.out else Path("freereg_out") / pair.name.replace("/", "_")
    paths = write_outputs(reg, out)
    np.set_printoptions(precision=4, suppress=True)
    print("T_cam_pc (maps the cloud into the image camera):")
    print(reg.T_cam_pc)
    print("T_pc_cam (the pose of the camera in the cloud's frame):")
    print(reg.T_pc_cam)
    print(f"wrote {', '.join(str(p) for p in paths.values())} ({reg.seconds:.1f} s)")
    print(f"result: {reg.result}")
    return 3 if args.strict and not reg.registered else 0
