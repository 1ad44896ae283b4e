"""Bad input, round 5: commands that never destroy a user's files, and crashes that became one line.

The book (``python -m freereg_lib.commands.book``) emptied its ``--out`` folder with ``shutil.rmtree``
before building: ``--out RUN`` deleted the executed notebooks, ``--out DIR`` a user's files. Now it
writes only into a new or empty folder or a site it built (a mark file), refuses ``--out`` equal to or
above an input, and checks the run folder, the site and the figures before it stages anything. Each
case here stops before Sphinx starts, or fakes Sphinx, so no test builds a site.
"""
from __future__ import annotations

import errno
import subprocess
from pathlib import Path

import pytest

from freereg_lib.commands import book as B
from freereg_lib.commands import book_inputs as BI

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
    real = BI._probe_write

    def probe(folder):  # as root, chmod does not stop writes: a read-only mount's error, simulated
        if Path(folder).resolve() == run.resolve():
            raise OSError(errno.EROFS, "Read-only file system")
        real(folder)

    monkeypatch.setattr(BI, "_probe_write", probe)
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
