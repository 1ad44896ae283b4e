"""The one config object: every hyper-parameter of FreeReg with the paper's defaults.

Values come from the paper (ICLR 2024) and the official code (WHU-USI3DV/FreeReg; docs/fidelity.md
says what is verified against it). Notebooks override fields through papermill parameters with
:func:`dataclasses.replace` or :meth:`FreeRegConfig.override`.
"""
from __future__ import annotations

import dataclasses
import numbers
import typing
from dataclasses import dataclass, field

import numpy as np

# The official configs' prompts; the backends append ", best quality" (the official a_prompt), so
# the conditional text is exactly "a photo of a room, furniture, household items, best quality".
INDOOR_PROMPT = "a photo of a room, furniture, household items"
OUTDOOR_PROMPT = "a vehicle camera photo of street view, trees, cars, people, house, road, sky"
NEGATIVE_PROMPT = "lowres, bad anatomy, bad hands, cropped, worst quality"

# RR threshold ladders of the paper's Table 9 (PnP vs Kabsch, in its appendix): (deg, m).
INDOOR_LADDER = ((5.0, 0.1), (10.0, 0.2), (15.0, 0.3), (20.0, 0.5), (25.0, 0.5))
KITTI_LADDER = ((3.0, 1.0), (5.0, 2.0), (7.0, 3.0), (10.0, 3.0), (10.0, 4.0))


def ranged(default, interval, *, distinct: bool = False):
    """A field's default with its range, declared beside it (the one place a range is written).

    ``interval`` is written as in mathematics: ``"[0, 1]"``, ``"(0, inf)"``, ``"[1, inf)"``;
    alternatives are joined by ``|`` (``"0 | [1, inf)"``: exactly 0 or at least 1). For a tuple
    field it holds for every entry; a tuple of intervals holds entry by entry within each item
    (``rr_ladder``'s (deg, m) rungs). ``distinct``: one or more entries, none repeated.
    :func:`range_problem` checks a value against it; ``FreeRegConfig``, the notebooks'
    parameter check (:mod:`freereg_lib.report.params`) and the batch grid check all call it.
    """
    return field(default=default, metadata={"range": interval, "distinct": distinct})


