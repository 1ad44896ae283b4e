"""The micro FCGF: its training pieces on hand-made cases, a few steps lower the loss, training
resumes exactly, the weights round-trip through the official checkpoints' loader, and the
micro backend hands its network to the pipeline."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from freereg_lib.models.micro import fcgf as MF  # noqa: E402
from freereg_lib.training import train_fcgf as T  # noqa: E402


def _pair(seed: int = 0, n: int = 500, size: float = 0.4) -> dict:
    """Two views of one small box corner: the same surface sampled twice, B in its own camera's
    frame, ``T`` its pose in A's."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, size, (2, n))
    faces = np.stack([np.stack([u, v, 0 * u], 1), np.stack([u, 0 * u, v], 1), np.stack([0 * u, u, v], 1)])
    a = faces.reshape(-1, 3)
    R = T.random_rotation(np.random.default_rng(seed + 1))
    T_a_b = np.eye(4)
    T_a_b[:3, :3], T_a_b[:3, 3] = R, [0.1, -0.2, 0.3]
    b_in_a = a + rng.normal(0, 0.002, a.shape)
    b = (b_in_a - T_a_b[:3, 3]) @ R  # into B's frame: T_a_b maps it back
    return {"a": MF_one(a), "b": MF_one(b), "T": T_a_b}


def MF_one(p):
    return T.one_per_voxel(p).astype(np.float32)


def test_random_rotation_is_a_rotation():
    R = T.random_rotation(np.random.default_rng(3))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_positive_pairs_exact():
    a = np.array([[0.0, 0, 0], [1, 0, 0], [5, 5, 5]])
    b = np.array([[0.01, 0, 0], [1.0, 0.02, 0], [1.0, -0.03, 0], [9, 9, 9]])
    pos = T.positive_pairs(a, b, radius=0.0375)
    assert pos.tolist() == [[0, 0], [1, 1], [1, 2]]
    assert T.positive_pairs(a, b[:0]).shape == (0, 2)


def test_batch_positives_agree_with_the_true_pose(monkeypatch):
    # Without rotations both crops sit in the camera frame around one centre, so each positive
    # pair's voxels are at most POS_RADIUS apart, plus a voxel of quantisation each side.
    monkeypatch.setattr(T, "random_rotation", lambda rng: np.eye(3))
    batch = T.make_batch(_pair(), np.random.default_rng(0), crop_radius=0.5, scale_aug=0.0, rotations="so3")
    assert batch is not None and len(batch["pos"]) > 100
    ia, ib = batch["pos"][:, 0], batch["pos"][:, 1]
    gap = np.linalg.norm((batch["coords_a"][ia] - batch["coords_b"][ib]) * T.VOXEL, axis=1)
    assert gap.max() <= T.POS_RADIUS + 2 * np.sqrt(3) * T.VOXEL
    assert np.median(gap) < 2 * T.VOXEL


def test_inference_frames_keep_the_positives_rigid():
    # Each side in its own frame: positives still match under one rigid motion, so distances
    # between positives agree on both sides up to quantisation.
    batch = T.make_batch(_pair(), np.random.default_rng(2), crop_radius=0.5, scale_aug=0.0)
    pos = batch["pos"][np.random.default_rng(0).choice(len(batch["pos"]), 200, replace=False)]
    a = batch["coords_a"][pos[:, 0]] * T.VOXEL
    b = batch["coords_b"][pos[:, 1]] * T.VOXEL
    da = np.linalg.norm(a[:, None] - a[None], axis=-1)
    db = np.linalg.norm(b[:, None] - b[None], axis=-1)
    assert np.abs(da - db).max() < 2 * T.POS_RADIUS + 4 * np.sqrt(3) * T.VOXEL
    assert np.median(np.abs(da - db)) < 2 * T.VOXEL
    # ... and each side stays in its own camera's frame, as the pipeline hands them to FCGF:
    # the rotation between the crops is the pair's true one, with no turn added.
    assert np.median(np.linalg.norm(a - b, axis=1)) > 3 * T.VOXEL
    u, _, vt = np.linalg.svd((a - a.mean(0)).T @ (b - b.mean(0)))
    R_fit = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    R_true = _pair()["T"][:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R_fit.T @ R_true) - 1) / 2, -1, 1)))
    assert angle < 3.0


