"""A registration's outputs: the cloud drawn on the image, the matches, and the files
``freereg register`` writes (pose, matches, candidates, figures)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from freereg_lib.geometry import projection
from freereg_lib.pipeline.register import Registration, _fmt
from freereg_lib.report import plots

POSE_HEADER = {
    "T_cam_pc": "T_cam_pc: maps points of the cloud's frame into the image camera, x_cam = R x_pc + t (OpenCV camera: "
                "x right, y down, z forward)",
    "T_pc_cam": "T_pc_cam: the pose of the image camera in the cloud's frame (its inverse, T_cam_pc, maps the cloud "
                "into the camera)",
}


def overlay_image(reg: Registration, T_cam_pc: np.ndarray | None = None) -> np.ndarray:
    """The cloud projected onto the image with the estimated pose (or ``T_cam_pc``), coloured by
    depth, ``(H, W, 3)`` float RGB."""

    pair = reg.pair
    T = reg.T_cam_pc if T_cam_pc is None else T_cam_pc
    if not np.all(np.isfinite(T)):
        return np.asarray(pair.image, dtype=np.float64) / 255.0
    depth, _ = projection.project_to_depth(pair.points, pair.K_image, T, pair.image_size, 0.01)
    return plots.overlay_depth(pair.image, depth, alpha=0.6)


def overlay_figure(reg: Registration):
    """The image, the cloud drawn on it with the estimated pose, and with the true pose when known."""

    images = [reg.pair.image, overlay_image(reg)]
    titles = ["image", f"cloud drawn with the estimated pose ({reg.result.split(':')[0]})"]
    if reg.errors:
        images.append(overlay_image(reg, reg.pair.T_cam_pc))
        titles.append(f"with the true pose (RE {_fmt(reg.errors['RE'], '.1f')} deg, TE {_fmt(reg.errors['TE'], '.2f')} m)")
    return plots.image_grid(images, titles, suptitle=f"{reg.pair.name} - {reg.backend}", cols=len(images),
                            width=6.0 * len(images))


def matches_figure(reg: Registration, max_lines: int = 200):
    """Image and depth view side by side with the matches: green the pose's inliers, red the rest."""

    f, m = reg.feats, reg.matches
    if f is None or m is None:
        return None
    inl = np.zeros(len(m), dtype=bool)
    if reg.pose is not None and reg.pose.success:
        inl[np.asarray(reg.pose.inliers, dtype=np.int64)] = True
    return plots.draw_matches(
        reg.pair.image, plots.depth_image(f.view.dense), f.uv_image[m.idx_image], f.uv_depth[m.idx_depth], inl,
        title=f"{reg.method} + {reg.solver}: {len(m)} matches, {reg.n_inliers} inliers (green) - depth camera "
              f"{reg.camera.name} - {reg.backend}", max_lines=max_lines)


def write_outputs(reg: Registration, out_dir: str | Path) -> dict[str, Path]:
    """Write ``T_cam_pc.txt``, ``T_pc_cam.txt``, ``registration.json``, ``candidates.csv``,
    ``matches.png``, ``overlay.png`` into ``out_dir``; returns their paths."""


    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, T in (("T_cam_pc", reg.T_cam_pc), ("T_pc_cam", reg.T_pc_cam)):
        paths[name] = out / f"{name}.txt"
        np.savetxt(paths[name], T, fmt="%.9f", header=POSE_HEADER[name] + ("" if reg.registered else
                                                                       "\nNOT REGISTERED: " + reg.result))
    cam = reg.camera
    doc = {
        "result": reg.result, "registered": reg.registered,
        "T_cam_pc": _json_matrix(reg.T_cam_pc), "T_pc_cam": _json_matrix(reg.T_pc_cam),
        "conventions": POSE_HEADER, "units": "metres (the cloud's units)",
        "method": reg.method, "solver": reg.solver, "backend": reg.backend,
        "n_matches": reg.n_matches, "n_inliers": reg.n_inliers, "inlier_ratio": reg.inlier_ratio,
        "scale": None if math.isnan(reg.scale) else reg.scale,
        "depth_camera": {"name": cam.name, "why": cam.why, "virtual": cam.virtual, "K": cam.K.tolist(),
                         "size_hw": list(cam.size), "T_pc_sensor": cam.T_pc_sensor.tolist()},
        "ground_truth": {k: (bool(v) if isinstance(v, (bool, np.bool_)) else (None if math.isnan(float(v)) else float(v)))
                         for k, v in reg.errors.items()},
        "seconds": reg.seconds,
        "inputs": {k: reg.pair.meta.get(k) for k in ("image_path", "cloud_path")},
    }
    paths["json"] = out / "registration.json"
    paths["json"].write_text(json.dumps(doc, indent=2) + "\n")
    paths["candidates"] = out / "candidates.csv"
    pd.DataFrame(reg.candidates).to_csv(paths["candidates"], index=False)
    fig = matches_figure(reg)
    if fig is not None:
        paths["matches"] = plots.save(fig, "matches", out)
        plots._plt().close(fig)
    fig = overlay_figure(reg)
    paths["overlay"] = plots.save(fig, "overlay", out)
    plots._plt().close(fig)
    return paths


def _json_matrix(T: np.ndarray):
    return [[None if not math.isfinite(v) else float(v) for v in row] for row in np.asarray(T)]
