"""Where a command's files and messages go: whether a folder takes files, probed before the work
starts, and a worker process's standard error sent to a log.

    from freereg_lib.commands.process_io import write_fault
    write_fault(Path("runs/mine"))   # "" or "cannot write in /work (Read-only file system)"
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path


def nearest_existing(path: Path) -> Path:
    """``path`` itself when it exists, else its nearest existing parent (the folder that would hold it)."""
    where = Path(path)
    while not where.exists() and where != where.parent:
        where = where.parent
    return where


def probe_write(folder: Path) -> None:
    """Create and remove a file in the existing ``folder``; an ``OSError`` when it cannot be written (as
    root ``os.access`` says yes to a read-only mount or ``/proc``, so only a write tells)."""
    fd, name = tempfile.mkstemp(prefix=".freereg-probe-", dir=folder)
    os.close(fd)
    os.unlink(name)


def write_fault(folder: Path) -> str:
    """Why a file cannot be created in ``folder`` (or, where it does not exist yet, in its nearest existing
    parent), as words without the argument's name: ``"<where> is a file, not a folder"`` or ``"cannot
    write in <where> (<reason>)"``; ``""`` when it can (:func:`probe_write`)."""
    where = nearest_existing(folder)
    if not where.is_dir():
        return f"{where} is a file, not a folder"
    try:
        probe_write(where)
    except OSError as exc:
        return f"cannot write in {where} ({exc.strerror or exc})"
    return ""


def redirect_stderr(log: Path) -> None:
    """Send this process's standard error, and its children's (they inherit it), to the end of ``log``:
    a worker's chatter is not the command's progress."""
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 2)
    os.close(fd)