@dataclass(frozen=True)
class FreeRegConfig:
    """Every knob of the pipeline. Defaults are the paper's indoor (3DMatch) setting."""

    outdoor: bool = False
    # Diffusion features.
    resize_hw: tuple[int, int] = ranged((512, 704), "[64, inf)")  # multiples of 64 (the backends check)
    t_hat: int = ranged(150, "[0, 999]")  # a timestep of SD's 1000
    ddim_steps: int = ranged(20, "[1, 1000]")
    ddim_eta: float = ranged(1.0, "[0, 1]")
    guidance_w: float = ranged(4.0, "[0, inf)")  # eps = (w + 1) U(c) - w U(c_u)
    controlnet_scale: float = ranged(1.0, "[0, inf)")  # weight of the ControlNet's residuals (diffusers' conditioning_scale); official 1
    batched_guidance: bool = False  # both guidance branches in one UNet call (a GPU speed-up)
    pair_batch: int = ranged(1, "[1, inf)")  # pairs whose diffusion features run as one batch (a GPU speed-up)
    # torch's threads while a model runs on the CPU. 1: the same numbers whatever the machine's load
    # (reductions split over 2 threads round differently) and no oversubscribed cores on a busy
    # machine (one pair's micro diffusion maps: 2.0 s at 1 thread busy or quiet, 12.1 s at 2 threads
    # beside one busy process). 0: torch's own count (a core each; the real models on a many-core CPU).
    cpu_threads: int = ranged(1, "[0, inf)")
    prompt: str = INDOOR_PROMPT
    negative_prompt: str = NEGATIVE_PROMPT
    layers: tuple[int, ...] = ranged((0, 4, 6), "[0, 8]", distinct=True)  # decoder layers 0..8
    pca_dim: int = ranged(128, "[1, inf)")
    pca_device: str | None = None  # None: float64 NumPy on the host; "cuda": float32 on the GPU
    seed: int = ranged(0, "[0, inf)")
    # Model weights and precision of the tiny / real backends (docs/real_data.md, "Weights";
    # docs/performance.md, "Faster runs").
    sd_unet_variant: str = "non_ema"  # the official (non-EMA) SD v1.5 UNet; "ema": diffusers' default files
    controlnet: str = "lllyasviel/control_v11f1p_sd15_depth"  # Table 1; or a single-file checkpoint (FreeReg-Ft)
    dtype: str = "float32"  # the official precision; "float16" / "bfloat16": faster on CUDA, other features
    # Depth handling.
    densify: str = "fast"  # "fast" | "multiscale" | "none"
    depth_min: float = ranged(0.01, "[0, inf)")  # and below depth_max
    depth_max: float = ranged(10.0, "(0, inf)")
    # The official 6 x 6 edge filter on the monocular depth map before its back-projection
    # for geometric features (projection.edge_filter); 0 disables. There is none on the cloud.
    edge_filter_m: float = ranged(0.2, "[0, inf)")
    # The official cfg.proj limits of the clouds handed to the geometric features
    # (projection.feature_cloud): depth < cloud_far_m and > cloud_near_m, then the mask
    # (depth_min, depth_max). ScanNet: 10 m although its masks reach 15 m.
    cloud_far_m: float = ranged(10.0, "(0, inf)")
    cloud_near_m: float = ranged(0.01, "[0, inf)")
    # Point cloud -> depth map: "official" = proj_pc2dpt (pixel truncated, z + 1e-5, z > 0.05 m,
    # no far limit); "round": nearest pixel within (depth_min, depth_max).
    cloud_projection: str = "official"
    # > 0: the cloud's depth-camera coordinates rounded to this grid first, so sub-grid changes
    # (a float64 cloud 5,000 km away keeps ~1e-9 m) flip no exact tie; 0: none, the official.
    cloud_snap_m: float = ranged(0.0, "[0, inf)")
    # fill_in_multiscale's remaining holes: the official 255 m (a KITTI hint reads them "far");
    # 0 leaves them empty (IP-Basic's own behaviour, "no measurement").
    multiscale_hole_m: float = ranged(255.0, "[0, inf)")
    # The official pipeline writes the densified map as a uint16 PNG (depth x depth_png_scale,
    # truncated) and reads it back; True does the same round trip (up to 1 mm lower indoors,
    # 1/256 m on KITTI), False keeps the float map.
    dense_png: bool = True
    depth_png_scale: float = ranged(1000.0, "(0, inf)")
    # Geometric features.
    geometric: str = "fpfh"  # "fpfh" | "fcgf"
    voxel_size: float = ranged(0.025, "(0, inf)")  # FCGF's voxel (the paper's)
    fpfh_voxel: float = ranged(0.05, "(0, inf)")  # FPFH needs coarser voxels than FCGF to be distinctive
    fpfh_radius_factor: float = ranged(5.0, "(0, inf)")  # FPFH radius = factor * voxel
    normal_radius_factor: float = ranged(2.0, "(0, inf)")
    tau_g: float = ranged(0.5, "[0, inf)")  # pixel -> nearest feature point farther than this gets a zero feature
    # Fusion and matching.
    fusion_w: float = ranged(0.5, "[0, 1]")  # 0: FreeReg-G alone, 1: FreeReg-D alone
    keypoint_grid: tuple[int, int] = ranged((32, 44), "[1, inf)")
    match_device: str = "cpu"  # "cuda[:N]" runs the mutual nearest neighbours on a GPU
    # Solvers.
    ransac_iters: int = ranged(50_000, "[1, inf)")
    kabsch_inlier_m: float = ranged(0.2, "(0, inf)")
    kabsch_with_scale: bool = True
    kabsch_scoring: str = "official"  # open3d 0.12's score (matches within the inlier distance); "open3d": the installed call
    kabsch_confidence: float = ranged(1.0, "(0, 1]")  # the official call never stops early; < 1 stops early (a speed-up)
    kabsch_max_scale_ratio: float = ranged(0.0, "0 | [1, inf)")  # > 0 rejects similarities scaling by more (0: the official call)
    ransac_n: int = ranged(4, "[3, inf)")  # a similarity needs 3 correspondences
    pnp_reproj_px: float = ranged(10.0, "(0, inf)")
    pnp_method: str = "iterative"  # the paper's (OpenCV's default); "usac": ~100x faster, coarser poses
    pnp_workers: int = ranged(1, "[1, inf)")  # threads sharing the PnP-RANSAC iterations (same solver, other samples)
    min_matches_kabsch: int = ranged(5, "[0, inf)")
    min_matches_pnp: int = ranged(8, "[0, inf)")
    # Evaluation.
    tau_c: float = ranged(0.3, "(0, inf)")
    fmr_ratio: float = ranged(0.05, "[0, 1]")
    rr_rot_deg: float = ranged(20.0, "(0, 180]")
    rr_trans_m: float = ranged(0.5, "(0, inf)")
    rr_ladder: tuple[tuple[float, float], ...] = ranged(INDOOR_LADDER, ("(0, 180]", "(0, inf)"))  # (deg, m) rungs
    # A pair with fewer than 3 evaluable matches: "official" scores IR 1, IN 1 (the official
    # ir_cal returns [0] distances); "zero": IR 0, IN the correct count. Rows say n_evaluable.
    eval_few_matches: str = "official"
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        _check_types(self)
        _check_ranges(self)

    def group(self, name: str) -> dict:
        """The fields of one of ``GROUPS`` (``"solvers"``, ``"evaluation"``, ...) as a dict."""
        if name not in GROUPS:
            raise KeyError(f"unknown config group {name!r}; known: {list(GROUPS)}")
        return {f: getattr(self, f) for f in GROUPS[name]}

    def override(self, **changes) -> "FreeRegConfig":
        """A copy with ``changes``; unknown names raise a ``TypeError`` naming them."""
        known = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise TypeError(f"unknown config field(s) {unknown}; known: {sorted(known)}")
        return dataclasses.replace(self, **changes)


