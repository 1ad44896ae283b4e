"""Train the micro FCGF from scratch: FCGF's hardest-contrastive loss on synthetic room clouds.

    python -m freereg_lib.training.train_fcgf [--out runs/micro/train] [--pairs 240] [--steps 500]
        [--crop-radius 1.0] [--export freereg_lib/models/micro/weights/fcgf]

The network is the plain-torch ``ResUNetBN2C`` of :mod:`freereg_lib.models.fcgf` at the
paper's 3DMatch settings (conv1 kernel 7, 32-d output, 2.5 cm voxels), so the weights it
writes load with :func:`~freereg_lib.models.fcgf.load_fcgf` exactly as the official
checkpoints do.

Data (:func:`training_pairs`): pair ``k`` is ``synthetic.make_pair("indoor", seed=(TRAIN_STREAM,
k))``, a seed sequence that evaluation refuses to reach (:func:`freereg_lib.data.synthetic.check_eval_seed`). Its two clouds are the ones the
pipeline gives FCGF at inference (:func:`freereg_lib.pipeline.compute_features`):

* image side: the image's depth (here the true one), range-limited and edge-filtered as the
  monocular map is, back-projected in the camera frame;
* depth side: the pipeline's depth view of the cloud (projected, densified), back-projected
  in the depth camera's frame (as the official code hands it to FCGF);

each reduced to one point per 2.5 cm voxel. Positives are voxels within 1.5 voxels of each
other under the true pose (FCGF's ``positive_pair_search_voxel_size_multiplier``).

``--image-side``: ``depth`` trains on the pairs above (the kinds FCGF meets at inference);
``cloud`` replaces the image side by the cloud's view from the image camera, made as the depth
side is (projected, densified, back-projected), so both sides are of one kind, as FCGF's
3DMatch fragment pairs are; ``mix`` draws one of the two for each step.

A step, as FCGF's 3DMatch training: one pair; a ball of ``--crop-radius`` around a random
overlapping point cut from both clouds (a 2-core CPU cannot afford whole rooms); each side in
its own camera's frame as at inference (``--rotations inference``, the default), or rotated
uniformly at random (``so3``: FCGF's ``rotation_range`` 360 deg); the image side scaled by
``U(1 - s, 1 + s)`` (FCGF's ``use_random_scale``, on here with ``--scale-aug`` 0.1 because the
image side is a monocular depth cloud at inference); both re-voxelised and passed through the
network as one sparse batch. Loss: FCGF's hardest-contrastive loss (threshold 0.1 on the
squared positive distance, 1.4 on the negative one, 1024 positives, 256 hardest-negative
candidates a side). Optimiser: AdamW
(:func:`~freereg_lib.training.train_diffusion.run_stage`, seeded per step, checkpoints, resume),
not FCGF's SGD: a few hundred steps, not 100 epochs.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from freereg_lib.data.synthetic.seeds import TRAIN_FCGF_PAIRS
from freereg_lib.models.micro.fcgf import VOXEL, build, save
from freereg_lib.training.views import progress_map

TRAIN_STREAM = TRAIN_FCGF_PAIRS  # 0xF3EE0002
CACHE_FRAMES = "camera-camera+cloud-view"  # both clouds in their camera's frame, and the image camera's cloud view
IMAGE_SIDES = ("depth", "cloud", "mix")
POS_RADIUS = 1.5 * VOXEL  # FCGF: positive_pair_search_voxel_size_multiplier x voxel
POS_MARGIN, NEG_MARGIN = 0.1, 1.4
NUM_POS, NUM_HN = 1024, 256
VAL_PAIRS = 4  # held out from the end of the training stream; --val-crops fixed crops and rotations each
BATCH_SHIFT = 1 << 14  # voxels between the two clouds of a batch (a multiple of the deepest stride)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="runs/micro/train", help="checkpoints and logs")
    p.add_argument("--pairs-file", default=None, help="cached training clouds (.npz); default OUT/../fcgf_pairs.npz")
    p.add_argument("--pairs", type=int, default=240, help="training pairs (plus %d validation pairs)" % VAL_PAIRS)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--warmup", type=int, default=50, help="linear learning-rate warm-up steps")
    p.add_argument("--crop-radius", type=float, default=1.0, help="metres around the crop's centre")
    p.add_argument("--scale-aug", type=float, default=0.1, help="image-side scale drawn from U(1-s, 1+s)")
    p.add_argument("--rotations", choices=("inference", "so3"), default="inference",
                   help="each side in its own camera's frame, as at inference, or FCGF's uniform SO(3)")
    p.add_argument("--image-side", choices=IMAGE_SIDES, default="depth",
                   help="the image side's cloud: its depth (as at inference), the cloud's view from the image "
                        "camera (the depth side's kind), or either, drawn per step")
    p.add_argument("--val-crops", type=int, default=1,
                   help="fixed crops per validation pair (the hit ratio of one crop a pair is noisy)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=50)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    p.add_argument("--workers", type=int, default=None, help="processes rendering the pairs")
    p.add_argument("--export", default=None, help="write the trained weights to this folder")
    return p.parse_args(argv)


# ------------------------------------------------------------------------------- data

def pair_clouds(pair, cfg=None) -> tuple[np.ndarray, np.ndarray]:
    """The two clouds the pipeline hands FCGF for ``pair``, with the image side's true depth:
    ``(image side (Na, 3) image camera's frame, depth side (Nb, 3) depth camera's frame)``, float64."""
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.geometry import cameras, projection
    from freereg_lib.pipeline import depth_view

    cfg = cfg or FreeRegConfig()
    d = np.asarray(pair.depth_gt, dtype=np.float64)
    d = np.where((d > cfg.depth_min) & (d < cfg.depth_max), d, 0.0)
    if cfg.edge_filter_m > 0:
        d = projection.edge_filter(d, cfg.edge_filter_m)
    image_side = cameras.backproject(d, pair.K_image)[0]
    depth_side = cameras.backproject(depth_view(pair, cfg).dense, pair.K_depth)[0]
    return image_side, depth_side


def cloud_view_from_image_camera(pair, cfg=None) -> np.ndarray:
    """The cloud as the pipeline would make a depth side of it from the image camera
    (projected, densified, back-projected): ``(N, 3)`` float64 in the image camera's frame."""
    from dataclasses import replace

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.geometry import cameras
    from freereg_lib.pipeline import depth_view

    cfg = cfg or FreeRegConfig()
    seen = replace(pair, K_depth=pair.K_image, depth_size=pair.image_size,
                   T_pc_sensor=cameras.invert(pair.T_cam_pc), sensor_depth=None)
    return cameras.backproject(depth_view(seen, cfg).dense, pair.K_image)[0]


