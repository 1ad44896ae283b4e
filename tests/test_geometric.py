"""FPFH features, their rigid invariance, pixel -> nearest feature point, the fcgf switch."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("open3d")

from freereg_lib.config import FreeRegConfig  # noqa: E402
from freereg_lib.features.geometric import fpfh_features, geometric_features, pixel_features
from freereg_lib.geometry.cameras import make_pose, rotation_about, transform  # noqa: E402


def room_corner(rng, n=6000):
    """A floor, two walls, a box and a ball: non-symmetric, dense enough for normals."""
    def plane(o, a, b, m):
        s = rng.uniform(0, 1, (m, 2))
        return np.asarray(o) + s[:, :1] * np.asarray(a) + s[:, 1:] * np.asarray(b)

    def box(c, size, m):
        p = rng.uniform(-0.5, 0.5, (m, 3))
        ax = rng.integers(0, 3, m)
        p[np.arange(m), ax] = np.sign(rng.uniform(-1, 1, m)) * 0.5
        return np.asarray(c) + p * np.asarray(size)

    k = n // 6
    ball = rng.normal(size=(k, 3))
    ball = ball / np.linalg.norm(ball, axis=1, keepdims=True) * 0.15 + [0.9, 0.3, 0.15]
    return np.vstack([
        plane([0, 0, 0], [1.2, 0, 0], [0, 1.2, 0], 2 * k),
        plane([0, 0, 0], [0, 1.2, 0], [0, 0, 0.7], k),
        plane([0, 1.2, 0], [1.2, 0, 0], [0, 0, 0.7], k),
        box([0.45, 0.7, 0.15], [0.3, 0.25, 0.3], k),
        ball,
    ])


def mutual_nn(fa, fb):
    from scipy.spatial import cKDTree

    _, ab = cKDTree(fb).query(fa)
    _, ba = cKDTree(fa).query(fb)
    keep = ba[ab] == np.arange(len(fa))
    return np.flatnonzero(keep), ab[keep]


def test_fpfh_is_invariant_to_a_rigid_motion():
    rng = np.random.default_rng(0)
    P = room_corner(rng)
    cam = np.array([1.5, -0.4, 0.9])
    T = make_pose(rotation_about([0.3, 1.0, 0.2], 0.8), [0.4, -1.2, 0.5])
    Q = transform(T, P)
    cam_q = transform(T, cam[None])[0]
    # No downsampling: point i of Q is the true correspondence of point i of P.
    a, fa = fpfh_features(P, 0.0, 0.06, 0.15, camera_location=cam)
    b, fb = fpfh_features(Q, 0.0, 0.06, 0.15, camera_location=cam_q)
    assert fa.shape == fb.shape == (len(P), 33) and fa.dtype == np.float32
    assert np.allclose(a, P) and np.allclose(b, Q)
    i, j = mutual_nn(fa, fb)
    assert len(i) > 0.3 * len(P)
    inlier = np.linalg.norm(transform(T, a[i]) - b[j], axis=1) < 0.03
    assert inlier.mean() > 0.9
    # A cloud that is NOT the same scene does not match like that.
    c, fc = fpfh_features(Q[:, [1, 0, 2]] * [1.0, 1.7, 0.6], 0.0, 0.06, 0.15,
                          camera_location=cam_q)
    i2, j2 = mutual_nn(fa, fc)
    assert (np.linalg.norm(transform(T, a[i2]) - b[j2], axis=1) < 0.03).mean() < 0.5


def test_fpfh_voxel_downsampling_and_config_dispatch():
    rng = np.random.default_rng(1)
    P = room_corner(rng)
    down, f = fpfh_features(P, 0.05, 0.1, 0.25)
    assert 100 < len(down) < len(P) // 2
    assert f.shape == (len(down), 33) and np.isfinite(f).all() and (f >= 0).all()
    cfg = FreeRegConfig()
    v = getattr(cfg, "fpfh_voxel", None) or cfg.voxel_size
    ref_down, ref_f = fpfh_features(P, v, cfg.normal_radius_factor * v,
                                    cfg.fpfh_radius_factor * v)
    down2, f2 = geometric_features(P, cfg)
    assert np.allclose(down2, ref_down) and np.allclose(f2, ref_f)
    empty_pts, empty_f = fpfh_features(np.zeros((0, 3)), 0.05, 0.1, 0.25)
    assert empty_pts.shape == (0, 3) and empty_f.shape == (0, 33)


def test_unknown_geometric_method():
    with pytest.raises(ValueError, match="unknown geometric"):
        geometric_features(np.zeros((10, 3)), FreeRegConfig(), method="shot")


def test_pixel_features_nearest_and_tau_g():
    feat_points = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0]])
    feats = np.array([[1.0, 0], [0, 1.0], [2.0, 2.0]], dtype=np.float32)
    q = np.array([[0.1, 0, 0],      # -> 0
                  [0.9, 0.1, 0],    # -> 1
                  [0, 1.7, 0],      # -> 2 (0.3 away)
                  [0, 1.0, 0],      # nearest is 1.0 away: beyond tau_g = 0.5
                  [np.nan, 0, 0]])  # no depth
    out = pixel_features(q, feat_points, feats, tau_g=0.5)
    assert out.shape == (5, 2) and out.dtype == np.float32
    assert np.array_equal(out, [[1, 0], [0, 1], [2, 2], [0, 0], [0, 0]])
    assert np.array_equal(pixel_features(q, feat_points, feats, tau_g=1.5)[3], [1, 0])
    assert pixel_features(q, np.zeros((0, 3)), np.zeros((0, 2)), 0.5).shape == (5, 2)


# ---------------------------------------------------------------------------------------
# FCGF (plain-torch ResUNetBN2C with MinkowskiEngine semantics).

def _dense_weight(kernel, k=3):
    """ME kernel (k^3, in, out), flat index ix + k iy + k^2 iz -> torch (out, in, kx, ky, kz)."""
    return kernel.reshape(k, k, k, *kernel.shape[1:]).permute(4, 3, 2, 1, 0)


def _random_sites(rng, n, grid, stride=1):
    c = rng.integers(0, grid // stride, (n, 3)) * stride
    return np.unique(c, axis=0)


def test_sparse_convs_match_dense_convolutions():
    torch = pytest.importorskip("torch")
    from freereg_lib.models.fcgf import SparseTensor, _Lookup, modules

    MEConv = modules()[0]
    rng = np.random.default_rng(0)
    G = 10
    fine = torch.from_numpy(_random_sites(rng, 300, G))
    feats = torch.from_numpy(rng.standard_normal((len(fine), 3)).astype(np.float32))
    dense = torch.zeros(1, 3, G, G, G)
    dense[0, :, fine[:, 0], fine[:, 1], fine[:, 2]] = feats.T
    tables = {}

    def ctx():
        return {"maps": {1: fine}, "lookup": lambda s, c: tables.setdefault(
            (s, len(c)), _Lookup(c, -64, G + 129))}

    torch.manual_seed(0)
    with torch.no_grad():
        # Stride 1 (kernels 3 and 5): equal to conv3d at the active sites.
        for k in (3, 5):
            conv = MEConv(3, 4, k)
            out = conv(SparseTensor(fine, feats), ctx())
            ref = torch.nn.functional.conv3d(dense, _dense_weight(conv.kernel, k), padding=k // 2)
            assert torch.equal(out.coords, fine)
            assert torch.allclose(out.feats, ref[0, :, fine[:, 0], fine[:, 1], fine[:, 2]].T,
                                  atol=1e-5)
        # Stride 2: output sites floor(c / 2) * 2, values of conv3d(stride 2, padding 1).
        conv = MEConv(3, 4, 3, stride=2)
        c2 = ctx()
        out = conv(SparseTensor(fine, feats), c2)
        expect_sites = np.unique(np.floor(fine.numpy() / 2) * 2, axis=0)
        assert np.array_equal(out.coords.numpy(), expect_sites) and out.stride == 2
        ref = torch.nn.functional.conv3d(dense, _dense_weight(conv.kernel), stride=2, padding=1)
        q = out.coords // 2
        assert torch.allclose(out.feats, ref[0, :, q[:, 0], q[:, 1], q[:, 2]].T, atol=1e-5)
        # Transposed stride 2 back onto the fine sites: conv_transpose3d at those sites.
        coarse_feats = torch.randn(len(out.coords), 4)
        tconv = MEConv(4, 2, 3, stride=2, transpose=True)
        back = tconv(SparseTensor(out.coords, coarse_feats, 2), c2)
        assert torch.equal(back.coords, fine) and back.stride == 1
        dense2 = torch.zeros(1, 4, G // 2, G // 2, G // 2)
        dense2[0, :, q[:, 0], q[:, 1], q[:, 2]] = coarse_feats.T
        wt = _dense_weight(tconv.kernel).transpose(0, 1)  # (in, out, kx, ky, kz)
        ref = torch.nn.functional.conv_transpose3d(dense2, wt, stride=2, padding=1,
                                                   output_padding=1)
        assert torch.allclose(back.feats, ref[0, :, fine[:, 0], fine[:, 1], fine[:, 2]].T,
                              atol=1e-5)


def test_fcgf_resunetbn2c_state_dict_layout_and_features(tmp_path):
    torch = pytest.importorskip("torch")
    from freereg_lib.models.fcgf import ResUNetBN2C, fcgf_features, load_fcgf

    torch.manual_seed(0)
    net = ResUNetBN2C(conv1_kernel_size=5).eval()
    sd = net.state_dict()
    # The official checkpoints' (MinkowskiEngine) names and shapes.
    expect = {
        "conv1.kernel": (125, 1, 32), "norm1.bn.running_var": (32,),
        "block1.conv2.kernel": (27, 32, 32), "conv4.kernel": (27, 128, 256),
        "conv4_tr.kernel": (27, 256, 128), "conv3_tr.kernel": (27, 256, 64),
        "conv2_tr.kernel": (27, 128, 64), "block2_tr.norm2.bn.weight": (64,),
        "conv1_tr.kernel": (96, 64), "final.kernel": (64, 32), "final.bias": (1, 32),
    }
    for k, shape in expect.items():
        assert tuple(sd[k].shape) == shape, k
    assert len([k for k in sd if k.endswith("kernel")]) == 23
    # Random BN statistics so eval-mode BN is not the identity.
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    rng = np.random.default_rng(1)
    pts = room_corner(rng, 3000)
    down, f = fcgf_features(pts, 0.05, net)
    assert f.shape == (len(down), 32) and f.dtype == np.float32 and len(down) < len(pts)
    assert np.allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-5)
    # A checkpoint as FCGF writes it (state_dict + a config object), with the other ME
    # versions' 1x1 kernel / bias shapes, loads strictly and gives the same features.
    ckpt = {k: v.clone() for k, v in net.state_dict().items()}
    ckpt["final.bias"] = ckpt["final.bias"].reshape(32)
    ckpt["conv1_tr.kernel"] = ckpt["conv1_tr.kernel"].reshape(1, 96, 64)
    path = tmp_path / "fcgf.pth"
    torch.save({"state_dict": ckpt, "config": {"model": "ResUNetBN2C"}}, path)
    net2 = load_fcgf(str(path))
    assert net2.conv1.kernel_size == 5
    down2, f2 = fcgf_features(pts, 0.05, net2)
    assert np.array_equal(down, down2) and np.allclose(f, f2, atol=1e-6)


def test_fcgf_through_geometric_features(tmp_path, monkeypatch):
    torch = pytest.importorskip("torch")
    from freereg_lib.models import MissingWeightsError
    from freereg_lib.models.fcgf import ResUNetBN2C

    monkeypatch.delenv("FREEREG_WEIGHTS", raising=False)
    cfg = FreeRegConfig(geometric="fcgf", voxel_size=0.05,
                        extra={"weights_dir": str(tmp_path)})
    with pytest.raises(MissingWeightsError, match="2019-08-19_06-17-41.pth"):
        geometric_features(np.zeros((10, 3)), cfg)
    torch.manual_seed(0)
    (tmp_path / "fcgf").mkdir()
    torch.save({"state_dict": ResUNetBN2C(conv1_kernel_size=7).state_dict()},
               tmp_path / "fcgf" / "2019-08-19_06-17-41.pth")
    pts = room_corner(np.random.default_rng(2), 2000)
    down, f = geometric_features(pts, cfg)
    assert f.shape == (len(down), 32)


def test_fcgf_3dmatch_checkpoint_is_the_2_5_cm_model():
    """The paper's footnote: the 2.5 cm 3DMatch model, 2019-08-19_06-17-41.pth (FCGF's
    2019-08-16_19-21-47.pth is its 5 cm model)."""
    from freereg_lib.models.fcgf import CHECKPOINTS

    assert CHECKPOINTS["3dmatch"] == dict(file="2019-08-19_06-17-41.pth", conv1_kernel_size=7, voxel=0.025)
    assert CHECKPOINTS["kitti"]["file"] == "KITTI-v0.3-ResUNetBN2C-conv1-5-nout32.pth"


class _RunsCode:
    """Unpickling this would call ``exec`` (what a malicious checkpoint does)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').write('ran')",))


