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
import math
import re
import sys
from pathlib import Path

import numpy as np

from freereg_lib.commands import user_inputs as UI
from freereg_lib.config import FreeRegConfig, config_for
from freereg_lib.data.pair import Pair
from freereg_lib.features.geometric import fcgf_checkpoint_path
from freereg_lib.geometry import cameras, projection
from freereg_lib.models import MissingWeightsError, get_backend
from freereg_lib.models.fcgf import load_fcgf
from freereg_lib.models.weightcheck import WeightsError
from freereg_lib.pipeline import register as R
from freereg_lib.report.registration import write_outputs


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
    m.add_argument("--setting", default="auto", choices=("auto",) + SETTINGS,
                   help="the paper's dataset setting to run: auto chooses 3dmatch (the depth view as it is, no hole "
                        "filling) for a dense cloud (a depth sensor's cloud in its frame, --depth-pose; a merged RGB-D "
                        "scan), demo (ScanNet's: projected and densified) for a sparse or thinned one, kitti with "
                        "--outdoor; the line 'setting:' says which and why")
    m.add_argument("--seed", type=int, default=0)
    d = r.add_argument_group("data")
    d.add_argument("--cloud-scale", type=float, default=1.0, help="multiply the cloud by this (0.001: mm -> m)")
    d.add_argument("--cloud-snap", type=float, default=0.0, metavar="M",
                   help="round the cloud's coordinates in its depth camera's frame to M metres before rendering it "
                        "(0: the official projection; 1e-6: a far cloud, e.g. UTM, gets the pose it gets at its origin)")
    d.add_argument("--gt-T-cam-pc", metavar="FILE", help="ground truth, cloud -> camera (4 x 4 text)")
    d.add_argument("--gt-T-pc-cam", metavar="FILE", help="ground truth, the camera's pose in the cloud's frame "
                   "(the official demo's rgb2pc.gt.pose.txt)")
    d.add_argument("--image-depth", metavar="FILE", help="the image's true depth (16-bit PNG), for IR / IN and "
                   "the stub's monocular depth")
    d.add_argument("--depth-scale", type=float, default=1000.0, help="depth PNG value per metre")
    d.add_argument("--stub-true-depth", action="store_true", help="with --backend stub: use --image-depth as the "
                   "monocular depth as it is (no added monocular error)")
    r.add_argument("--out", metavar="DIR", help="output folder (default: freereg_out/<image>-<cloud>)")
    r.add_argument("--strict", action="store_true", help="exit status 3 when the result is FAILED")
    return p


# The dataset settings of config_for that a user's pair can take (README, "Your own data").
SETTINGS = ("demo", "3dmatch", "scannet", "kitti")


# A cloud whose projection fills this share of its footprint's pixels is used as a depth map as it
# is. On its own sensor's camera a depth sensor's cloud fills ~100 % and a thinned one about the
# share kept; on the virtual cameras at a cloud's centre (closer than any sensor was) a merged
# RGB-D scan of half-size ICL frames fills 15-16 %, one of full-size frames thinned ninefold 7 %
# (both take 3dmatch: it registers them), one thinned tenfold 3 %, the official demo's 17k-point
# cloud 2 % (6 % on its own sensor).
SENSOR_DENSE_FILL = 0.8
VIRTUAL_DENSE_FILL = 0.05
# The footprint is the FILL_BLOCK x FILL_BLOCK pixel blocks that a point reaches, not the hit
# pixels closed by a kernel: after a 7 x 7 closing a point farther than 7 px from the others is its
# own footprint, so a sparse cloud read as dense (the official demo's 17k points "filled" 17 % of
# the views at their centre, 2 % of the pixels of the blocks they reach; a 1 % sample of a sensor's
# points 86 %). A block holds one point of a cloud spaced a block apart: 1 / 64 of its pixels.
FILL_BLOCK = 8