# The config's responsibilities, in pipeline order. The fields stay flat (the notebooks'
# parameters, the batch grids and ``override`` name them directly); every field belongs to
# exactly one group, and ``FreeRegConfig.group(name)`` reads one.
GROUPS: dict[str, tuple[str, ...]] = {
    "run": ("outdoor", "seed", "extra"),
    "backend": ("sd_unet_variant", "controlnet", "dtype", "batched_guidance", "pair_batch", "cpu_threads"),
    "diffusion": ("resize_hw", "t_hat", "ddim_steps", "ddim_eta", "guidance_w", "controlnet_scale", "prompt",
                  "negative_prompt", "layers", "pca_dim", "pca_device"),
    "projection": ("densify", "depth_min", "depth_max", "edge_filter_m", "cloud_far_m", "cloud_near_m",
                   "cloud_projection", "cloud_snap_m", "multiscale_hole_m", "dense_png", "depth_png_scale"),
    "geometric": ("geometric", "voxel_size", "fpfh_voxel", "fpfh_radius_factor", "normal_radius_factor", "tau_g"),
    "matching": ("fusion_w", "keypoint_grid", "match_device"),
    "solvers": ("ransac_iters", "kabsch_inlier_m", "kabsch_with_scale", "kabsch_scoring", "kabsch_confidence",
                "kabsch_max_scale_ratio", "ransac_n", "pnp_reproj_px", "pnp_method", "pnp_workers",
                "min_matches_kabsch", "min_matches_pnp"),
    "evaluation": ("tau_c", "fmr_ratio", "rr_rot_deg", "rr_trans_m", "rr_ladder", "eval_few_matches"),
}


