"""``freereg register`` in its own terms: ``--up -y`` as the README writes it,
``--geometric fpfh|fcgf``, and messages that name the command's flags, not Python keywords."""
from __future__ import annotations

import pytest

from freereg_lib.commands import cli
from freereg_lib.data.datasets.icl import ICLSample
from freereg_lib.pipeline import register as R
from freereg_lib.report import pair_files as PF


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cli")
    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    paths = PF.write_user_files(pair, tmp / "in")
    K = pair.K_image
    paths["K"] = [f"{v:.6f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])]
    return paths


def _run(argv, capsys):
    rc = cli.main(["register", *argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.parametrize("spelling, value", [(["--up", "-y"], "-y"), (["--up=-y"], "-y"), (["--up", "-z"], "-z"),
                                             (["--up", "x"], "x"), ([], "auto")])
def test_up_takes_negative_axes_as_the_readme_writes_them(spelling, value):
    args = cli._parser().parse_args(cli._join_signed_values(["register", "a.png", "b.ply", *spelling, "--views", "2"]))
    assert args.up == value and args.views == 2 and (args.image, args.cloud) == ("a.png", "b.ply")


def test_the_command_runs_with_up_minus_y(files, capsys, tmp_path):
    # ICL's clouds are in a camera frame: "up" is -y (README, "The depth camera").
    rc, out, err = _run([str(files["image"]), str(files["cloud"]), "--K", *files["K"], "--image-depth",
                         str(files["image_depth"]), "--backend", "stub", "--up", "-y", "--views", "1", "--no-refine",
                         "--ransac-iters", "500", "--out", str(tmp_path / "out")], capsys)
    assert rc == 0, err
    assert "centre/yaw0" in (tmp_path / "out" / "candidates.csv").read_text() and "result: " in out


def test_geometric_is_a_flag_and_fcgf_without_its_checkpoint_names_flags(files, capsys, tmp_path):
    args = cli._parser().parse_args(["register", "a.png", "b.ply", "--geometric", "fcgf"])
    assert args.geometric == "fcgf"
    rc, out, err = _run([str(files["image"]), str(files["cloud"]), "--K", *files["K"], "--image-depth",
                         str(files["image_depth"]), "--backend", "stub", "--geometric", "fcgf", "--weights-dir",
                         str(tmp_path / "no_weights"), "--out", str(tmp_path / "out")], capsys)
    assert rc == 1 and "FCGF checkpoint not found" in err, err
    assert "--fcgf-checkpoint FILE" in err and "--geometric fpfh" in err
    assert "cfg.extra" not in err and "geometric='fpfh'" not in err
    assert not (tmp_path / "out").exists()
    rc, out, err = _run([str(files["image"]), str(files["cloud"]), "--K", *files["K"], "--fcgf-checkpoint", "x.pth"],
                        capsys)
    assert rc == 2 and "--fcgf-checkpoint is for --geometric fcgf" in err


def test_the_missing_weights_message_speaks_flags(files, capsys, tmp_path):
    rc, out, err = _run([str(files["image"]), str(files["cloud"]), "--K", *files["K"], "--backend", "real",
                         "--device", "cpu", "--weights-dir", str(tmp_path / "nowhere")], capsys)
    assert rc == 1 and "Pretrained weights are missing" in err, err
    assert "weights_dir=" not in err and "get_backend" not in err and 'backend="stub"' not in err, err
    assert "--weights-dir" in err and "--backend stub" in err


def test_in_flags_rewrites_the_library_spellings():
    msg = ("Then copy the folder(s) here and pass weights_dir=... to get_backend (or set FREEREG_WEIGHTS, or "
           "cfg.extra['weights_dir']); ... pass weights_dir='/w/models'. Note: weights_dir /x does not exist. "
           'To run without weights, use backend="stub" or backend="tiny"; device="cpu"')
    out = cli.in_flags(msg)
    assert "pass --weights-dir FOLDER (or set FREEREG_WEIGHTS)" in out and "pass --weights-dir /w/models" in out
    assert "Note: --weights-dir /x does not exist" in out and "--backend stub or --backend tiny" in out
    assert "--device cpu" in out and "weights_dir" not in out and "cfg." not in out
