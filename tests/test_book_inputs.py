"""The book command on bad sources: one line naming the file and what was expected, exit 2.

A run folder is faked in ``tmp_path`` (one good notebook of the repository beside the bad one);
every case stops before Sphinx starts (:mod:`freereg_lib.commands.book_inputs`), so no test here
builds a site. Before the check, these cases ended in a traceback (``JSONDecodeError``,
``KeyError: 'cells'``, ``IsADirectoryError``, ``UnicodeDecodeError``) or a Sphinx failure.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from freereg_lib.commands import book as B
from freereg_lib.commands import book_inputs as BI

ROOT = Path(__file__).resolve().parents[1]
GOOD = ROOT / "notebooks" / "03_fusion.ipynb"


def _run(tmp_path: Path, kind: str) -> tuple[Path, Path]:
    """A run folder holding a good notebook and a bad one of ``kind``; the bad file's path."""
    run = tmp_path / "run"
    run.mkdir()
    (run / GOOD.name).write_bytes(GOOD.read_bytes())
    bad = run / "01_diffusion_features.ipynb"
    if kind == "truncated":
        bad.write_bytes(GOOD.read_bytes()[:5000])
    elif kind == "empty":
        bad.write_bytes(b"")
    elif kind == "empty-object":
        bad.write_text("{}")
    elif kind == "directory":
        bad.mkdir()
    elif kind == "cells-not-a-list":
        bad.write_text('{"cells": {}, "nbformat": 4, "metadata": {}}')
    return run, bad


def _book(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as info:
        B.main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "Traceback" not in err, err
    assert err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("kind, says", [
    ("truncated", "not JSON at line"), ("empty", "an empty file"), ("empty-object", "no 'cells' and no 'nbformat'"),
    ("directory", "a folder; expected a notebook file"), ("cells-not-a-list", "'cells' is a dict, not a list")])
def test_a_bad_notebook_is_named_before_sphinx(tmp_path, capsys, monkeypatch, kind, says):
    run, bad = _run(tmp_path, kind)
    monkeypatch.setattr(B, "build_book", lambda *a, **k: pytest.fail("the build started"))
    err = _book([str(run)], capsys)
    assert err.startswith(f"book: {bad}: ") and says in err, err
    assert "expected" in err
    if kind == "truncated":
        assert "cut off" in err


def test_a_docs_page_that_is_not_utf8_is_named(tmp_path, capsys, monkeypatch):
    run, _ = _run(tmp_path, "none")
    root = tmp_path / "project"
    (root / "docs").mkdir(parents=True)
    (root / "docs" / "good.md").write_text("# Good\n", encoding="utf-8")
    page = root / "docs" / "latin1.md"
    page.write_bytes("# Caf\u00e9\n\nd\u00e9j\u00e0 vu\n".encode("latin-1"))
    monkeypatch.setattr(B, "ROOT", root)
    monkeypatch.setattr(B, "build_book", lambda *a, **k: pytest.fail("the build started"))
    err = _book([str(run)], capsys)
    assert err.startswith(f"book: {page}: not UTF-8 (byte 0xe9 on line 1)") and "expected a Markdown page" in err


def test_good_sources_pass_and_a_missing_run_folder_is_named(tmp_path):
    run, _ = _run(tmp_path, "none")
    assert BI.source_fault(run, ROOT / "docs", [ROOT / p for p in B.EXTRA_PAGES]) == ""
    assert BI.source_fault(ROOT / "notebooks", ROOT / "docs") == ""  # the repository's own notebooks
    missing = tmp_path / "nowhere"
    assert BI.source_fault(missing, ROOT / "docs").startswith(f"{missing}: no such folder; expected the run folder")


def test_the_command_exits_2_without_a_traceback(tmp_path):
    run, bad = _run(tmp_path, "truncated")
    proc = subprocess.run([sys.executable, "-m", "freereg_lib.commands.book", str(run)], capture_output=True,
                          text=True, timeout=120, cwd=ROOT, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(f"book: {bad}: not JSON") and proc.stderr.count("\n") == 1
    assert not (run / "book_src").exists() and not (run / "site").exists()  # nothing staged, nothing built
