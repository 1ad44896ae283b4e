"""Bad input, round 5: commands that never destroy a user's files, and crashes that became one line.

The book (``python -m freereg_lib.commands.book``) emptied its ``--out`` folder with ``shutil.rmtree``
before building: ``--out RUN`` deleted the executed notebooks, ``--out DIR`` a user's files. Now it
writes only into a new or empty folder or a site it built (a mark file), refuses ``--out`` equal to or
above an input, and checks the run folder, the site and the figures before it stages anything. Each
case here stops before Sphinx starts, or fakes Sphinx, so no test builds a site.
"""
from __future__ import annotations

import errno
import re
import subprocess
from pathlib import Path

import pytest

from freereg_lib.commands import book as B
from freereg_lib.commands import book_inputs as BI
from freereg_lib.commands import process_io as PIO

ROOT = Path(__file__).resolve().parents[1]
GOOD = ROOT / "notebooks" / "03_fusion.ipynb"


@pytest.fixture
def run(tmp_path) -> Path:
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / GOOD.name).write_bytes(GOOD.read_bytes())
    return folder


def _refused(argv: list[str], capsys, monkeypatch) -> str:
    monkeypatch.setattr(B, "stage_notebooks", lambda *a, **k: pytest.fail("the book started staging"))
    assert B.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("book: ") and err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_out_equal_to_the_run_folder_is_refused_and_nothing_is_deleted(run, capsys, monkeypatch):
    err = _refused([str(run), "--out", str(run)], capsys, monkeypatch)
    assert f"--out {run}: is the run folder" in err
    assert (run / GOOD.name).is_file()


def test_out_above_the_run_folder_is_refused(run, capsys, monkeypatch):
    err = _refused([str(run), "--out", str(run.parent)], capsys, monkeypatch)
    assert "holds the run folder" in err and (run / GOOD.name).is_file()


def test_out_holding_a_users_file_is_refused_and_the_file_kept(run, tmp_path, capsys, monkeypatch):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("two years of work")
    err = _refused([str(run), "--out", str(mine)], capsys, monkeypatch)
    assert "holds files the book did not write (thesis.tex)" in err
    assert (mine / "thesis.tex").read_text() == "two years of work"


def test_out_inside_the_staging_folder_or_a_file_is_refused(run, tmp_path, capsys, monkeypatch):
    assert "book_src" in _refused([str(run), "--out", str(run / "book_src" / "site")], capsys, monkeypatch)
    (tmp_path / "a_file").write_text("x")
    assert "a file, not a folder" in _refused([str(run), "--out", str(tmp_path / "a_file")], capsys, monkeypatch)


def test_out_under_proc_is_one_line(run, capsys, monkeypatch):
    err = _refused([str(run), "--out", "/proc/freereg_site"], capsys, monkeypatch)
    assert "cannot write in /proc" in err


def test_a_read_only_run_folder_is_one_line_before_staging(run, capsys, monkeypatch):
    real = PIO.probe_write

    def probe(folder):  # as root, chmod does not stop writes: a read-only mount's error, simulated
        if Path(folder).resolve() == run.resolve():
            raise OSError(errno.EROFS, "Read-only file system")
        real(folder)

    monkeypatch.setattr(PIO, "probe_write", probe)
    err = _refused([str(run), "--out", str(run.parent / "site")], capsys, monkeypatch)
    assert f"{run}: cannot write in the run folder (Read-only file system)" in err


def test_a_figure_that_is_not_a_png_is_named(run, capsys, monkeypatch):
    (run / "figures").mkdir()
    fig = run / "figures" / "03_features_fused.png"
    fig.write_bytes(b"\xff\xd8\xff\xe0JFIF a jpeg saved under a png name")
    err = _refused([str(run)], capsys, monkeypatch)
    assert f"{fig}: not a PNG image" in err


def _fake_sphinx(monkeypatch):
    def sphinx(cmd, **kw):
        Path(cmd[-1], "index.html").write_text("<html></html>")
        return subprocess.CompletedProcess(cmd, 0, "", "")
    monkeypatch.setattr(B.subprocess, "run", sphinx)


