"""The one config object: every hyper-parameter of FreeReg with the paper's defaults.

Values come from the paper (ICLR 2024) and the official code, as listed in
``shared/paper/FACTS.md``. Notebooks override fields through papermill parameters with
:func:`dataclasses.replace` or :meth:`FreeRegConfig.override`.
"""
from __future__ import annotations

import dataclasses
import numbers
import typing
from dataclasses import dataclass, field

# The official configs' prompts; the backends append ", best quality" (the official a_prompt), so
# the conditional text is exactly "a photo of a room, furniture, household items, best quality".
INDOOR_PROMPT = "a photo of a room, furniture, household items"
OUTDOOR_PROMPT = "a vehicle camera photo of street view, trees, cars, people, house, road, sky"
NEGATIVE_PROMPT = "lowres, bad anatomy, bad hands, cropped, worst quality"

# RR threshold ladders of the paper's Table 9 (PnP vs Kabsch, in its appendix): (deg, m).
INDOOR_LADDER = ((5.0, 0.1), (10.0, 0.2), (15.0, 0.3), (20.0, 0.5), (25.0, 0.5))
KITTI_LADDER = ((3.0, 1.0), (5.0, 2.0), (7.0, 3.0), (10.0, 3.0), (10.0, 4.0))


@dataclass(frozen=True)
class FreeRegConfig:
    """Every knob of the pipeline. Defaults are the paper's indoor (3DMatch) setting."""

    outdoor: bool = False
    # Diffusion features.
    resize_hw: tuple[int, int] = (512, 704)
    t_hat: int = 150
    ddim_steps: int = 20
    ddim_eta: float = 1.0
    guidance_w: float = 4.0  # eps = (w + 1) U(c) - w U(c_u)
    controlnet_scale: float = 1.0  # weight of the ControlNet's residuals (diffusers' conditioning_scale); official 1
    batched_guidance: bool = False  # both guidance branches in one UNet call (a GPU speed-up)
    pair_batch: int = 1  # pairs whose diffusion features run as one batch (a GPU speed-up)
    prompt: str = INDOOR_PROMPT
    negative_prompt: str = NEGATIVE_PROMPT
    layers: tuple[int, ...] = (0, 4, 6)
    pca_dim: int = 128
    pca_device: str | None = None  # None: float64 NumPy on the host; "cuda": float32 on the GPU
    seed: int = 0
    # Model weights and precision of the tiny / real backends (README "Weights", "Faster runs").
    sd_unet_variant: str = "non_ema"  # the official (non-EMA) SD v1.5 UNet; "ema": diffusers' default files
    controlnet: str = "lllyasviel/control_v11f1p_sd15_depth"  # Table 1; or a single-file checkpoint (FreeReg-Ft)
    dtype: str = "float32"  # the official precision; "float16" / "bfloat16": faster on CUDA, other features
    # Depth handling.
    densify: str = "fast"  # "fast" | "multiscale" | "none"
    depth_min: float = 0.01
    depth_max: float = 10.0
    # The official 6 x 6 edge filter on the monocular depth map before its back-projection
    # for geometric features (projection.edge_filter); 0 disables. There is none on the cloud.
    edge_filter_m: float = 0.2
    # Geometric features.
    geometric: str = "fpfh"  # "fpfh" | "fcgf"
    voxel_size: float = 0.025  # FCGF's voxel (the paper's)
    fpfh_voxel: float = 0.05  # FPFH needs coarser voxels than FCGF to be distinctive
    fpfh_radius_factor: float = 5.0  # FPFH radius = factor * voxel
    normal_radius_factor: float = 2.0
    tau_g: float = 0.5  # pixel -> nearest feature point farther than this gets a zero feature
    # Fusion and matching.
    fusion_w: float = 0.5
    keypoint_grid: tuple[int, int] = (32, 44)
    match_device: str = "cpu"  # "cuda[:N]" runs the mutual nearest neighbours on a GPU
    # Solvers.
    ransac_iters: int = 50_000
    kabsch_inlier_m: float = 0.2
    kabsch_with_scale: bool = True
    kabsch_scoring: str = "official"  # Open3D's fitness score; "matches": scored by the matches it explains
    kabsch_confidence: float = 1.0  # the official call never stops early; < 1 stops early (a speed-up)
    kabsch_max_scale_ratio: float = 0.0  # > 0 rejects similarities scaling by more (0: the official call)
    ransac_n: int = 4
    pnp_reproj_px: float = 10.0
    pnp_method: str = "iterative"  # the paper's (OpenCV's default); "usac": ~100x faster, coarser poses
    pnp_workers: int = 1  # threads sharing the PnP-RANSAC iterations (same solver, other samples)
    min_matches_kabsch: int = 5
    min_matches_pnp: int = 8
    # Evaluation.
    tau_c: float = 0.3
    fmr_ratio: float = 0.05
    rr_rot_deg: float = 20.0
    rr_trans_m: float = 0.5
    rr_ladder: tuple[tuple[float, float], ...] = INDOOR_LADDER
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        _check_types(self)

    def override(self, **changes) -> "FreeRegConfig":
        """A copy with ``changes``; unknown names raise a ``TypeError`` naming them."""
        known = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise TypeError(f"unknown config field(s) {unknown}; known: {sorted(known)}")
        return dataclasses.replace(self, **changes)


def config_for(dataset: str, kitti_trans_threshold: float = 3.0, **changes) -> FreeRegConfig:
    """The paper's configuration for ``dataset``.

    ``dataset`` is one of ``3dmatch``, ``scannet``, ``demo`` (the official demo pair:
    ScanNet's setting, as its ``config/demo.yaml``), ``icl``, ``synthetic_indoor`` (indoor
    settings) or ``kitti``, ``synthetic_outdoor`` (outdoor settings). KITTI's RR translation
    threshold is 3 m in the paper and 4 m in the official code; pass
    ``kitti_trans_threshold=4.0`` for the latter.
    """
    name = dataset.lower().replace("-", "_")
    indoor = {"3dmatch", "scannet", "demo", "icl", "synthetic_indoor", "synthetic", "indoor"}
    outdoor = {"kitti", "kitti_dc", "synthetic_outdoor", "outdoor"}
    if name in indoor:
        base = FreeRegConfig()
        if name in ("scannet", "demo"):  # the official config/demo.yaml is scannet.yaml's setting
            base = base.override(depth_max=15.0)
        elif name == "3dmatch":
            base = base.override(densify="none")  # the raw sensor depth, holes kept
    elif name in outdoor:
        base = FreeRegConfig(
            outdoor=True,
            resize_hw=(512, 1280),
            prompt=OUTDOOR_PROMPT,
            densify="multiscale",
            depth_min=0.5,
            depth_max=80.0,
            edge_filter_m=1.0,
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
    try:
        import numpy as np
    except ImportError:  # pragma: no cover
        return bool
    return np.bool_


def _type_name(tp) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")
