"""Derive the shipped TUM RGB-D sample (freereg_lib/data/tum_fr1_rpy) from TUM's original frames.

TUM's freiburg1 images are not undistorted, and the library's cameras are pinholes, so each frame is
undistorted with TUM's calibrated Plumb Bob model: the colour image bilinearly (saved as JPEG, quality 95,
as the ICL sample), the depth by nearest neighbour (a depth is never blended across an edge; saved as
16-bit PNG at TUM's scale, 5000 per metre). Poses and the README come from the raw folder as they are.

    python tools/derive_tum_sample.py RAW_FOLDER freereg_lib/data/tum_fr1_rpy

RAW_FOLDER holds color/NNNNN.png, depth/NNNNN.png (TUM's files, renamed by frame), intrinsics.json with
``distortion_k1_k2_p1_p2_k3``, trajectory.log and trajectory_depth.log.
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np


def main(raw: Path, out: Path) -> None:
    intr = json.loads((raw / "intrinsics.json").read_text())
    K = np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]], np.float64)
    dist = np.asarray(intr["distortion_k1_k2_p1_p2_k3"], np.float64)
    size = (int(intr["width"]), int(intr["height"]))
    map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K, size, cv2.CV_32FC1)
    (out / "color").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    for path in sorted((raw / "color").glob("*.png")):
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        cv2.imwrite(str(out / "color" / f"{path.stem}.jpg"), cv2.remap(bgr, map_x, map_y, cv2.INTER_LINEAR),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
        depth = cv2.imread(str(raw / "depth" / path.name), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.dtype != np.uint16:
            raise SystemExit(f"{raw / 'depth' / path.name}: expected a 16-bit depth PNG")
        cv2.imwrite(str(out / "depth" / path.name), cv2.remap(depth, map_x, map_y, cv2.INTER_NEAREST))
    kept = {k: intr[k] for k in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")}
    (out / "intrinsics.json").write_text(json.dumps(kept, indent=1) + "\n")
    for name in ("trajectory.log", "trajectory_depth.log", "frames.txt"):
        shutil.copyfile(raw / name, out / name)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
