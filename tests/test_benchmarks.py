"""The benchmark script runs (CI mode, tiny sizes) and prints its table; the speed-ups it
measures give the same results as the straightforward versions they replaced."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from freereg_lib.features import matching
from freereg_lib.geometry import cameras, projection

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "bench_pipeline.py"
STAGE_NAMES = (
    "projection + densify",
    "diffusion RGB",
    "diffusion depth",
    "monocular depth",
    "PCA + keypoint sampling",
    "geometric features",
    "matching",
    "solver PnP-RANSAC",
    "solver Kabsch-RANSAC",
    "metrics",
    "END TO END",
    "mutual NN",
)


def _run(*args, timeout=600, script=SCRIPT):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, str(script), *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _main(monkeypatch, capsys, name, *args):
    """``name``'s ``main(args)`` in this process: ``(exit status, stdout, stderr)``. bench_pipeline
    measures memory and sets torch's threads, so its table comes from a run as a program above."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import importlib

    rc = importlib.import_module(name).main(list(args))
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def test_ci_mode_prints_the_stage_table(tmp_path):
    out_json = tmp_path / "bench.json"
    proc = _run("--mode", "ci", "--json", str(out_json), "--pair-batch", "2")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = proc.stdout
    for name in (*STAGE_NAMES, "diffusion depth, 2 pairs per call (per pair)"):
        assert name in out, f"stage {name!r} missing from the table:\n{out}"
    header = next(line for line in out.splitlines() if line.startswith("stage "))
    assert "time median [s]" in header and "peak [MiB]" in header
    # The device is named: CPU model, torch version and threads.
    assert "device: CPU" in out and torch.__version__ in out and "threads" in out
    with open("/proc/cpuinfo") as fh:
        model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.lower().startswith("model name")), None)
    if model:
        assert model in out
    # Every stage row has a time and the stub chain has memory figures.
    data = json.loads(out_json.read_text())
    chain = data["results"][0]
    assert chain["backend"] == "stub"
    for name in ("projection + densify", "matching", "solver PnP-RANSAC", "solver Kabsch-RANSAC"):
        assert all(t >= 0 for t in chain["times"][name])
        assert chain["memory"][name]["py_peak_mib"] is not None
    assert any(r["backend"] == "tiny" for r in data["results"])
    assert data["device"]["torch"] == torch.__version__


def test_pnp_benchmark_prints_one_row_per_method(tmp_path, monkeypatch, capsys):
    out_json = tmp_path / "pnp.json"
    rc, out, err = _main(monkeypatch, capsys, "bench_pnp", "--pairs", "1", "--iters", "300", "--methods", "iterative",
                         "iterative:2", "usac", "--json", str(out_json))
    assert rc == 0, out[-3000:] + err[-3000:]
    rows = [line for line in out.splitlines() if line.startswith("| ") and "PnP method" not in line]
    assert [r.split("|")[1].strip() for r in rows] == ["iterative", "iterative:2", "usac"]
    assert "device: CPU" in out and out_json.is_file()
    rc, _, err = _main(monkeypatch, capsys, "bench_pnp", "--pairs", "1", "--methods", "magic", "usac:x")
    assert rc == 2 and "magic" in err and "usac:x" in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present: gpu mode would run")
def test_gpu_mode_without_a_gpu_says_not_measured(monkeypatch, capsys):
    rc, _, err = _main(monkeypatch, capsys, "bench_pipeline", "--mode", "gpu")
    assert rc == 2
    assert "not measured: no GPU" in err


# ---------------------------------------------------------------------------------------
# The speed-ups keep the results.

def _mutual_nn_two_products(a, b, chunk=2048):
    """The first implementation: nearest neighbours both ways, one product per direction."""
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)

    def nearest(q_all, base):
        base_sq = (base * base).sum(1)
        out = torch.empty(q_all.shape[0], dtype=torch.long)
        for s in range(0, q_all.shape[0], chunk):
            d = base_sq[None, :] - 2.0 * (q_all[s:s + chunk] @ base.T)
            out[s:s + chunk] = d.argmin(1)
        return out

    ab, ba = nearest(ta, tb), nearest(tb, ta)
    idx = torch.arange(len(a))
    keep = ba[ab] == idx
    return idx[keep].numpy(), ab[keep].numpy()


