"""The synthetic world against real rooms, on the same statistics and with the same code.

For each image-to-cloud pair it measures what decides how hard the pair is for the geometric half,
before any learned model enters:

* FreeReg-G with the image's TRUE depth (FPFH, the ``3dmatch`` config): IR, and registration with
  Kabsch- and PnP-RANSAC (:func:`freereg_lib.commands.real_frames.pair_rows`);
* the pair: overlap (:func:`freereg_lib.data.synthetic.overlap_ratio`) and the baseline between
  the image camera and the depth sensor (rotation in degrees, translation in metres);
* the depth: median and 10th / 90th percentiles of the image's true depth, shares per metre;
* the cloud's local geometry at FPFH's scale (5 cm voxels, 10 cm neighbourhoods): surface
  variation (the covariance's smallest eigenvalue over their sum), the share of planar points
  (variation < 0.01) and the normal variation (mean angle between a point's normal and its
  neighbours');
* the image: mean Sobel gradient of the grey image in [0, 1] and the share of pixels above 0.05;
* how much is in view: depth segments (regions between depth steps of more than 5 cm holding at
  least 0.2 % of the pixels), the same measure on both kinds of frames.

Real frames: the shipped ICL-NUIM living room (rendered, noise-free) and TUM fr1 desk (a Kinect v1),
every pair (colour of frame i, cloud of frame j, i < j) whose overlap is above 30 %, as 3DMatch's.

    python -m freereg_lib.training.world_stats --world blocks --world rooms --pairs 30 --seed 7301 \
        --out freereg_lib/models/micro/weights/world_stats.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

VOXEL_M = 0.05
RADIUS_M = 0.10
PLANAR_BELOW = 0.01
GRADIENT_ABOVE = 0.05
DEPTH_STEP_M = 0.05
SEGMENT_MIN_SHARE = 0.002
DEPTH_BINS_M = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, np.inf)
MIN_OVERLAP = 0.3  # 3DMatch's pairs: overlap above 30 %


def baseline(T_cam_sensor: np.ndarray) -> tuple[float, float]:
    """Rotation angle (deg) and translation norm (m) of a ``(4, 4)`` relative pose."""
    c = np.clip((np.trace(T_cam_sensor[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c))), float(np.linalg.norm(T_cam_sensor[:3, 3]))


def depth_stats(depth: np.ndarray) -> dict:
    """Percentiles (m) and per-metre shares of the valid pixels of ``depth (H, W)``."""
    d = depth[depth > 0]
    if len(d) == 0:
        return {"depth_p10": np.nan, "depth_median": np.nan, "depth_p90": np.nan, "depth_shares": []}
    p10, p50, p90 = np.percentile(d, [10, 50, 90])
    shares = np.histogram(d, bins=np.asarray(DEPTH_BINS_M))[0] / len(d)
    return {"depth_p10": float(p10), "depth_median": float(p50), "depth_p90": float(p90),
            "depth_shares": [float(s) for s in shares]}


def geometry_stats(points: np.ndarray) -> dict:
    """Surface variation, planar share and normal variation (deg) of ``points (N, 3)`` at 5 cm
    voxels and 10 cm neighbourhoods."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    # Voxels on coordinates relative to the cloud's corner, so far-away frames bin alike.
    pcd.translate(-np.min(points, axis=0))
    pcd = pcd.voxel_down_sample(VOXEL_M)
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=RADIUS_M, max_nn=30)
    pcd.estimate_covariances(search)
    pcd.estimate_normals(search)
    eig = np.linalg.eigvalsh(np.asarray(pcd.covariances))
    variation = eig[:, 0] / np.maximum(eig.sum(axis=1), 1e-12)
    pts, normals = np.asarray(pcd.points), np.asarray(pcd.normals)
    _, nbr = cKDTree(pts).query(pts, k=min(11, len(pts)))
    cosines = np.abs(np.einsum("nd,nkd->nk", normals, normals[nbr[:, 1:]]))
    return {"surface_variation": float(np.mean(variation)),
            "planar_share": float(np.mean(variation < PLANAR_BELOW)),
            "normal_variation_deg": float(np.degrees(np.mean(np.arccos(np.clip(cosines, 0.0, 1.0)))))}