def test_hardest_contrastive_is_zero_for_perfect_features():
    # Positives share a feature, negatives are orthogonal: within both margins, loss 0.
    fa = torch.eye(4)
    fb = torch.eye(4)
    pos = np.array([[0, 0], [1, 1], [2, 2], [3, 3]])
    loss = T.hardest_contrastive(fa, fb, pos, torch.Generator().manual_seed(0), num_hn=4)
    # Orthogonal unit vectors are sqrt(2) = 1.414 apart, beyond the 1.4 negative margin.
    assert float(loss) == pytest.approx(0.0, abs=1e-6)
    swapped = T.hardest_contrastive(fa, fb[[1, 0, 3, 2]], pos, torch.Generator().manual_seed(0), num_hn=4)
    assert float(swapped) > 1.0


def test_hardest_contrastive_is_fcgfs_loss_on_a_hand_made_case():
    # FCGF's positive term hinges the *squared* distance at 0.1: partners (1, 0) and (0.6, 0.8)
    # are 0.8 apart squared, so 0.7; a side of one point has no negative (its hardest
    # candidate is its own positive, masked out).
    fa, fb = torch.tensor([[1.0, 0.0]]), torch.tensor([[0.6, 0.8]])
    loss = T.hardest_contrastive(fa, fb, np.array([[0, 0]]), torch.Generator().manual_seed(0))
    assert float(loss) == pytest.approx(0.7, abs=1e-6)
    # Partners (0, 0) and (0, 1): 1 - 0.1 = 0.9. A's anchor is nearest to B's (0, 0.4), 0.4 away:
    # (1.4 - 0.4)^2 = 1; B's anchor to A's (0, 0.5): (1.4 - 0.5)^2 = 0.81; the sides averaged.
    fa2, fb2 = torch.tensor([[0.0, 0.0], [0.0, 0.5]]), torch.tensor([[0.0, 1.0], [0.0, 0.4]])
    loss2 = T.hardest_contrastive(fa2, fb2, np.array([[0, 0]]), torch.Generator().manual_seed(0))
    assert float(loss2) == pytest.approx(0.9 + (1.0 + 0.81) / 2, abs=1e-5)