def config_for(dataset: str, kitti_trans_threshold: float = 3.0, **changes) -> FreeRegConfig:
    """The paper's configuration for ``dataset``.

    ``dataset`` is one of ``3dmatch``, ``scannet``, ``demo`` (the official demo pair:
    ScanNet's setting, as its ``config/demo.yaml``), ``icl``, ``synthetic_indoor`` (indoor
    settings) or ``kitti``, ``synthetic_outdoor`` (outdoor settings). KITTI's RR translation
    threshold is 3 m in the paper and 4 m in the official code; pass
    ``kitti_trans_threshold=4.0`` for the latter.
    """
    name = dataset.lower().replace("-", "_")
    indoor = {"3dmatch", "scannet", "demo", "icl", "synthetic_indoor", "synthetic_rooms", "synthetic", "indoor"}
    outdoor = {"kitti", "kitti_dc", "synthetic_outdoor", "outdoor"}
    if name in indoor:
        base = FreeRegConfig()
        if name in ("scannet", "demo"):  # the official config/demo.yaml is scannet.yaml's setting
            base = base.override(depth_max=15.0)
        elif name in ("3dmatch", "icl"):
            base = base.override(densify="none")  # sensor RGB-D frames: the raw depth, holes kept
    elif name in outdoor:
        base = FreeRegConfig(
            outdoor=True,
            resize_hw=(512, 1280),
            prompt=OUTDOOR_PROMPT,
            densify="multiscale",
            depth_min=0.5,
            depth_max=80.0,
            edge_filter_m=1.0,
            cloud_far_m=80.0,
            depth_png_scale=256.0,
            cloud_near_m=0.5,
            voxel_size=0.3,
            fpfh_voxel=0.5,
            tau_g=5.0,
            keypoint_grid=(32, 80),
            kabsch_inlier_m=4.0,
            tau_c=3.0,
            rr_rot_deg=10.0,
            rr_trans_m=kitti_trans_threshold,
            rr_ladder=KITTI_LADDER,
        )
    else:
        raise ValueError(
            f"unknown dataset {dataset!r}; expected one of {sorted(indoor | outdoor)}"
        )
    return base.override(**changes)


# --------------------------------------------------------------------------------------
# Type checking of the fields (a grid or papermill value of the wrong type must fail here,
# once, with the field's name, not later as an error on every pair).

def _check_types(cfg: FreeRegConfig) -> None:
    """Raise ``TypeError`` naming every field of ``cfg`` whose value has the wrong type.

    Integers are accepted for float fields, lists for tuple fields (papermill and YAML give
    lists; they are stored as tuples so that configs compare and hash alike). ``bool`` is
    not an int here, and a number written as text (``"2000"``, ``"5e4"``, ``"false"``) is
    refused with a hint: YAML reads ``5e4`` as a string.
    """
    hints = _field_types()
    problems = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        ok, fixed = _conforms(value, hints[f.name])
        if not ok:
            hint = ""
            if isinstance(value, str):
                hint = (" (a number or a boolean written as text: YAML reads 5e4 as a string, "
                        "write 50000 or 5.0e+4, and true / false unquoted)")
            problems.append(f"{f.name}={value!r} is {type(value).__name__}, expected {_type_name(hints[f.name])}{hint}")
        elif fixed is not value:
            object.__setattr__(cfg, f.name, fixed)
    if problems:
        raise TypeError("FreeRegConfig: " + "; ".join(problems))


_HINTS: dict = {}


def _field_types() -> dict:
    if not _HINTS:
        _HINTS.update(typing.get_type_hints(FreeRegConfig))
    return _HINTS


