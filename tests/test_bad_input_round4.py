"""Red team, fourth pass: each case failed on the code before the fix (a traceback, a
silent wrong answer, or a message that hid its comparison)."""
from __future__ import annotations

import dataclasses
import io
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from freereg_lib.commands import batch, cli
from freereg_lib.data import synthetic
from freereg_lib.data.datasets.common import read_points
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.data.pair import geometry_fault
from freereg_lib.geometry import cameras
from freereg_lib.geometry import pose
from freereg_lib.pipeline import register as R
from freereg_lib.report import pair_files as PF
from freereg_lib.training import evaluate_depth as ED
from freereg_lib.training import evaluate_split as ES


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("r4")
    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    paths = PF.write_user_files(pair, tmp / "in")
    K = pair.K_image
    paths["K"] = [f"{v:.6f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])]
    return paths


def _argv(files, *more):
    return ["register", str(files["image"]), str(files["cloud"]), "--K", *files["K"], "--image-depth",
            str(files["image_depth"]), "--backend", "stub", "--ransac-iters", "200", "--views", "1", *more]


def test_write_ply_keeps_float64(tmp_path):
    utm = np.array([[500_000.123456, 5_400_000.654321, 100.25], [500_001.5, 5_400_002.25, 99.75]])
    back = read_points(PF.write_ply(tmp_path / "utm.ply", utm))
    np.testing.assert_array_equal(back, utm)  # float32 lost 0.25 m at 5,400 km
    small = read_points(PF.write_ply(tmp_path / "f32.ply", utm.astype(np.float32) - 500_000))
    assert (tmp_path / "f32.ply").read_bytes().count(b"property float ") == 3 and small.shape == (2, 3)


def test_out_naming_an_existing_file_stops_before_registering(files, tmp_path, capsys):
    blocker = tmp_path / "taken"
    blocker.write_text("mine")
    for out in (blocker, blocker / "sub"):
        assert cli.main(_argv(files, "--out", str(out))) == 2
        captured = capsys.readouterr()
        assert f"{blocker} is an existing file" in captured.err and "--out" in captured.err
        assert "backend:" not in captured.out and "Traceback" not in captured.err  # nothing ran
    assert blocker.read_text() == "mine"


@pytest.mark.parametrize("content", [b"", b"<html>404 Not Found</html>", b"PK\x03\x04 cut"],
                         ids=["empty", "html", "truncated-zip"])
def test_a_bad_fcgf_checkpoint_is_an_input_error(files, tmp_path, capsys, content):
    ckpt = tmp_path / "fcgf.pth"
    ckpt.write_bytes(content)
    rc = cli.main(_argv(files, "--geometric", "fcgf", "--fcgf-checkpoint", str(ckpt), "--out", str(tmp_path / "o")))
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and f"--fcgf-checkpoint {ckpt}" in err
    assert not (tmp_path / "o").exists()


def _verdict(n_inliers: int, nulls: list[int], solver: str = "kabsch", scale: float = 1.0) -> str:
    from freereg_lib.config import config_for
    from freereg_lib.pipeline import verdict

    res = pose.PoseResult(np.eye(4), True, solver, inliers=np.arange(n_inliers), scale=scale)
    return verdict.decide(res, nulls, solver, config_for("demo"))[1]


def test_the_verdict_prints_the_numbers_it_compares():
    # The support (inliers over the shuffled matches' best) with its parts, against the fitted least.
    from freereg_lib.pipeline import verdict

    need = verdict.MIN_SUPPORT["kabsch"]
    assert _verdict(20, [0, 11, 9, 10]).startswith(
        f"20 inliers = 1.82 x the 11 the same solver reaches on the matches shuffled (chance; 4 shuffles: "
        f"0, 11, 9, 10), below {need:g} x")
    # A null that found no pose counts as the solver's minimum of matches (Kabsch 5, PnP 8).
    assert "= 1.50 x the 8 " in _verdict(12, [0, 0], "pnp")
    assert "is outside [0.67, 1.5]" in _verdict(200, [10], scale=1.6)


# --------------------------------------------------------------------------------------
# The parity command (tools/parity.py) on bad fixtures: one line naming the file, exit 2.

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import parity  # noqa: E402 - a repository tool beside the library, not in it

GOOD = ROOT / "tests" / "fixtures" / "parity" / "return_uv" / "480x640_8x11.npz"


def _parity(directory, capsys) -> tuple[int, str]:
    """The command's ``main`` in this process: a traceback would fail the test here as well, and
    each Python start-up it saves costs ~0.1 s of CPU; :func:`_parity_script` runs the script."""
    rc = parity.main([str(directory)])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err, captured.err
    return rc, captured.out


def _parity_script(directory) -> tuple[int, str]:
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "parity.py"), str(directory)], capture_output=True,
                          text=True, cwd=ROOT)
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc.returncode, proc.stdout


def _write_bad(path: Path, kind: str) -> None:
    if kind == "truncated":
        path.write_bytes(GOOD.read_bytes()[:200])
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "text":
        path.write_text("in_x = [1, 2, 3]\n")
    elif kind == "object-array":
        np.savez(path, in_x=np.array([{"a": 1}], dtype=object), out_y=np.zeros(2))
    elif kind == "directory":
        path.mkdir()