def projected_fill(points: np.ndarray, K: np.ndarray, size: tuple[int, int], T_sensor_pc: np.ndarray) -> float:
    """The share of the pixels of the cloud's footprint that a point of the cloud reaches, on the
    camera ``K``, ``size = (H, W)`` at ``T_sensor_pc``; the footprint is the
    :data:`FILL_BLOCK`-pixel square blocks holding at least one projected point (no closing). About
    1 for a depth sensor's cloud seen from its sensor, about the kept share for a thinned one,
    under 1 / 64 for points a block or more apart. 0 when fewer than 100 pixels are reached."""
    depth, _ = projection.project_to_depth(points, K, T_sensor_pc, size, 1e-6)
    hit = depth > 0
    if hit.sum() < 100:
        return 0.0
    H, W = hit.shape
    b = FILL_BLOCK
    hb, wb = -(-H // b), -(-W // b)
    padded = np.zeros((hb * b, wb * b), dtype=bool)
    padded[:H, :W] = hit
    blocks = padded.reshape(hb, b, wb, b).any(axis=(1, 3))
    # Blocks cut by the image's border hold fewer pixels: count the pixels inside the image only.
    inside = np.zeros((hb * b, wb * b), dtype=bool)
    inside[:H, :W] = True
    pixels = int(inside.reshape(hb, b, wb, b).sum(axis=(1, 3))[blocks].sum())
    return float(hit.sum() / max(pixels, 1))


def cloud_fill(pair: Pair, virtual: bool, cfg: FreeRegConfig) -> tuple[float, str, float]:
    """:func:`projected_fill` on the camera(s) the cloud will be rendered on: the pair's depth
    camera, else the median over the four virtual ones at its centre; where, and the threshold
    of a dense cloud there."""
    if pair.meta.get("depth_camera") and not virtual:
        return (projected_fill(pair.points, pair.K_depth, tuple(pair.depth_size), cameras.invert(pair.T_pc_sensor)),
                "its depth camera (--depth-pose)", SENSOR_DENSE_FILL)
    cams = [c for c in R.virtual_cameras(pair.points, pair.K_image, pair.image_size, cfg, n_yaw=4)
            if c.name.startswith("centre")]
    fills = [projected_fill(pair.points, c.K, c.size, cameras.invert(c.T_pc_sensor)) for c in cams]
    return float(np.median(fills)) if fills else 0.0, "virtual depth cameras at its centre", VIRTUAL_DENSE_FILL


def choose_setting(setting: str, pair: Pair, outdoor: bool, virtual: bool,
                   demo_layout: bool = False) -> tuple[str, str]:
    """The :func:`~freereg_lib.config.config_for` setting for the command's pair, and why.

    The paper densifies a depth view only where the cloud leaves it sparse: 3DMatch's sensor
    depth is used as it is (holes kept), ScanNet's and KITTI's projected clouds are filled.
    So an indoor cloud that is dense where it will be rendered (:func:`cloud_fill`: a depth
    sensor's cloud in its frame, ``--depth-pose``; a merged RGB-D scan) takes the 3DMatch
    setting, and a thinned or sparse one the demo's (ScanNet's: projected and densified);
    outdoors KITTI's. Filling a dense view only smears its edges: on half-size ICL frames
    (pairs 0-40, 50-90, 100-140, 150-190, 30-70, 170-210 built as in tests/test_own_scans.py, stub
    true depth, Kabsch, 2,000 iterations) the demo setting registered 3 of 6 sensor-frame and 2 of
    6 merged world-frame clouds, the 3DMatch setting all of them
    (measured: 7 vs 14 of 18 7-Scenes pairs, 0 vs 4 of 6 world-frame ones). The official
    demo layout takes its own config/demo.yaml. ``setting`` other than ``"auto"`` wins.
    """
    if setting != "auto":
        return setting, "given (--setting)"
    if outdoor:
        return "kitti", "--outdoor: the cloud is projected and densified (multiscale), the paper's KITTI setting"
    if demo_layout:
        return "demo", "the official demo layout: its config/demo.yaml (ScanNet's setting, densified)"
    fill, where, dense = cloud_fill(pair, virtual, config_for("demo"))
    if fill >= dense:
        return "3dmatch", (f"the cloud fills {fill:.0%} of its footprint on {where} (>= {dense:.0%}): used as a "
                           "depth map as it is, no hole filling")
    return "demo", (f"the cloud fills {fill:.0%} of its footprint on {where} (< {dense:.0%}): projected and "
                    "densified (ScanNet's setting, the official demo's)")


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
    for pattern, repl in _FLAG_WORDS:
        message = re.sub(pattern, repl, message)
    return message


def _fail(msg: str) -> int:
    print(f"freereg register: error: {msg}", file=sys.stderr)
    return 2


def register_command(args) -> int:

    try:
        if args.outdoor and args.setting in ("demo", "3dmatch", "scannet"):
            return _fail(f"--setting {args.setting} is an indoor setting; --outdoor asks for kitti")
        outdoor = args.outdoor or args.setting == "kitti"
        if args.stub_true_depth and args.backend != "stub":
            return _fail(f"--stub-true-depth is for --backend stub (got --backend {args.backend})")
        if args.stub_true_depth and not (args.image_depth or args.demo):
            return _fail("--stub-true-depth needs --image-depth FILE (the depth the stub then uses as it is)")
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
                                 outdoor)
        rough = UI.read_pose(args.rough_pose, "--rough-pose")
        # The output folder is checked before the registration runs (minutes on a CPU), not after.
        out = Path(args.out) if args.out else Path("freereg_out") / pair.name.replace("/", "_")
        blocked = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
        if blocked is not None:
            return _fail(f"{'--out ' if args.out else 'the output folder '}{out}: {blocked} is an existing file, "
                         "not a folder; give --out a folder (it is created when missing)")
        if unwritable := UI.output_fault(out):
            return _fail(("--out " if args.out else "the output folder ") + unwritable)
        if args.ransac_iters < 1:
            return _fail(f"--ransac-iters must be >= 1, got {args.ransac_iters}")
        if args.fcgf_checkpoint and args.geometric != "fcgf":
            return _fail("--fcgf-checkpoint is for --geometric fcgf")
        name, why_setting = choose_setting(args.setting, pair, outdoor, args.virtual, bool(args.demo))
        extra = {"weights_dir": args.weights_dir} if args.weights_dir else {}
        if args.fcgf_checkpoint:
            extra["fcgf_checkpoint"] = args.fcgf_checkpoint
        if not (math.isfinite(args.cloud_snap) and args.cloud_snap >= 0):
            return _fail(f"--cloud-snap must be a number >= 0 (metres; 0: none), got {args.cloud_snap}")
        try:
            cfg = config_for(name, seed=args.seed, ransac_iters=args.ransac_iters,
                             kabsch_scoring=args.kabsch_scoring, geometric=args.geometric, extra=extra,
                             cloud_snap_m=args.cloud_snap)
        except (ValueError, TypeError) as exc:
            return _fail(in_flags(UI._one_line(exc)))
    except R.InputError as exc:
        return _fail(str(exc))

    try:
        backend = get_backend(args.backend, cfg, device=args.device,
                              **({"mono_mae": 0.0} if args.stub_true_depth else {}))
        if args.geometric == "fcgf":
            # A missing checkpoint stops here, before any model runs; one that is there but is no
            # FCGF checkpoint is the user's bad input (exit 2), not a FAILED registration later.
            path = fcgf_checkpoint_path(cfg)
            try:
                load_fcgf(path)
            except WeightsError as exc:
                return _fail(f"--fcgf-checkpoint {path}: {UI._one_line(exc)}" if args.fcgf_checkpoint
                             else UI._one_line(exc))
    except (MissingWeightsError, ValueError, RuntimeError) as exc:
        print(f"freereg register: cannot load the {args.backend} backend:\n{in_flags(str(exc))}", file=sys.stderr)
        return 1
    print(f"setting: {name}: {why_setting}")
    given = pair.meta.get("resampled_from")  # an image of non-square pixels (inputs_check.square_pixels)
    print(f"image {pair.meta.get('image_path')} ({pair.image_size[1]} x {pair.image_size[0]}"
          f"{f', resampled from {given[1]} x {given[0]} to square pixels' if given else ''}), cloud "
          f"{pair.meta.get('cloud_path')} ({len(pair.points)} points)")
    try:
        reg = R.register(pair, backend, cfg, method=args.method, solver=args.solver,
                         depth_cameras="virtual" if args.virtual else None, refine=not args.no_refine,
                         rough_T_pc_cam=rough, up=args.up, n_yaw=args.views)
    except R.InputError as exc:
        return _fail(str(exc))
    paths = write_outputs(reg, out)
    np.set_printoptions(precision=4, suppress=True)
    print("T_cam_pc (maps the cloud into the image camera):")
    print(reg.T_cam_pc)
    print("T_pc_cam (the pose of the camera in the cloud's frame):")
    print(reg.T_pc_cam)
    print(f"wrote {', '.join(str(p) for p in paths.values())} ({reg.seconds:.1f} s)")
    print(f"result: {reg.result}")
    if not reg.registered:  # name the inputs that fail this way when they are wrong, the intrinsics first
        K_flag = "--K" if args.K is not None else (f"--intrinsics {args.intrinsics}" if args.intrinsics
                                                     else "of the demo layout")
        print(UI.failure_hint(pair, reg.scale if reg.solver == "kabsch" else None, K_flag,
                              f"--depth-scale {args.depth_scale:g}" if args.image_depth else None))
    return 3 if args.strict and not reg.registered else 0
