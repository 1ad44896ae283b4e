"""The repository stands on its own: no tracked text file points to files outside it (the folder
beside the repository that some sessions had, its design notes) or to the tracker's issue numbers,
which a reader of a clone cannot open. History belongs in docs/changelog.md, told by date."""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Spelt in pieces so that this file does not match itself.
OUTSIDE = re.compile("|".join([r"\bshar" + r"ed/", r"\bDESIG" + r"N\.md\b", r"\b[Ii]ssu" + r"es?\s+#?\d+", r"#\d{1,3}\b(?=\s*\))"]))


def _tracked_text_files() -> list[Path]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip("not a git checkout")
    files = []
    for name in out.stdout.split("\0"):
        path = ROOT / name
        if not name or not path.is_file() or path.stat().st_size > 5_000_000:
            continue
        head = path.read_bytes()[:8192]
        if b"\0" in head:  # binary (weights, PNGs)
            continue
        files.append(path)
    return files


def hits(text: str) -> list[str]:
    return [line.strip()[:160] for line in text.splitlines() if OUTSIDE.search(line)]


def test_the_pattern_sees_each_kind_of_mention():
    assert len(hits("see ../shar" + "ed/paper/FACTS.md\nas DESIGN" + ".md says\n(iss" + "ue 42)\nIssue" + " 43: x\nok")) == 4
    assert not hits("the shared memory of a worker; issue a warning; 3 issues remain; tissue 4")


def test_no_tracked_file_mentions_outside_files_or_issue_numbers():
    found = []
    for path in _tracked_text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        found += [f"{path.relative_to(ROOT)}: {h}" for h in hits(text)]
    assert not found, f"{len(found)} mentions of files outside the repository or of issue numbers:\n" + "\n".join(found[:60])