def _features(rng, n, m, c, noise):
    a = rng.standard_normal((n, c)).astype(np.float32)
    b = a[rng.integers(0, n, m)] + noise * rng.standard_normal((m, c)).astype(np.float32)
    b[:3] = 0.0  # zero rows (a geometric feature beyond tau_g): exact ties
    b[5:8] = b[8:11]  # duplicates: more exact ties
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-5)
    return a, b


@pytest.mark.parametrize("n,m,c,chunk", [(700, 300, 33, 2048), (300, 2500, 417, 128),
                                         (2100, 2300, 64, 1000), (50, 40, 3, 7)])
def test_mutual_nn_one_product_equals_two_products(rng, n, m, c, chunk):
    a, b = _features(rng, n, m, c, noise=0.8)
    ref = _mutual_nn_two_products(a, b, chunk)
    got = matching.mutual_nn(a, b, chunk=chunk)
    assert len(ref[0]) > 0
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    # The torch path (used on CUDA) gives the same answer; checked here on CPU tensors.
    ab, ba = matching._both_torch(torch.from_numpy(a), torch.from_numpy(b), chunk)
    idx = np.arange(n)
    keep = ba.numpy()[ab.numpy()] == idx
    np.testing.assert_array_equal(idx[keep], ref[0])
    np.testing.assert_array_equal(ab.numpy()[keep], ref[1])


def test_mutual_nn_integer_features_many_ties(rng):
    a = rng.integers(0, 3, (600, 4)).astype(np.float32)
    b = rng.integers(0, 3, (2500, 4)).astype(np.float32)
    ref = _mutual_nn_two_products(a, b, 256)
    got = matching.mutual_nn(a, b, chunk=256)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


def test_mutual_nn_rejects_non_finite():
    a = np.ones((4, 3), np.float32)
    b = np.ones((5, 3), np.float32)
    b[2, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        matching.mutual_nn(a, b)


def _zbuffer_lexsort(points, K, T, size, dmin, dmax):
    """The first implementation of the z-buffer: sort by pixel, then depth."""
    H, W = size
    uv, z = cameras.project(cameras.transform(T, points), K)
    u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    keep = (z > max(dmin, 0.0)) & (z < dmax) & np.isfinite(u) & np.isfinite(v)
    keep &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
    rows = np.nonzero(keep)[0]
    flat = v[rows].astype(np.int64) * W + u[rows].astype(np.int64)
    order = np.lexsort((z[rows], flat))
    flat, rows = flat[order], rows[order]
    first = np.ones(len(flat), bool)
    first[1:] = flat[1:] != flat[:-1]
    depth = np.zeros(H * W)
    index = np.full(H * W, -1, np.int64)
    depth[flat[first]] = z[rows[first]]
    index[flat[first]] = rows[first]
    return depth.reshape(H, W), index.reshape(H, W)


def test_zbuffer_without_sorting_equals_lexsort(rng):
    P = rng.uniform([-1, -1, 0.5], [1, 1, 4], (40000, 3))
    P = np.concatenate([P, P[:500], P[7:60]])  # exact duplicates: ties at one pixel and depth
    K = cameras.intrinsics(60.0, 60.0, 40.0, 30.0)
    T = cameras.make_pose(cameras.rotation_about(np.array([0.1, 1.0, 0.0]), 0.2), [0.05, 0.0, 0.3])
    for dmin, dmax in [(0.0, np.inf), (1.0, 3.0)]:
        d0, i0 = _zbuffer_lexsort(P, K, T, (60, 80), dmin, dmax)
        d1, i1 = projection.project_to_depth(P, K, T, (60, 80), dmin, dmax)
        np.testing.assert_array_equal(d1, d0)
        np.testing.assert_array_equal(i1, i0)