def texture_stats(image: np.ndarray) -> dict:
    """Mean Sobel gradient of the grey ``image (H, W, 3) uint8`` in [0, 1] units, and the share of
    pixels whose gradient exceeds 0.05."""
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    g = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    return {"gradient_mean": float(g.mean()), "textured_share": float(np.mean(g > GRADIENT_ABOVE))}


def depth_segments(depth: np.ndarray) -> int:
    """Regions of ``depth (H, W)`` bounded by steps of more than 5 cm (or no depth) that hold at
    least 0.2 % of the pixels."""
    import cv2

    valid = depth > 0
    step = np.zeros_like(valid)
    step[:, 1:] |= np.abs(np.diff(depth, axis=1)) > DEPTH_STEP_M
    step[1:, :] |= np.abs(np.diff(depth, axis=0)) > DEPTH_STEP_M
    n, _, stats, _ = cv2.connectedComponentsWithStats((valid & ~step).astype(np.uint8), connectivity=4)
    return int(np.sum(stats[1:, cv2.CC_STAT_AREA] >= SEGMENT_MIN_SHARE * depth.size))


def pair_stats(pair, backend, cfg) -> dict:
    """Every statistic of one pair (the module docstring), FreeReg-G with the true depth included."""
    from freereg_lib.commands.real_frames import pair_rows
    from freereg_lib.data.synthetic import overlap_ratio

    rows = {r["solver"]: r for r in pair_rows(pair, backend, cfg, depths=("true",))}
    rot, trans = baseline(pair.T_cam_pc @ pair.T_pc_sensor)
    return {"pair": pair.name, "IR": float(rows["kabsch"]["IR"]),
            "RR_kabsch": bool(rows["kabsch"]["registered"]), "RR_pnp": bool(rows["pnp"]["registered"]),
            "overlap": overlap_ratio(pair), "baseline_deg": rot, "baseline_m": trans,
            **depth_stats(pair.depth_gt), **geometry_stats(pair.points), **texture_stats(pair.image),
            "depth_segments": depth_segments(pair.depth_gt)}


SUMMARY = (("IR", "FreeReg-G IR, true depth (%)", 100), ("RR_kabsch", "RR Kabsch (%)", 100),
           ("RR_pnp", "RR PnP (%)", 100), ("overlap", "overlap (%)", 100),
           ("baseline_deg", "baseline rotation (deg)", 1), ("baseline_m", "baseline translation (m)", 1),
           ("depth_median", "depth median (m)", 1), ("depth_p90", "depth 90th percentile (m)", 1),
           ("surface_variation", "surface variation (x 100)", 100), ("planar_share", "planar share (%)", 100),
           ("normal_variation_deg", "normal variation (deg)", 1), ("gradient_mean", "image gradient (x 100)", 100),
           ("textured_share", "textured pixels (%)", 100), ("depth_segments", "depth segments in view", 1))


def summarize(rows: list[dict], seed: int = 0) -> dict:
    """Per statistic: mean with a 95 % bootstrap interval over pairs, and the median."""
    from freereg_lib.training.evaluate import bootstrap_ci

    out = {}
    for key, _, scale in SUMMARY:
        v = np.asarray([float(r[key]) for r in rows]) * scale
        lo, hi = bootstrap_ci(v, seed=seed)
        out[key] = {"mean": float(v.mean()), "ci95": [float(lo), float(hi)], "median": float(np.median(v))}
    out["depth_shares"] = [float(x) for x in 100 * np.mean([r["depth_shares"] for r in rows], axis=0)]
    out["n_pairs"] = len(rows)
    return out