def test_a_site_the_book_built_is_rebuilt_and_an_empty_folder_used(run, tmp_path, monkeypatch):
    _fake_sphinx(monkeypatch)
    site = tmp_path / "empty"
    site.mkdir()
    assert B.build_book(run, site) == site.resolve() / "index.html"
    assert (site / BI.SITE_MARK).is_file()
    (site / "stale.html").write_text("from the last build")
    B.build_book(run, site)  # the book's own site: emptied and rebuilt
    assert not (site / "stale.html").exists() and (site / "index.html").is_file()


# --- the training commands: rows files and weights folders, checked before any pair runs ------------------

import json  # noqa: E402

from freereg_lib.training import command_inputs as CI  # noqa: E402
from freereg_lib.training import evaluate_finetune as EF  # noqa: E402
from freereg_lib.training import evaluate_mono as EM  # noqa: E402
from freereg_lib.training import evaluate_rgbd_v2 as ER  # noqa: E402
from freereg_lib.training import finetune_controlnet as FC  # noqa: E402
from freereg_lib.training import other_backbones as OB  # noqa: E402
from freereg_lib.training.splits import SPLITS  # noqa: E402


def _mono_rows(path: Path, split: str = "test", n: int = 2, cut: bool = False) -> Path:
    recs = [{"k": k, "pair_seed": SPLITS[split].pair_seeds(k + 1)[k], "rows": [{"modality": "RGB", "solver": "pnp"}]}
            for k in range(n)]
    text = "".join(json.dumps(r) + "\n" for r in recs)
    path.write_text(text[:-25] if cut else text)
    return path


def _exit_2(main, argv, capsys, monkeypatch, module) -> str:
    """The one error line (after argparse's usage lines, where the command uses ``parser.error``)."""
    monkeypatch.setattr(module, "run", lambda *a, **k: pytest.fail("a pair started"))
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "Traceback" not in err, err
    last = err.splitlines()[-1]
    assert err.count("\n") == 1 or "error: " in last, err
    return last.split("error: ", 1)[-1] + "\n"


@pytest.mark.parametrize("module, name", [(EM, "evaluate_mono"), (ER, "evaluate_rgbd_v2"), (OB, "other_backbones")])
def test_rows_naming_a_folder_is_one_line_before_any_pair(tmp_path, capsys, monkeypatch, module, name):
    err = _exit_2(module.main, ["--rows", str(tmp_path), "--pairs", "1"], capsys, monkeypatch, module)
    assert err.startswith(f"{name}: --rows {tmp_path}: a folder; expected a rows file"), err


@pytest.mark.parametrize("module", [EM, ER, OB])
def test_rows_in_a_read_only_folder_is_one_line_before_any_pair(tmp_path, capsys, monkeypatch, module):
    def read_only(folder):  # as root, chmod does not stop writes: a read-only mount's error, simulated
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(PIO, "probe_write", read_only)
    err = _exit_2(module.main, ["--rows", str(tmp_path / "r.jsonl"), "--pairs", "1"], capsys, monkeypatch, module)
    assert f"cannot write in {tmp_path} (Read-only file system)" in err


def test_a_rows_file_whose_last_line_is_cut_is_named(tmp_path, capsys, monkeypatch):
    rows = _mono_rows(tmp_path / "r.jsonl", cut=True)
    err = _exit_2(EM.main, ["--rows", str(rows), "--pairs", "3"], capsys, monkeypatch, EM)
    assert f"--rows {rows}, line 2: cut off (a run stopped while writing it)" in err


def test_summarize_on_another_commands_rows_is_named(tmp_path, capsys, monkeypatch):
    rows = _mono_rows(tmp_path / "mono.jsonl")
    err = _exit_2(OB.main, ["--summarize", "--rows", str(rows)], capsys, monkeypatch, OB)
    assert f"--rows {rows}, line 1: not a row of other_backbones" in err