def test_a_few_steps_lower_the_loss_on_a_fixed_batch():
    net = MF.build(0).train()
    # A 0.3 m crop: 290 voxels a side, not 510, a quarter less CPU a step; the loss falls by a
    # quarter over the 4 steps as on the 0.5 m crop (1.47 -> 1.11 here, 1.50 -> 1.07 there).
    batch = T.make_batch(_pair(), np.random.default_rng(1), crop_radius=0.3, scale_aug=0.0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    losses = []
    for _ in range(4):
        fa, fb = T.forward_pair(net, batch)
        loss = T.hardest_contrastive(fa, fb, batch["pos"], torch.Generator().manual_seed(0))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.85 * losses[0], losses


def test_training_resumes_bit_identical(tmp_path):
    import json as _json

    pairs = [_pair(0), _pair(1), _pair(2)]
    cache = tmp_path / "pairs.npz"
    arrays = {f"{k}{i}": p[k] for i, p in enumerate(pairs) for k in ("a", "b", "T")}
    arrays.update({f"a_cloud{i}": p["a"] for i, p in enumerate(pairs)})
    np.savez(cache, n=3, frames=T.CACHE_FRAMES, **arrays)
    common = ["--pairs", "2", "--pairs-file", str(cache), "--crop-radius", "0.3", "--threads", "1",
              "--checkpoint-every", "1", "--warmup", "2"]
    T.VAL_PAIRS = 1
    try:
        # The straight run checkpoints only at its end (the later flag wins): not interrupted,
        # it needs no step-1 checkpoint, and each costs a validation and a ~100 MB write.
        T.main(common + ["--out", str(tmp_path / "a"), "--steps", "2", "--export", str(tmp_path / "wa"),
                         "--checkpoint-every", "2"])
        T.main(common + ["--out", str(tmp_path / "b"), "--steps", "1"])
        T.main(common + ["--out", str(tmp_path / "b"), "--steps", "2", "--export", str(tmp_path / "wb")])
    finally:
        T.VAL_PAIRS = 4
    a = (tmp_path / "wa" / MF.WEIGHTS_FILE).read_bytes()
    b = (tmp_path / "wb" / MF.WEIGHTS_FILE).read_bytes()
    assert a == b
    facts = _json.loads((tmp_path / "wb" / "training.json").read_text())
    assert len(facts["loss"]) == 2 and facts["val"][-1][0] == 2


def test_weights_round_trip_through_the_official_loader(tmp_path):
    from freereg_lib.models.fcgf import fcgf_features, load_fcgf

    net = MF.build(5).eval()
    MF.save(net, tmp_path)
    loaded = load_fcgf(str(tmp_path / MF.WEIGHTS_FILE))
    assert loaded.conv1.kernel_size == 7
    pts = _pair()["a"].astype(np.float64)
    _, f0 = fcgf_features(pts, MF.VOXEL, net)
    _, f1 = fcgf_features(pts, MF.VOXEL, loaded)
    # float16 on disk: features agree to float16 precision, not bit for bit.
    assert np.abs(f0 - f1).max() < 2e-2
    with pytest.raises(FileNotFoundError, match="train_fcgf --export"):
        MF.load(tmp_path / "nowhere")


def test_micro_backend_gives_the_pipeline_its_fcgf():
    from freereg_lib import pipeline
    from freereg_lib.config import FreeRegConfig
    from freereg_lib.data import synthetic
    from freereg_lib.models import get_backend

    cfg = replace(FreeRegConfig(), geometric="fcgf")
    backend = get_backend("micro", cfg, random_weights=True)
    # 60 x 80: the clouds keep the same 1408 keypoints, and FCGF's sparse convolutions run on
    # fewer voxels (0.8 s, not 1.9 s, for both sides).
    pair = synthetic.make_pair("indoor", seed=7, image_size=(60, 80))
    feats = pipeline.compute_features(pair, backend, cfg, diffusion=False, geometric=True, mono=pair.depth_gt)
    assert feats.geo_image.shape[1] == 32 and feats.geo_depth.shape[1] == 32
    norms = np.linalg.norm(feats.geo_depth, axis=1)
    assert np.all((np.abs(norms - 1) < 1e-4) | (norms == 0))
    # The FPFH config of the same backend gives FPFH's 33-d features: the choice is cfg's.
    fp = pipeline.compute_features(pair, backend, replace(cfg, geometric="fpfh"), diffusion=False, geometric=True,
                                   mono=pair.depth_gt)
    assert fp.geo_image.shape[1] == 33


def test_recent_fcgf_features_come_from_memory_only_for_the_same_cloud_and_network(monkeypatch):
    from freereg_lib.features import geometric
    from freereg_lib.models import fcgf as F

    net = MF.build(1).eval()
    calls = []
    real = F.fcgf_features
    monkeypatch.setattr(F, "fcgf_features", lambda *a, **k: calls.append(1) or real(*a, **k))
    pts = _pair(3)["a"].astype(np.float64)
    d0, f0 = geometric.fcgf_features(pts, MF.VOXEL, model=net)
    d1, f1 = geometric.fcgf_features(pts.copy(), MF.VOXEL, model=net)
    assert len(calls) == 1 and np.array_equal(f0, f1) and np.array_equal(d0, d1)
    f1[:] = 0  # a caller changing its copy does not change what is kept
    assert np.array_equal(geometric.fcgf_features(pts, MF.VOXEL, model=net)[1], f0)
    moved = pts.copy()
    moved[0, 0] += 0.01
    geometric.fcgf_features(moved, MF.VOXEL, model=net)
    assert len(calls) == 2
    with torch.no_grad():
        next(net.parameters()).add_(1e-3)  # a trained (changed) network
    geometric.fcgf_features(pts, MF.VOXEL, model=net)
    assert len(calls) == 3


def test_table9_ordering_is_read_from_both_ladders():
    from freereg_lib.training.evaluate_fcgf import ladder_line, ladder_order

    tight, loose = "RR@5deg/0.1m", "RR@25deg/0.5m"

    def res(pnp, kabsch):
        return {"FreeReg-G pnp": {"ladder": {tight: pnp[0], loose: pnp[1]}},
                "FreeReg-G kabsch": {"ladder": {tight: kabsch[0], loose: kabsch[1]}}}

    paper_like = res((10.0, 40.0), (3.3, 60.0))
    assert ladder_order(paper_like, "FreeReg-G")["holds"] is True
    assert ladder_order(res((10.0, 70.0), (3.3, 60.0)), "FreeReg-G")["holds"] is False  # PnP ahead at both ends
    assert ladder_order(res((0.0, 40.0), (3.3, 60.0)), "FreeReg-G")["holds"] is False  # Kabsch ahead at both
    assert ladder_order(res((0.0, 0.0), (0.0, 3.3)), "FreeReg-G")["holds"] == "tie"  # 0 % at the tight rung
    line = ladder_line(ladder_order(paper_like, "FreeReg-G"), paper_like)
    assert "5deg/0.1m: 10.0/3.3" in line and "is seen here in direction only" in line
    tie = res((0.0, 0.0), (0.0, 3.3))
    assert "cannot be told (a tie at one end)" in ladder_line(ladder_order(tie, "FreeReg-G"), tie)
    assert "PnP 9.4 / Kabsch 3.5" in line and "40.2 / 65.3" in line  # the paper's Table 9, 3DMatch row


def test_fcgf_card_states_the_rotations_trained_with_and_the_table9_verdict(tmp_path, monkeypatch):
    import json

    from freereg_lib.training import card

    stats = {"mean": 1.0, "ci": [0.0, 2.0]}
    row = {"IR": stats, "FMR": stats, "RR": stats, "ladder": {"RR@5deg/0.1m": 0.0, "RR@25deg/0.5m": 3.3}}
    chain = {"micro (FCGF)": {f"{m} {s}": row for m in ("FreeReg-G", "FreeReg") for s in ("kabsch", "pnp")},
             "micro (FPFH)": {"FreeReg-G kabsch": row}, "random weights (FCGF)": {"FreeReg-G kabsch": row},
             "micro (FCGF) label": "micro", "IR_ratio_trained_random": 1.0, "p_trained_vs_random": 0.5}
    (tmp_path / "eval.json").write_text(json.dumps({"n_pairs": 30, "seed": 2026, "chain": chain}))
    for rotations, expected in (("inference", "in the frame the pipeline gives it (its own camera's)"),
                                ("so3", "rotated uniformly in SO(3)")):
        args = {"pairs": 2, "crop_radius": 0.6, "scale_aug": 0.1, "lr": 5e-4, "warmup": 1, "seed": 0,
                "rotations": rotations}
        (tmp_path / "training.json").write_text(json.dumps({
            "arguments": args, "train_stream": "s", "validation_pairs": "v", "voxels_per_cloud_mean": 1,
            "steps": 2, "parameters_millions": 8.8, "step_seconds": 1.0, "loss": [1.0, 0.9],
            "val": [[2, {"loss": 0.9, "hit_ratio": 0.05}]]}))
        text = card.write_fcgf_card(tmp_path).read_text()
        assert expected in text
        assert "cannot be told (a tie at one end)" in text  # both solvers at 0 % on the tightest rung
        assert "Image side:" not in text  # the default, the image's depth, is stated with the data
        # The first card draws its figure; the later ones are read for their words only, and
        # each drawing costs ~0.3 s of matplotlib.
        assert (tmp_path / "training.png").stat().st_size > 0
        monkeypatch.setattr(card, "plot_fcgf_training", lambda training, path: None)
    training = json.loads((tmp_path / "training.json").read_text())
    training["arguments"]["image_side"] = "cloud"
    (tmp_path / "training.json").write_text(json.dumps(training))
    assert "Image side: the cloud's view from the image camera" in card.write_fcgf_card(tmp_path).read_text()
    training["val_baselines"] = {"": {"fpfh": 0.089, "chance": 0.018}}
    (tmp_path / "training.json").write_text(json.dumps(training))
    assert "hit ratio at 10 cm 5.0 % (on the same crops FPFH 8.9 %, random features 1.8 %)" in \
        card.write_fcgf_card(tmp_path).read_text()


def test_image_side_chooses_the_cloud_of_the_batch():
    # "cloud" crops the image camera's view of the cloud (here every other voxel of the image
    # side), "depth" the image's own depth; "mix" draws both over a few steps.
    pair = _pair()
    pair["a_cloud"] = pair["a"][::2]

    def n_image_voxels(side, seed):
        return len(T.make_batch(pair, np.random.default_rng(seed), 0.5, 0.0, image_side=side)["coords_a"])

    depth, cloud = n_image_voxels("depth", 4), n_image_voxels("cloud", 4)
    assert cloud < 0.7 * depth
    mixed = {n_image_voxels("mix", s) > 0.85 * depth for s in range(12)}
    assert mixed == {True, False}
    with pytest.raises(ValueError, match="image_side"):
        T.make_batch(pair, np.random.default_rng(0), 0.5, 0.0, image_side="mono")


def test_fpfh_baseline_on_crops_beats_chance_on_a_rigid_copy():
    # B is A's surface moved rigidly: FPFH, rotation invariant with normals facing each camera,
    # finds far more true partners than random features do; the crops carry their cameras.
    batch = T.make_batch(_pair(), np.random.default_rng(2), crop_radius=0.5, scale_aug=0.0)
    assert batch["points_a"].shape == (len(batch["coords_a"]), 3)
    assert batch["points_b"].shape == (len(batch["coords_b"]), 3)
    np.testing.assert_array_equal(np.floor(batch["points_b"] / T.VOXEL).astype(int), batch["coords_b"])
    base = T.baseline_hit_ratios([batch])
    assert base["fpfh"] > 2 * base["chance"]
    assert 0.0 <= base["chance"] < 0.5