def table(summaries: dict[str, dict]) -> str:
    """A Markdown table, one column per source: mean [95 % interval] (median)."""
    names = list(summaries)
    lines = ["| statistic | " + " | ".join(f"{n} ({summaries[n]['n_pairs']} pairs)" for n in names) + " |",
             "|---|" + "---|" * len(names)]
    for key, label, _ in SUMMARY:
        cells = [f"{s[key]['mean']:.1f} [{s[key]['ci95'][0]:.1f}, {s[key]['ci95'][1]:.1f}] ({s[key]['median']:.1f})"
                 for s in (summaries[n] for n in names)]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    edges = [f"{int(b)}" for b in DEPTH_BINS_M[:-1]]
    bins = " / ".join(f"{a}-{b}" for a, b in zip(edges, edges[1:])) + f" / {edges[-1]}+"
    lines.append(f"| depth shares, {bins} m (%) | "
                 + " | ".join(" / ".join(f"{x:.0f}" for x in summaries[n]["depth_shares"]) for n in names) + " |")
    return "\n".join(lines)


def measure(pairs, desc: str, progress: bool = True) -> list[dict]:
    """Rows of :func:`pair_stats` over ``pairs`` with the ``3dmatch`` config and the stub backend."""
    from tqdm.auto import tqdm

    from freereg_lib.config import config_for
    from freereg_lib.models import get_backend

    cfg = config_for("3dmatch")
    backend = get_backend("stub", cfg)
    return [pair_stats(p, backend, cfg) for p in tqdm(pairs, desc=desc, disable=not progress)]


def real_pairs(root: Path, min_overlap: float = MIN_OVERLAP):
    """The pairs (colour of frame i, depth of frame j), i < j, of a real sample folder that overlap by
    more than ``min_overlap``: 3DMatch's image-to-cloud protocol, not the easiest frames."""
    from freereg_lib.data.datasets.icl import ICLSample
    from freereg_lib.data.synthetic import overlap_ratio

    sample = ICLSample(root)
    for i in sample.frames:
        for j in sample.frames:
            if i < j and overlap_ratio(pair := sample.pair(i, j)) > min_overlap:
                yield pair


def main(argv=None) -> None:
    from freereg_lib.data.datasets.icl import ICL_ROOT, TUM_ROOT
    from freereg_lib.data.synthetic import WORLDS, make_pair
    from freereg_lib.training.provenance import machine_record

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--world", action="append", choices=WORLDS, help="synthetic world(s) to measure (repeatable)")
    p.add_argument("--pairs", type=int, default=30, help="synthetic pairs per world")
    p.add_argument("--seed", type=int, default=5150, help="pair seeds seed * 1_000_003 + k")
    p.add_argument("--no-real", action="store_true", help="skip the shipped real frames (ICL-NUIM, TUM fr1)")
    p.add_argument("--out", type=Path, default=None, help="JSON with every row and summary")
    p.add_argument("--table", type=Path, default=None, metavar="JSON", help="print the table of a written JSON and stop")
    a = p.parse_args(argv)
    if a.table:
        print(table(json.loads(a.table.read_text())["summaries"]))
        return
    rows: dict[str, list[dict]] = {}
    for world in a.world or ["rooms"]:
        seeds = [a.seed * 1_000_003 + k for k in range(a.pairs)]
        rows[f"synthetic {world}"] = measure((make_pair("indoor", seed=s, world=world) for s in seeds), world)
    if not a.no_real:
        rows["ICL-NUIM living room (rendered)"] = measure(real_pairs(ICL_ROOT), "icl")
        rows["TUM fr1 desk (Kinect v1)"] = measure(real_pairs(TUM_ROOT), "tum")
    summaries = {name: summarize(r) for name, r in rows.items()}
    print(table(summaries))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"command": "python -m freereg_lib.training.world_stats " + " ".join(sys.argv[1:] if argv is None else argv),
                                     "seed": a.seed, "summaries": summaries, "rows": rows,
                                     "provenance": machine_record()}, indent=1) + "\n")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