def test_fcgf_checkpoint_that_would_run_code_is_refused_without_running_it(tmp_path):
    torch = pytest.importorskip("torch")
    from freereg_lib.models.fcgf import CheckpointRefused, ResUNetBN2C, load_fcgf

    marker = tmp_path / "pwned"
    state = ResUNetBN2C(conv1_kernel_size=7).state_dict()
    for legacy in (False, True):
        path = tmp_path / f"evil{int(legacy)}.pth"
        torch.save({"state_dict": state, "config": _RunsCode(marker)}, path,
                   _use_new_zipfile_serialization=not legacy)
        with pytest.raises(CheckpointRefused) as err:
            load_fcgf(str(path))
        assert str(path) in str(err.value) and "not a plain state-dict checkpoint" in str(err.value)
        assert "builtins.exec" in str(err.value)
        assert not marker.exists()


class _EasyDict(dict):
    """What ``easydict.EasyDict`` pickles like: a dict whose items are also attributes."""

    def __init__(self, d=None):
        super().__init__(d or {})
        for k, v in (d or {}).items():
            setattr(self, k, v)


_EasyDict.__module__, _EasyDict.__qualname__, _EasyDict.__name__ = "easydict", "EasyDict", "EasyDict"


def test_fcgf_checkpoint_with_its_easydict_config_loads(tmp_path, monkeypatch):
    """FCGF's trainer pickles its config as an ``easydict.EasyDict``: read as an inert dict."""
    import sys
    import types

    torch = pytest.importorskip("torch")
    from freereg_lib.models.fcgf import ResUNetBN2C, _load_checkpoint_file, load_fcgf

    mod = types.ModuleType("easydict")
    mod.EasyDict = _EasyDict
    monkeypatch.setitem(sys.modules, "easydict", mod)
    torch.manual_seed(0)
    net = ResUNetBN2C(conv1_kernel_size=7)
    for legacy in (False, True):
        path = tmp_path / f"fcgf{int(legacy)}.pth"
        torch.save({"state_dict": net.state_dict(), "config": _EasyDict({"voxel_size": 0.025}),
                    "best_val": np.float64(0.9)}, path, _use_new_zipfile_serialization=not legacy)
        monkeypatch.delitem(sys.modules, "easydict")  # not installed where it is loaded
        ckpt = _load_checkpoint_file(str(path))
        assert ckpt["config"]["voxel_size"] == 0.025 and float(ckpt["best_val"]) == 0.9
        net2 = load_fcgf(str(path))
        assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), net2.state_dict().values()))
        monkeypatch.setitem(sys.modules, "easydict", mod)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """The sparse convolutions are many small ops: one thread avoids OpenMP spinning on a
    busy 2-core machine (restored afterwards)."""
    try:
        import torch
    except ImportError:  # pragma: no cover
        yield
        return
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_fpfh_at_the_keypoints_equals_the_full_computation():
    """``at``: only the rows the keypoints read are computed, bitwise the full features' rows,
    so the keypoints' features are identical (the pipeline's use)."""
    from freereg_lib import config_for
    from freereg_lib.data import synthetic
    from freereg_lib.geometry import cameras, keypoints

    cfg = config_for("synthetic_indoor")
    pair = synthetic.make_pair("indoor", seed=3, image_size=(240, 320))
    uv = keypoints.grid_keypoints(pair.image_size, cfg.keypoint_grid)
    z = cameras.nearest_sample(pair.depth_gt, uv)
    query = cameras.transform(cameras.invert(pair.T_cam_pc), cameras.lift(uv, z, pair.K_image))
    query[::7] = np.nan  # pixels without depth
    down, full = geometric_features(pair.points, cfg)
    down_at, some = geometric_features(pair.points, cfg, at=query)
    np.testing.assert_array_equal(down_at, down)
    computed = np.any(some != 0, axis=1)
    assert 0 < computed.sum() < 0.5 * len(down)  # far fewer rows than the cloud's
    np.testing.assert_array_equal(some[computed], full[computed])
    np.testing.assert_array_equal(pixel_features(query, down_at, some, cfg.tau_g),
                                  pixel_features(query, down, full, cfg.tau_g))
