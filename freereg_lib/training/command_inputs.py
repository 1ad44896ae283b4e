"""A training command's files checked before it spends work: its rows file and its weights folders.

The split evaluations append one JSON line per pair to ``--rows`` and summarize them later. A
``--rows`` that names a folder, sits in a read-only folder, ends in a line cut off by a killed run,
holds another command's rows, or (with ``--summarize``) another split's pairs, used to surface as
a traceback after the first pair was computed and lost, or as a summary of the wrong split.
:func:`rows_fault` says which, as one line naming the file (and line) and what was expected;
:func:`exit_on_bad_rows` prints it and exits with status 2 before any pair runs.

:func:`weights_fault` checks a weights folder the way the loaders do (whole ``.safetensors``
files, the ``SHA256SUMS`` of every sub-folder, a readable ``training.json``), so a fine-tuning or
an evaluation refuses a damaged folder up front instead of writing rows from it.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from freereg_lib.commands.process_io import write_fault
from freereg_lib.training.splits import SPLITS


def rows_fault(path: str | Path, command: str, row_key: str, split: str | None = None,
               writing: bool = False) -> str:
    """What is wrong with the rows file ``path`` of ``command`` ("" when nothing), as one line.

    ``row_key``: a key every row of this command carries (another command's rows lack it);
    ``split``: with ``--summarize``, the split its pairs must come from; ``writing``: the command
    will append to it."""
    path = Path(path)
    if path.is_dir():
        return f"--rows {path}: a folder; expected a rows file (JSON lines), e.g. {path / 'rows.jsonl'}"
    if path.exists():
        try:
            raw = path.read_bytes()
        except OSError as exc:
            return f"--rows {path}: cannot read it ({exc.strerror or exc})"
        lines = raw.decode("utf-8", "replace").splitlines()
        for no, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except ValueError as exc:
                if no == len(lines) and not raw.endswith(b"\n"):
                    return (f"--rows {path}, line {no}: cut off (a run stopped while writing it); delete that last "
                            "line (the pairs before it are kept) and run again")
                return f"--rows {path}, line {no}: not JSON ({exc}); expected one JSON object per pair"
            if not (isinstance(rec, dict) and isinstance(rec.get("k"), int) and isinstance(rec.get("rows"), list)
                    and all(isinstance(r, dict) and row_key in r for r in rec["rows"])):
                return (f"--rows {path}, line {no}: not a row of {command} (expected 'k', and 'rows' each with "
                        f"'{row_key}'): another command's rows file?")
            if split is not None and "pair_seed" in rec:
                want = SPLITS[split].pair_seeds(rec["k"] + 1)[rec["k"]]
                if rec["pair_seed"] != want:
                    named = next((name for name, s in SPLITS.items() if name != "development"
                                  and s.pair_seeds(rec["k"] + 1)[rec["k"]] == rec["pair_seed"]), None)
                    return (f"--rows {path}, line {no}: pair {rec['k']} has the seed {rec['pair_seed']}, not the "
                            f"{SPLITS[split].name} split's ({want})" + (f": these are the {named} split's rows, "
                            f"pass --split {named}" if named else ""))
    if writing:
        if path.exists():
            try:
                with open(path, "ab"):
                    pass
            except OSError as exc:
                return f"--rows {path}: cannot append to it ({exc.strerror or exc}); give a writable rows file"
        why = write_fault(path.parent)
        if why:
            return f"--rows {path}: {why}; give a rows file in a writable folder"
    return ""


def exit_on_bad_rows(argv, command: str, row_key: str) -> None:
    """Check the ``--rows`` of a split command's ``argv`` (:func:`rows_fault`) and exit with status 2
    and one line ``<command>: ...`` when it is bad; return quietly otherwise (argparse says the rest)."""
    import argparse

    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--rows")
    pre.add_argument("--split", default="test")
    pre.add_argument("--summarize", action="store_true")
    known, _ = pre.parse_known_args(argv)
    if not known.rows or known.split not in SPLITS:
        return
    fault = rows_fault(known.rows, command, row_key, known.split if known.summarize else None,
                       writing=not known.summarize)
    if fault:
        print(f"{command}: {fault}", file=sys.stderr)
        raise SystemExit(2)


def weights_fault(folder: str | Path) -> str:
    """What is wrong with the weights folder ``folder`` ("" when nothing, or no such folder yet): a
    file that is not whole or does not match the ``SHA256SUMS`` of its folder, in ``folder`` or any
    sub-folder, or a ``training.json`` that is not JSON."""
    from freereg_lib.models.weightcheck import WeightsError, check_folder

    folder = Path(folder)
    if not folder.exists():
        return ""  # not made yet (a later phase's --init-from): the command's own message when it is needed
    if not folder.is_dir():
        return f"{folder}: not a folder; expected an exported weights folder"
    for d in [folder, *sorted(p for p in folder.rglob("*") if p.is_dir())]:
        try:
            check_folder(d)
        except WeightsError as exc:
            return str(exc)
        except OSError as exc:
            return f"{d}: cannot read it ({exc.strerror or exc})"
    facts = folder / "training.json"
    if facts.exists():
        try:
            json.loads(facts.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            return f"{facts}: not readable as JSON ({exc}); expected the training facts of an exported weights folder"
    return ""