def _conforms(value, tp):
    """``(ok, value)``; for tuple types a list is returned as a tuple."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is type(None):
        return value is None, value
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", typing.Union)):
        for arg in args:
            ok, fixed = _conforms(value, arg)
            if ok:
                return True, fixed
        return False, value
    if tp is bool:
        return isinstance(value, (bool, _np_bool())), value
    if tp is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, (bool, _np_bool())), value
    if tp is float:
        return isinstance(value, numbers.Real) and not isinstance(value, (bool, _np_bool())), value
    if tp is str:
        return isinstance(value, str), value
    if tp is dict or origin is dict:
        return isinstance(value, dict), value
    if tp is tuple or origin is tuple:
        if not isinstance(value, (tuple, list)):
            return False, value
        if len(args) == 2 and args[1] is Ellipsis:
            items = [_conforms(v, args[0]) for v in value]
        elif args:
            if len(value) != len(args):
                return False, value
            items = [_conforms(v, a) for v, a in zip(value, args)]
        else:
            return True, tuple(value)
        if not all(ok for ok, _ in items):
            return False, value
        fixed = tuple(v for _, v in items)
        same = isinstance(value, tuple) and all(a is b for a, b in zip(fixed, value))
        return True, value if same else fixed
    return True, value  # a type this check does not know: accepted


def _np_bool():
    return np.bool_


def _type_name(tp) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


# --------------------------------------------------------------------------------------
# Ranges of the numeric fields (declared with :func:`ranged` beside each default).

class _Interval:
    """One interval of :func:`ranged`'s notation, or a single value (``"0"``)."""

    def __init__(self, text: str):
        text = text.strip()
        self.text = text
        if text[:1] in "[(":
            lo, hi = (s.strip() for s in text[1:-1].split(","))
            self.lo, self.hi = float(lo), float(hi)
            self.lo_open, self.hi_open = text[0] == "(", text[-1] == ")"
        else:
            self.lo = self.hi = float(text)
            self.lo_open = self.hi_open = False

    def holds(self, v: float) -> bool:
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return bool(above and below)


def _holds(spec: str, v) -> bool:
    if not isinstance(v, numbers.Real) or isinstance(v, bool):
        return True  # the type check reports it
    return any(_Interval(part).holds(float(v)) for part in spec.split("|"))


def field_range(name: str):
    """The declared range of field ``name`` (``None`` for a field without one)."""
    f = FreeRegConfig.__dataclass_fields__.get(name)
    return None if f is None else f.metadata.get("range")


def range_problem(name: str, value) -> str:
    """One line naming ``name``, ``value`` and the declared range when ``value`` lies outside
    it; ``""`` when it is inside, or ``name`` has no range. Lists count as tuples."""
    f = FreeRegConfig.__dataclass_fields__.get(name)
    spec = None if f is None else f.metadata.get("range")
    if spec is None:
        return ""
    shown = tuple(value) if isinstance(value, list) else value
    if isinstance(value, (tuple, list)):
        if f.metadata.get("distinct") and (not value or len(set(value)) != len(value)):
            return (f"{name}={shown!r} must name one or more distinct entries, each in {spec} "
                    f"(got {'none' if not value else 'a repeated one'})")
        for item in value:
            if isinstance(spec, tuple):  # entry by entry within each item (a ladder's rungs)
                parts = item if isinstance(item, (tuple, list)) else (item,)
                if any(not _holds(s, v) for s, v in zip(spec, parts)):
                    return f"{name}={shown!r} is out of range: each item must be in {' x '.join(spec)}, got {item!r}"
            elif not _holds(spec, item):
                return f"{name}={shown!r} is out of range: each entry must be in {spec}, got {item!r}"
        return ""
    if not _holds(spec, value):
        return f"{name}={value!r} is out of range: expected {' or '.join(s.strip() for s in spec.split('|'))}"
    return ""


# Text fields with a closed set of values, checked when the config is made: a typo failed later, in
# the middle of an evaluation, with a message that did not name the field.
CHOICES = {"eval_few_matches": ("official", "zero")}


def _check_ranges(cfg: FreeRegConfig) -> None:
    """Raise ``ValueError`` (one line) naming every field of ``cfg`` outside its declared range."""
    problems = [p for f in dataclasses.fields(cfg) if (p := range_problem(f.name, getattr(cfg, f.name)))]
    problems += [f"{name}={getattr(cfg, name)!r} is not one of {', '.join(map(repr, allowed))}"
                 for name, allowed in CHOICES.items() if getattr(cfg, name) not in allowed]
    if not problems and not cfg.depth_min < cfg.depth_max:
        problems.append(f"depth_min={cfg.depth_min!r} must be below depth_max={cfg.depth_max!r}")
    if problems:
        raise ValueError("FreeRegConfig: " + "; ".join(problems))
