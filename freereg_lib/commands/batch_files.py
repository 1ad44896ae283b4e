"""Two guards of :mod:`freereg_lib.commands.batch`: the grid reader that refuses a duplicate key, and the
lock that keeps a second runner out of a run folder.
"""
from __future__ import annotations

import contextlib
import os
import socket
import time
from pathlib import Path


def unique_key_loader():
    """``yaml.SafeLoader`` that refuses a mapping repeating a key (PyYAML keeps the last one
    silently: ``n_pairs: 1`` then ``n_pairs: 2`` would run 2); merge keys (``<<``) still merge."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=deep)
                    if not isinstance(key, (str, int, float, bool)):
                        continue  # an unhashable key: PyYAML's own error follows
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r} (first at line {seen[key]}; YAML would keep "
                            "only the last: remove one)", key_node.start_mark)
                    seen[key] = key_node.start_mark.line + 1
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


LOCK_FILE = ".runner.lock"


class RunFolderLocked(RuntimeError):
    """Another runner holds the run folder (:func:`lock_run_folder`)."""


@contextlib.contextmanager
def lock_run_folder(run_dir: Path):
    """Hold ``<run_dir>/.runner.lock`` (an exclusive ``fcntl.flock``) while the block runs, so a
    second runner on the same folder stops at once (:class:`RunFolderLocked`, naming the holder)
    instead of executing every job a second time. The lock ends with the process, even a killed
    one; where ``fcntl`` does not exist (Windows) nothing is locked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = run_dir / LOCK_FILE
    with open(path, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            raise RunFolderLocked(
                f"{run_dir} is in use by another runner ({holder}); wait for it to finish, or give this run "
                "its own --name or --runs-dir") from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
        f.flush()
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