def test_summarize_of_another_splits_rows_is_refused(tmp_path, capsys, monkeypatch):
    rows = _mono_rows(tmp_path / "test.jsonl", split="test")
    err = _exit_2(EM.main, ["--summarize", "--split", "dev", "--rows", str(rows)], capsys, monkeypatch, EM)
    assert "not the development split's" in err and "these are the test split's rows, pass --split test" in err


def _weights(tmp_path: Path) -> Path:
    from safetensors.numpy import save_file

    from freereg_lib.models import weightcheck

    folder = tmp_path / "finetuned"
    (folder / "controlnet").mkdir(parents=True)
    (folder / "training.json").write_text(json.dumps({"stages": {"controlnet": {"loss": [1.0]}}}))
    save_file({"w": __import__("numpy").arange(64, dtype="float32")}, folder / "controlnet" / "model.safetensors")
    weightcheck.write_manifest(folder / "controlnet")
    data = bytearray((folder / "controlnet" / "model.safetensors").read_bytes())
    data[-3] ^= 0x10  # one bit of one weight
    (folder / "controlnet" / "model.safetensors").write_bytes(bytes(data))
    return folder


def test_evaluate_finetune_refuses_bit_flipped_weights(tmp_path, capsys, monkeypatch):
    weights = _weights(tmp_path)
    err = _exit_2(EF.main, ["--model", "finetuned", "--weights", str(weights), "--rows", str(tmp_path / "r.jsonl")],
                  capsys, monkeypatch, EF)
    assert "model.safetensors does not match its checksum" in err and not (tmp_path / "r.jsonl").exists()