@pytest.mark.parametrize("kind", ["truncated", "empty", "text", "object-array", "directory"])
def test_parity_names_an_unreadable_fixture_and_exits_2(tmp_path, kind, capsys):
    (tmp_path / "return_uv").mkdir()
    _write_bad(tmp_path / "return_uv" / "c.npz", kind)
    rc, out = _parity(tmp_path, capsys)
    lines = out.splitlines()
    assert rc == 2, out
    assert lines[0].startswith("return_uv: ") and "FAIL" in lines[0] and str(tmp_path / "return_uv" / "c.npz") in lines[0]
    assert lines[-1] == "1 functions: 0 ok, 1 FAIL, 0 skipped"


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", '{"functions": [1]}', "\xff\xfe"])
def test_parity_names_a_malformed_manifest_and_exits_2(tmp_path, text, capsys):
    shutil.copytree(GOOD.parent, tmp_path / "return_uv")
    (tmp_path / "manifest.json").write_bytes(text.encode("latin-1"))
    rc, out = _parity(tmp_path, capsys)
    assert rc == 2 and out.count("\n") == 1 and f"{tmp_path / 'manifest.json'}: not a fixture manifest" in out, out


@pytest.mark.parametrize("rename", [lambda k: k.replace("out_", "OUT_"), lambda k: k if k.startswith("in_") else None],
                         ids=["misspelt-OUT_", "no-out-arrays"])
def test_parity_fails_a_case_with_nothing_to_compare_even_when_the_function_is_wrong(tmp_path, rename, monkeypatch):
    (tmp_path / "return_uv").mkdir()
    with np.load(GOOD) as z:
        arrays = {rename(k): z[k] for k in z.files if rename(k)}
    np.savez(tmp_path / "return_uv" / "c.npz", **arrays)
    monkeypatch.setitem(parity.ADAPTERS, "return_uv", lambda i: {"uv": np.zeros(3)})  # the project made wrong
    buf = io.StringIO()
    rc = parity.run(tmp_path, out=buf)
    lines = buf.getvalue().splitlines()
    assert rc == 2 and lines[0].startswith("return_uv: ") and lines[0].endswith("]") and "FAIL" in lines[0], lines
    assert ("OUT_" in lines[0]) if "OUT" in str(list(arrays)) else ("no out_<name> array" in lines[0])


def test_parity_fails_a_function_with_no_case_and_a_folder_with_no_function(tmp_path):
    (tmp_path / "return_uv").mkdir()
    rc, out = _parity_script(tmp_path)  # the script itself: its exit status is main's
    assert rc == 1 and out.splitlines()[0] == f"return_uv: max error inf (tolerance 0) FAIL [no <case>.npz in " \
                                              f"{tmp_path / 'return_uv'}]", out
    empty = tmp_path / "empty"
    empty.mkdir()
    rc, out = _parity_script(empty)
    assert rc == 2 and out == f"no function folder (<function>/<case>.npz) in {empty}: nothing checked\n"


# --------------------------------------------------------------------------------------
# The evaluation commands: one line naming the argument, exit 2, before any work.

def _exits_2(main, argv, capsys) -> str:
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "Traceback" not in err, err
    return err.strip().splitlines()[-1]


@pytest.mark.parametrize("argv, says", [(["--pairs", "0"], "--pairs must be >= 1, got 0"),
                                        (["--seed", "-1"], "--seed must be >= 0"),
                                        (["--boot", "0"], "--boot must be >= 1")])
def test_evaluate_depth_refuses_bad_values(argv, says, capsys):
    assert says in _exits_2(ED.main, argv + ["--no-card", "--figure", ""], capsys)


def test_evaluate_depth_figure_draws_one_pair(tmp_path):
    pair = synthetic.make_pair("indoor", seed=3, image_size=(48, 64))
    preds = {"micro": [pair.depth_gt * 1.1], "stub": [pair.depth_gt * 0.9]}
    ED.plot_figure([pair], preds, tmp_path / "one.png")  # was an IndexError after the evaluation ran
    assert (tmp_path / "one.png").stat().st_size > 1000