def one_per_voxel(points: np.ndarray, voxel: float = VOXEL) -> np.ndarray:
    """The first point of each voxel (FCGF's quantisation), ``(M, 3)``."""
    from freereg_lib.models.fcgf import voxelize

    return np.asarray(points)[voxelize(points, voxel)[1]]


def _training_pair(k: int) -> dict:
    from freereg_lib.data import synthetic as S

    pair = S.make_pair("indoor", seed=(TRAIN_STREAM, int(k)))
    a, b = pair_clouds(pair)
    return {"a": one_per_voxel(a).astype(np.float32), "b": one_per_voxel(b).astype(np.float32),
            "a_cloud": one_per_voxel(cloud_view_from_image_camera(pair)).astype(np.float32),
            "T": pair.T_cam_pc @ pair.T_pc_sensor}


def training_pairs(n: int, first: int = 0, workers: int | None = None, progress: bool = True) -> list[dict]:
    """Clouds of training pairs ``first .. first + n - 1``: ``a`` image side, ``b`` depth
    side, each in its camera's frame, ``a_cloud`` the cloud's view from the image camera
    (:func:`cloud_view_from_image_camera`), one point per voxel, float32; ``T`` the true pose
    of the depth camera in the image camera (``T_cam_pc @ T_pc_sensor``)."""
    return progress_map(_training_pair, list(range(first, first + n)), workers, "rendering training pairs", "pair",
                        progress, chunksize=2)


def load_or_make_pairs(path: Path, n: int, workers: int | None = None) -> list[dict]:
    """The cached clouds of the first ``n`` pairs in ``path`` (made and saved when absent, or
    when the cache holds another count or frames)."""
    path = Path(path)
    if path.exists():
        with np.load(path) as z:
            if int(z["n"]) == n and "frames" in z and str(z["frames"]) == CACHE_FRAMES:
                return [{key: z[f"{key}{k}"] for key in ("a", "b", "a_cloud", "T")} for k in range(n)]
    pairs = training_pairs(n, workers=workers)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    arrays = {f"{key}{k}": p[key] for k, p in enumerate(pairs) for key in ("a", "b", "a_cloud", "T")}
    np.savez(tmp, n=n, frames=CACHE_FRAMES, **arrays)
    os.replace(tmp, path)
    return pairs