def test_finetune_init_from_a_damaged_folder_is_one_line(tmp_path, capsys):
    weights = _weights(tmp_path)
    with pytest.raises(SystemExit) as info:
        FC.parse_args(["--init-from", str(weights), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "does not match its checksum" in err and "Traceback" not in err


# --- freereg register --out: checked writable before the registration runs --------------------------------

from freereg_lib.commands import cli  # noqa: E402
from freereg_lib.commands import user_inputs as UI  # noqa: E402


def test_register_out_in_a_read_only_folder_stops_before_registering(tmp_path, capsys, monkeypatch):
    from freereg_lib.data.datasets.icl import ICLSample
    from freereg_lib.report import pair_files as PF

    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    paths = PF.write_user_files(pair, tmp_path / "in")
    K = [f"{v:.6f}" for v in (pair.K_image[0, 0], pair.K_image[1, 1], pair.K_image[0, 2], pair.K_image[1, 2])]

    def read_only(folder):  # as root, chmod does not stop writes: a read-only mount's error, simulated
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(PIO, "probe_write", read_only)
    monkeypatch.setattr(cli, "write_outputs", lambda *a, **k: pytest.fail("registered, then failed to write"))
    out = tmp_path / "ro" / "result"
    rc = cli.main(["register", str(paths["image"]), str(paths["cloud"]), "--K", *K, "--image-depth", str(paths["image_depth"]),
                   "--backend", "stub",
                   "--ransac-iters", "50", "--views", "1", "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == 2 and f"--out {out}: cannot write in {tmp_path} (Read-only file system)" in captured.err, captured.err
    assert "Traceback" not in captured.err and "backend:" not in captured.out


# --- round 4's unclear cases: a config typo, a parity manifest naming a function with no folder ----------

def test_a_config_typo_in_a_closed_choice_is_named_when_made():
    from freereg_lib.config import FreeRegConfig

    with pytest.raises(ValueError, match=r"eval_few_matches='x' is not one of 'official', 'zero'"):
        FreeRegConfig(eval_few_matches="x")
    assert FreeRegConfig().override(eval_few_matches="zero").eval_few_matches == "zero"


def test_parity_fails_when_the_manifest_lists_a_function_with_no_folder(tmp_path, capsys):
    import shutil
    import sys

    sys.path.insert(0, str(ROOT / "tools"))
    import parity

    shutil.copytree(ROOT / "tests" / "fixtures" / "parity" / "return_uv", tmp_path / "return_uv")
    (tmp_path / "manifest.json").write_text(json.dumps({"functions": {"return_uv": {}, "fill_in_fast": {}}}))
    rc = parity.main([str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 1 and f"fill_in_fast: FAIL [the manifest lists it, and {tmp_path / 'fill_in_fast'} does not exist" in out


@pytest.mark.parametrize("module, argv", [
    ("diagnose", ["--weights", "{w}", "--pairs", "1"]), ("evaluate", ["--weights", "{w}", "--pairs", "1"]),
    ("evaluate_depth", ["--weights", "{w}"]), ("train_depth", ["--init-from", "{w}", "--out", "{o}"]),
    ("train_diffusion", ["--init-from", "{w}", "--out", "{o}"])])
def test_every_training_command_refuses_a_damaged_weights_folder_first(tmp_path, capsys, monkeypatch, module, argv):
    import importlib

    mod = importlib.import_module(f"freereg_lib.training.{module}")
    weights = _weights(tmp_path)
    for heavy in ("diagnose", "evaluate", "train", "run"):  # whatever would spend the work
        if callable(getattr(mod, heavy, None)):
            monkeypatch.setattr(mod, heavy, lambda *a, **k: pytest.fail("the work started"))
    argv = [a.format(w=weights, o=tmp_path / "out") for a in argv]
    with pytest.raises(SystemExit) as info:
        (mod.parse_args if hasattr(mod, "parse_args") else mod.main)(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "does not match its checksum" in err and "Traceback" not in err, err


def test_a_failed_registration_names_the_intrinsics_and_what_its_scale_says(tmp_path, capsys):
    """Round 4: a focal length off by 2x was reported as FAILED with no word of K."""
    from freereg_lib.data.datasets.icl import ICLSample
    from freereg_lib.report import pair_files as PF

    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    paths = PF.write_user_files(pair, tmp_path / "in")
    K = [f"{v:.6f}" for v in (2 * pair.K_image[0, 0], 2 * pair.K_image[1, 1], pair.K_image[0, 2], pair.K_image[1, 2])]
    rc = cli.main(["register", str(paths["image"]), str(paths["cloud"]), "--K", *K, "--image-depth",
                   str(paths["image_depth"]), "--backend", "stub", "--ransac-iters", "200", "--views", "1",
                   "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert rc == 0 and "result: FAILED" in out, out[-600:]
    check = next(line for line in out.splitlines() if line.startswith("check: "))
    assert "the intrinsics --K (fx 262.5" in check and "--depth-scale 1000" in check, check
    # A focal length doubled shrinks the image side: the scale is below 1 (0.5 for an exact pose; 200
    # RANSAC iterations on a wrong K give 0.5-0.7 depending on the candidate camera chosen).
    assert re.search(r"the scale 0\.[4-7]\d makes the image side (1\.[3-9]|2\.[0-4])x smaller", check), check


def test_depth_in_other_units_without_ground_truth_names_the_units(tmp_path, capsys):
    """Round 4: an image depth in 2x units, no ground truth: FAILED, the units not named."""
    from freereg_lib.data.datasets.icl import ICLSample
    from freereg_lib.report import pair_files as PF

    pair = PF.downscale_pair(ICLSample().pair(10, 40), 0.25)
    paths = PF.write_user_files(pair, tmp_path / "in")
    K = [f"{v:.6f}" for v in (pair.K_image[0, 0], pair.K_image[1, 1], pair.K_image[0, 2], pair.K_image[1, 2])]
    rc = cli.main(["register", str(paths["image"]), str(paths["cloud"]), "--K", *K, "--image-depth",
                   str(paths["image_depth"]), "--depth-scale", "2000", "--backend", "stub", "--ransac-iters", "200",
                   "--views", "1", "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert rc == 0 and "result: FAILED" in out, out[-600:]
    assert "and the depth units --depth-scale 2000: a wrong focal length or depth unit fails this way" in out