def test_evaluate_split_summarize_names_a_missing_or_malformed_rows_file(tmp_path, capsys):
    missing = tmp_path / "none.jsonl"
    assert f"--rows {missing}: cannot read it" in _exits_2(ES.main, ["--summarize", "--rows", str(missing)], capsys)
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"k": 0, "rows": []}\n{"k": 1, "rows": [\n')
    assert f"--rows {bad}, line 2: not a row" in _exits_2(ES.main, ["--summarize", "--rows", str(bad)], capsys)
    bad.write_text('{"rows": []}\n')
    assert f"--rows {bad}, line 1" in _exits_2(ES.main, ["--summarize", "--rows", str(bad)], capsys)
    bad.write_text('{"k": 3, "rows": []}\n')
    assert "no row of pair k = 0" in _exits_2(ES.main, ["--summarize", "--rows", str(bad)], capsys)


@pytest.mark.parametrize("shard, says", [("a/b", "expected i/n, two integers"), ("3/2", "expected 0 <= i < n"),
                                         ("0/0", "expected 0 <= i < n"), ("1", "expected i/n")])
def test_evaluate_split_refuses_a_shard_that_runs_nothing(shard, says, tmp_path, capsys):
    rows = tmp_path / "rows.jsonl"
    assert f"--shard {shard}: {says}" in _exits_2(ES.main, ["--shard", shard, "--rows", str(rows)], capsys)
    assert not rows.exists()


# --------------------------------------------------------------------------------------
# A pair's geometry checked against itself (Pair.validate -> geometry_fault).

@pytest.fixture(scope="module")
def icl_pair():
    # A quarter the size (as the register files above): every fault is named with the same
    # numbers on either side of the thresholds (at most 4 % on the cloud, then 74 %, against
    # 5 % and 76 % full size), and the cloud's k-d tree queries take half the CPU.
    return PF.downscale_pair(ICLSample().pair(50, 90), 0.25)


@pytest.mark.parametrize("fault, says", [
    ("inverted", "T_cam_pc looks inverted"), (3.0, "depth_gt is 3 x the truth"), (10.0, "depth_gt is 10 x the truth"),
    (0.1, "depth_gt is a tenth of the truth"), (0.5, "2 mm PNG units read as millimetres"),
    (5.0, "0.2 mm PNG units read as millimetres")])
def test_validate_names_an_inverted_pose_or_a_depth_in_other_units(icl_pair, fault, says):
    # Measured when written on 6 ICL pairs, 3 synthetic rooms and 2 streets: every fault named, no good pair refused.
    if fault == "inverted":
        bad = dataclasses.replace(icl_pair, T_cam_pc=cameras.invert(icl_pair.T_cam_pc))
    else:
        bad = dataclasses.replace(icl_pair, depth_gt=icl_pair.depth_gt * fault)
    with pytest.raises(ValueError) as info:
        bad.validate()
    msg = str(info.value)
    assert msg.startswith("pair icl/00050-00090: depth_gt lifted with T_cam_pc does not land on the point cloud: ")
    assert says in msg and "\n" not in msg
    share = float(re.search(r"cloud: ([\d.]+)% of its pixels", msg).group(1))
    then = float(re.search(r"then ([\d.]+)%", msg).group(1))
    assert share < 10 and then > 50  # the numbers compared, printed


@pytest.mark.parametrize("make", [lambda: ICLSample().pair(0, 40), lambda: synthetic.make_pair("indoor", seed=2),
                                  lambda: synthetic.make_pair("outdoor", seed=1)], ids=["icl", "room", "street"])
def test_validate_passes_consistent_pairs(make):
    pair = make()
    assert geometry_fault(pair) == "" and pair.validate() is pair


# --------------------------------------------------------------------------------------
# Batch jobs write their notebooks' figures inside their own job folder.

def test_batch_jobs_write_figures_in_their_own_folder(tmp_path):
    nb = json.loads((ROOT / "tests" / "fixtures" / "batch_fixture.ipynb").read_text())
    params = next(c for c in nb["cells"] if "parameters" in c.get("metadata", {}).get("tags", []))
    params["source"] = "".join(params["source"]).rstrip("\n") + '\nfigures_dir = "../figures"  # shared by default\n'
    nb["cells"].append({"cell_type": "code", "id": "figure", "metadata": {}, "execution_count": None, "outputs": [], "source":
                        "import pathlib\npathlib.Path(figures_dir).mkdir(parents=True, exist_ok=True)\n"
                        "(pathlib.Path(figures_dir) / 'fig.png').write_text(f'{seed}')\n"})
    (tmp_path / "nbs").mkdir()
    (tmp_path / "nbs" / "fig_fixture.ipynb").write_text(json.dumps(nb))
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({"notebooks": [str(tmp_path / "nbs" / "fig_fixture.ipynb")],
                                    "grid": {"seed": [1, 2]}, "base": {"n_pairs": 2}}))
    assert batch.main(["run", str(grid), "--runs-dir", str(tmp_path / "runs"), "--name", "a"]) == 0
    for job in batch.load_grid(grid).jobs:
        unit = tmp_path / "runs" / "a" / job.id
        assert (unit / "figures" / "fig.png").read_text() == str(job.params["seed"])
    assert not (tmp_path / "figures").exists()  # the shared folder beside the notebook stays untouched


def test_swapped_cx_cy_are_named_not_blamed_on_depth_size(files, tmp_path, capsys):
    fx, fy, cx, cy = files["K"]
    argv = ["register", str(files["image"]), str(files["cloud"]), "--K", fx, fy, cy, cx, "--image-depth",
            str(files["image_depth"]), "--backend", "stub", "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "--K: cx, cy look swapped" in err and f"--K {float(fx):g} {float(fy):g} {float(cx):g} {float(cy):g}" in err
    assert "depth-size" not in err and "depth_size" not in err and err.count("\n") == 1