# --------------------------------------------------------------------------- batches

def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly from SO(3) (a normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def positive_pairs(a: np.ndarray, b: np.ndarray, radius: float = POS_RADIUS) -> np.ndarray:
    """``(P, 2)`` index pairs ``(i, j)`` with ``|a_i - b_j| <= radius`` (same frame), sorted."""
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), np.int64)
    hits = cKDTree(b).query_ball_point(a, radius)
    i = np.repeat(np.arange(len(a)), [len(h) for h in hits])
    j = np.fromiter((x for h in hits for x in sorted(h)), dtype=np.int64, count=len(i))
    return np.stack([i, j], axis=1)


def make_batch(pair: dict, rng: np.random.Generator, crop_radius: float, scale_aug: float,
               rotations: str = "inference", image_side: str = "depth") -> dict | None:
    """One training batch of a pair: voxel coordinates of both crops (``coords_a``,
    ``coords_b``), their positive pairs (``pos``), the crops' points (``points_a``,
    ``points_b``, one per voxel) and each side's camera centre in its crop's frame
    (``camera_a``, ``camera_b``: FPFH orients normals towards it); None when the crop holds
    no positive.

    ``rotations``: ``"inference"`` keeps each side in its own camera's frame, as the pipeline
    hands them to FCGF; ``"so3"`` rotates each side uniformly at random (FCGF's 3DMatch recipe).
    ``image_side``: the image side's cloud, ``"depth"`` (``pair["a"]``), ``"cloud"``
    (``pair["a_cloud"]``) or ``"mix"`` (either, drawn from ``rng``)."""
    from freereg_lib.models.fcgf import voxelize

    if image_side == "mix":
        image_side = "cloud" if rng.random() < 0.5 else "depth"
    if image_side not in ("depth", "cloud"):
        raise ValueError(f"image_side must be one of {IMAGE_SIDES}, got {image_side!r}")
    T = np.asarray(pair["T"], dtype=np.float64)
    a = np.asarray(pair["a" if image_side == "depth" else "a_cloud"], dtype=np.float64)
    b_cam = np.asarray(pair["b"], dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    near = positive_pairs(a, b_cam)
    if len(near) == 0:
        return None
    centre = a[near[rng.integers(len(near)), 0]]
    in_b = np.linalg.norm(b_cam - centre, axis=1) <= crop_radius
    a = a[np.linalg.norm(a - centre, axis=1) <= crop_radius]
    b_cam = b_cam[in_b]
    scale = rng.uniform(1 - scale_aug, 1 + scale_aug) if scale_aug > 0 else 1.0
    if rotations == "so3":
        ra, rb = random_rotation(rng), random_rotation(rng)
        b_side = (b_cam - centre) @ rb.T
        camera_b = (T[:3, 3] - centre) @ rb.T
    else:  # each side in its own camera's frame, as at inference
        ra = np.eye(3)
        b_own = np.asarray(pair["b"], dtype=np.float64)[in_b]
        b_side = b_own - b_own.mean(0)
        camera_b = -b_own.mean(0)
    a_side = ((a - centre) * scale) @ ra.T
    coords_a, sel_a = voxelize(a_side, VOXEL)
    coords_b, sel_b = voxelize(b_side, VOXEL)
    pos = positive_pairs(a[sel_a], b_cam[sel_b])
    if len(pos) == 0:
        return None
    return {"coords_a": coords_a, "coords_b": coords_b, "pos": pos, "points_a": a_side[sel_a],
            "points_b": b_side[sel_b], "camera_a": ((-centre) * scale) @ ra.T, "camera_b": camera_b}


def baseline_hit_ratios(batches: list[dict], seed: int = 0) -> dict:
    """What a trained network has to beat on ``batches``: the mean hit ratio of FPFH (the
    pipeline's radii at its 5 cm FPFH voxel, normals facing each camera, computed on the
    crops' voxels) and of random unit features (chance)."""
    import torch

    from freereg_lib.config import FreeRegConfig
    from freereg_lib.features.geometric import fpfh_features

    cfg = FreeRegConfig()
    r_normal, r_feature = cfg.normal_radius_factor * cfg.fpfh_voxel, cfg.fpfh_radius_factor * cfg.fpfh_voxel
    g = torch.Generator().manual_seed(seed)
    fpfh, chance = [], []
    for b in batches:
        args = (b["pos"], b["coords_a"], b["coords_b"])
        fa = fpfh_features(b["points_a"], 0, r_normal, r_feature, camera_location=b["camera_a"])[1]
        fb = fpfh_features(b["points_b"], 0, r_normal, r_feature, camera_location=b["camera_b"])[1]
        fpfh.append(hit_ratio(torch.from_numpy(fa.astype(np.float32)), torch.from_numpy(fb.astype(np.float32)), *args))
        ra = torch.nn.functional.normalize(torch.randn(len(b["coords_a"]), 32, generator=g), dim=1)
        rb = torch.nn.functional.normalize(torch.randn(len(b["coords_b"]), 32, generator=g), dim=1)
        chance.append(hit_ratio(ra, rb, *args))
    return {"fpfh": float(np.mean(fpfh)), "chance": float(np.mean(chance))}


def forward_pair(net, batch: dict):
    """Features of both crops from one pass (cloud B shifted far along x, as ME batches)."""
    import torch

    from freereg_lib.models.fcgf import SparseTensor

    cb = batch["coords_b"].copy()
    cb[:, 0] += BATCH_SHIFT
    coords = torch.from_numpy(np.concatenate([batch["coords_a"], cb]))
    out = net(SparseTensor(coords, torch.ones(len(coords), net.conv1.cin)))
    na = len(batch["coords_a"])
    return out.feats[:na], out.feats[na:]


def hardest_contrastive(fa, fb, pos: np.ndarray, g, num_pos: int = NUM_POS, num_hn: int = NUM_HN):
    """FCGF's ``contrastive_hardest_negative_loss``: ``pos_loss + (neg_loss_a + neg_loss_b) / 2``.

    Positives (``pos`` index pairs, at most ``num_pos`` drawn) are pulled until their
    *squared* feature distance is within ``POS_MARGIN`` (FCGF's ``pos_thresh``, applied to
    ``|f_a - f_b|^2``); for each, the nearest of ``num_hn`` random candidates of the other
    side, unless it is itself a positive of that point, is pushed beyond ``NEG_MARGIN`` in
    distance, squared hinge.
    """
    import torch

    na, nb = len(fa), len(fb)
    pos_t = torch.from_numpy(pos)
    if len(pos_t) > num_pos:
        pos_t = pos_t[torch.randperm(len(pos_t), generator=g)[:num_pos]]
    ia, ib = pos_t[:, 0], pos_t[:, 1]
    sel_a = torch.randperm(na, generator=g)[:min(na, num_hn)]
    sel_b = torch.randperm(nb, generator=g)[:min(nb, num_hn)]
    pos_keys = torch.from_numpy(pos[:, 0] * nb + pos[:, 1])

    def dist(x, y):
        return torch.sqrt(torch.clamp((x[:, None, :] - y[None, :, :]).pow(2).sum(-1), min=1e-7))

    d_ab = dist(fa[ia], fb[sel_b])  # anchors of A against candidates of B
    d_ba = dist(fb[ib], fa[sel_a])
    min_ab, arg_ab = d_ab.min(1)
    min_ba, arg_ba = d_ba.min(1)
    mask_a = ~torch.isin(ia * nb + sel_b[arg_ab], pos_keys)
    mask_b = ~torch.isin(sel_a[arg_ba] * nb + ib, pos_keys)
    pos_loss = torch.relu((fa[ia] - fb[ib]).pow(2).sum(1) - POS_MARGIN).mean()
    neg_a = torch.relu(NEG_MARGIN - min_ab[mask_a]).pow(2).mean() if mask_a.any() else fa.sum() * 0
    neg_b = torch.relu(NEG_MARGIN - min_ba[mask_b]).pow(2).mean() if mask_b.any() else fa.sum() * 0
    return pos_loss + (neg_a + neg_b) / 2


def hit_ratio(fa, fb, pos: np.ndarray, coords_a, coords_b, tau: float = 0.1) -> float:
    """FCGF's hit ratio on a crop: the share of image-side voxels with a positive whose feature
    nearest neighbour on the other side lies within ``tau`` metres of a true partner (distance
    measured between the voxels' own positives, so rotations do not matter)."""
    import torch

    anchors = np.unique(pos[:, 0])
    nn = torch.cdist(fa[torch.from_numpy(anchors)], fb).argmin(1).numpy()
    # A prediction is a hit when the predicted voxel b lies within tau of some partner of a:
    # with the crop's B voxels in a common frame that is the partners' spread (<= POS_RADIUS).
    partners: dict[int, list[int]] = {}
    for i, j in pos:
        partners.setdefault(int(i), []).append(int(j))
    b = np.asarray(coords_b, dtype=np.float64) * VOXEL
    hits = 0
    for k, i in enumerate(anchors):
        # coords_b are rotated, but distances within B are not: compare B to B.
        d = np.linalg.norm(b[partners[int(i)]] - b[nn[k]], axis=1).min()
        hits += d <= tau
    return float(hits / max(len(anchors), 1))


# ----------------------------------------------------------------------------- training

def main(argv=None) -> int:
    import torch

    from freereg_lib.training.train_diffusion import run_stage

    args = parse_args(argv)
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pairs = load_or_make_pairs(Path(args.pairs_file or out.parent / "fcgf_pairs.npz"),
                               args.pairs + VAL_PAIRS, args.workers)
    train, val = pairs[:args.pairs], pairs[args.pairs:]
    sizes = np.array([[len(p["a"]), len(p["b"])] for p in train])
    print(f"{len(train)} training pairs, {len(val)} validation pairs; voxels per cloud "
          f"{int(sizes.mean())} on average", flush=True)
    net = build(args.seed)

    def draw(rng, p, image_side=args.image_side):
        while True:
            batch = make_batch(p(rng), rng, args.crop_radius, args.scale_aug, args.rotations, image_side)
            if batch is not None:
                return batch

    def loss_fn(rng, g):
        batch = draw(rng, lambda r: train[r.integers(len(train))])
        fa, fb = forward_pair(net, batch)
        return hardest_contrastive(fa, fb, batch["pos"], g)

    # Validation crops always pair the kinds of inference (image side on its depth); a run on
    # same-kind clouds also reports its hit ratio on same-kind crops of the same places.
    kinds = {"": "depth"} if args.image_side == "depth" else {"": "depth", "_same_kind": "cloud"}
    val_batches = {suffix: [] for suffix in kinds}
    for suffix, side in kinds.items():
        for k, p in enumerate(val):
            for c in range(args.val_crops):
                rng = np.random.default_rng((args.seed, k) if c == 0 else (args.seed, k, c))
                val_batches[suffix].append(draw(rng, lambda r, p=p: p, side))

    baselines = {suffix: baseline_hit_ratios(batches) for suffix, batches in val_batches.items()}
    for suffix, base in baselines.items():
        print(f"validation crops{suffix.replace('_', ' ')}: hit ratio of FPFH {100 * base['fpfh']:.1f} %, "
              f"of random features (chance) {100 * base['chance']:.1f} %", flush=True)

    def val_fn():
        out = {}
        for suffix, batches in val_batches.items():
            g = torch.Generator().manual_seed(0)
            losses, hits = [], []
            for batch in batches:
                fa, fb = forward_pair(net, batch)
                losses.append(float(hardest_contrastive(fa, fb, batch["pos"], g)))
                hits.append(hit_ratio(fa, fb, batch["pos"], batch["coords_a"], batch["coords_b"]))
            out.update({"loss" + suffix: float(np.mean(losses)), "hit_ratio" + suffix: float(np.mean(hits))})
        return out

    log = run_stage("fcgf", net, loss_fn, val_fn, args.steps, args.lr, args, out)
    seconds = time.perf_counter() - t_start
    if args.export:
        facts = {
            "arguments": {k: v for k, v in vars(args).items()
                          if k not in ("out", "pairs_file", "export", "threads", "workers")},
            "train_stream": f"synthetic.make_pair('indoor', seed=({TRAIN_STREAM:#x}, k)) for k in 0..pairs-1",
            "validation_pairs": f"k = pairs .. pairs + {VAL_PAIRS - 1} of the same stream",
            "voxels_per_cloud_mean": int(sizes.mean()),
            "parameters_millions": round(sum(p.numel() for p in net.parameters()) / 1e6, 3),
            "step_seconds": round(log["seconds"], 1),
            "last_run_seconds": round(seconds, 1),
            "steps": log["steps"], "loss": log["loss"], "val": log["val"],
            "val_baselines": baselines,
        }
        print(f"weights written to {save(net, Path(args.export), facts)}", flush=True)
    print(f"total time {seconds / 60:.1f} min", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
