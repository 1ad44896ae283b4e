"""Training views for the micro models, rendered from the synthetic world.

Scenes are drawn from ``numpy.random.default_rng((TRAIN_STREAM, k))`` (:func:`room_rng`): a seed
sequence of two words. NumPy reads the integer ``TRAIN_STREAM + k * 2**32`` as the same two words,
so an integer seed *can* reproduce room ``k``; evaluation refuses such seeds
(:func:`freereg_lib.data.synthetic.check_eval_seed`, in ``make_pair`` and the evaluation commands), so no
evaluation pair shares a room with the training data.

Each view is a camera of a training room rendered at the synthetic pairs' size (480 x 640),
then reduced to what the models see, exactly as the pipeline makes it at inference:

* ``rgb``: the image resized to the diffusion input by the official rule
  (:func:`~freereg_lib.models.base.rgb_to_unit`'s resize), ``(3, h, w) uint8``;
* ``hint``: the ControlNet hint of the same camera made as at inference: the camera's depth
  back-projected, subsampled to the synthetic cloud size, projected back on the camera,
  densified per ``cfg.densify`` (:func:`freereg_lib.pipeline.depth_view`), normalised by the
  official rule and resized (:func:`~freereg_lib.models.base.depth_hint`), ``(3, h, w) uint8``;
* ``depth``: the true depth at ``depth_hw`` (nearest), ``(h_d, w_d) float32`` metres, for the
  depth model.
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freereg_lib.data.synthetic.seeds import TRAIN_ROOMS

TRAIN_STREAM = TRAIN_ROOMS  # 0xF3EE0001
RENDER_HW = (480, 640)
DIFFUSION_HW = (128, 192)
DEPTH_HW = (120, 160)
# "indoor": the blocks world the committed weights were trained in; "rooms": the calibrated world.
WORLD_KINDS = ("indoor", "rooms")


# A rooms camera can stand inside a piece of furniture whose footprint the free-space test misses
# (training room 931: no pixel between 0.05 and 10 m); such a view is drawn again. The blocks world
# never redraws, so its views stay the committed models' training views.
OPEN_DEPTH_M = (0.3, 10.0)
MIN_OPEN_SHARE = 0.5
BLOCKED_REDRAWS = 10


def room_rng(k: int) -> np.random.Generator:
    """The generator of training room ``k``."""
    return np.random.default_rng((TRAIN_STREAM, int(k)))


def _scene_views(args) -> dict[str, np.ndarray]:
    """All views of training room ``k`` (run in a worker process): ``(k, views_per_scene, kind)``, or
    with a fourth item ``sense``, which turns each view's depth frame into a sensor's before its cloud
    is made (``sense.rng(k)`` draws the artefacts and the sensed cloud's subsample; ``sense(depth, rng)``
    returns the sensed frame; the cameras, images and ``depth`` stay the clean ones)."""
    k, views_per_scene, kind, *rest = args
    sense = rest[0] if rest else None
    import cv2

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data.pair import Pair
    from freereg_lib.data.synthetic import rooms
    from freereg_lib.data.synthetic.indoor import _indoor_camera, _indoor_scene
    from freereg_lib.data.synthetic.pairs import _subsample
    from freereg_lib.geometry.cameras import backproject, intrinsics, invert, transform
    from freereg_lib.models.base import depth_hint, resize_to
    from freereg_lib.pipeline import depth_view

    if kind not in WORLD_KINDS:
        raise ValueError(f"training views exist for the indoor worlds only {WORLD_KINDS}, got kind={kind!r}")
    scene_of, camera_of = (_indoor_scene, _indoor_camera) if kind == "indoor" else (rooms._room_scene, rooms._scan_camera)
    cfg = FreeRegConfig()
    rng = room_rng(k)
    art = sense.rng(k) if sense is not None else None
    scene, room = scene_of(rng)
    H, W = RENDER_HW
    f = 525.0 * W / 640
    K = intrinsics(f, f, (W - 1) / 2, (H - 1) / 2)
    out = {"rgb": [], "hint": [], "depth": []}
    for _ in range(views_per_scene):
        for _draw in range(1 + (BLOCKED_REDRAWS if kind == "rooms" else 0)):
            T_world_cam = camera_of(rng, room)
            hits, depth, _ids = scene.camera_view(T_world_cam, K, RENDER_HW)
            if kind != "rooms" or np.mean((depth > OPEN_DEPTH_M[0]) & (depth < OPEN_DEPTH_M[1])) >= MIN_OPEN_SHARE:
                break
        image = scene.shade(hits, RENDER_HW)
        if sense is None:
            pts = transform(T_world_cam, backproject(depth, K)[0])
            pts = pts[_subsample(rng, len(pts))]
        else:
            pts = transform(T_world_cam, backproject(sense(depth, art), K)[0])
            # The room stream draws the clean cloud's subsample all the same, so that the next camera is
            # the clean views' next camera; the sensed cloud is subsampled on the artefact stream.
            _subsample(rng, int(np.count_nonzero(depth > 0)))
            pts = pts[_subsample(art, len(pts))]
        pair = Pair(image=image, K_image=K, points=pts, K_depth=K.copy(), depth_size=RENDER_HW,
                    T_pc_sensor=T_world_cam, T_cam_pc=invert(T_world_cam), name=f"train/{k}")
        dense = depth_view(pair, cfg).dense
        out["rgb"].append(resize_to(image, DIFFUSION_HW).transpose(2, 0, 1))
        out["hint"].append(np.rint(depth_hint(dense, DIFFUSION_HW) * 255).astype(np.uint8))
        out["depth"].append(cv2.resize(depth.astype(np.float32), DEPTH_HW[::-1],
                                       interpolation=cv2.INTER_NEAREST))
    return {key: np.stack(v) for key, v in out.items()}


def render_views(n_scenes: int, views_per_scene: int = 4, first_scene: int = 0,
                 kind: str = "indoor", workers: int | None = None,
                 progress: bool = True) -> dict[str, np.ndarray]:
    """Views of training rooms ``first_scene .. first_scene + n_scenes - 1``.

    Returns ``rgb (N, 3, 128, 192) uint8``, ``hint (N, 3, 128, 192) uint8``,
    ``depth (N, 120, 160) float32`` with ``N = n_scenes * views_per_scene``, in scene order
    (the same arguments give identical arrays whatever ``workers`` is).
    """
    jobs = [(k, views_per_scene, kind) for k in range(first_scene, first_scene + n_scenes)]
    parts = progress_map(_scene_views, jobs, workers, "rendering training rooms", "room", progress, chunksize=4)
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def progress_map(fn, jobs: list, workers: int | None, desc: str, unit: str, progress: bool = True,
                 chunksize: int = 1) -> list:
    """``[fn(job) for job in jobs]`` in order, over ``workers`` processes (default: one per
    core, at most one per job) with a progress bar; one worker runs in this process."""
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    out = []
    with tqdm(total=len(jobs), desc=desc, unit=unit, disable=not progress) as bar:
        if workers <= 1:
            for item in map(fn, jobs):
                out.append(item)
                bar.update()
        else:
            with ProcessPoolExecutor(workers) as pool:
                for item in pool.map(fn, jobs, chunksize=chunksize):
                    out.append(item)
                    bar.update()
    return out


def load_or_render(path: str | Path, n_scenes: int, views_per_scene: int = 4,
                   progress: bool = True, kind: str = "indoor") -> dict[str, np.ndarray]:
    """The views cached in ``path`` (``.npz``), rendered and saved first when absent or made
    with other counts or in another world (``kind``, :data:`WORLD_KINDS`)."""
    path = Path(path)
    if path.exists():
        with np.load(path) as z:
            cached_kind = str(z["kind"]) if "kind" in z.files else "indoor"
            if int(z["n_scenes"]) == n_scenes and int(z["views_per_scene"]) == views_per_scene and cached_kind == kind:
                return {k: z[k] for k in ("rgb", "hint", "depth")}
    views = render_views(n_scenes, views_per_scene, kind=kind, progress=progress)
    save_views(views, path, n_scenes, views_per_scene, kind)
    return views


def save_views(views: dict[str, np.ndarray], path: str | Path, n_scenes: int, views_per_scene: int,
               kind: str = "indoor") -> None:
    """Cache ``views`` in ``path`` (``.npz``) as :func:`load_or_render` reads them; written whole
    or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, n_scenes=n_scenes, views_per_scene=views_per_scene, kind=kind, **views)
    os.replace(tmp, path)
