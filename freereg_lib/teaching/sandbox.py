"""The student's process: its limits, its file-system confinement, and its end.

* :func:`limit` (in the student's process, before any student code): ``RLIMIT_AS`` (memory),
  ``RLIMIT_CPU``, ``RLIMIT_FSIZE`` (largest file written), no core dumps, and a cap on new
  processes. As root, the grader starts it as an unprivileged user (:func:`student_ids`).
* :func:`confine`: Linux Landlock (kernel 5.13+, no privileges needed), also before any
  student code: reading only the Python standard library, NumPy and the system's libraries
  (not ``freereg_lib``, the project's notebooks, answer keys or anything else of yours),
  writing only in the submission's scratch folder, no TCP, and (kernel 6.12+) no signals to
  processes outside. Where Landlock is missing the grade says so.
* :func:`end_all` (in the grader): SIGKILL to the student's process group and session, to its
  cgroup where one could be made, and to every process left that carries the submission's
  marker in its environment, sits in its session or process group, was adopted by the grader
  (a sub-reaper) from outside its session, or descends from any of those: a child that
  called ``setsid()`` is found all the same.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import resource
import signal
import sys
import time
from pathlib import Path

MARKER_ENV = "FREEREG_GRADE_MARKER"
_PR_SET_NO_NEW_PRIVS, _PR_SET_CHILD_SUBREAPER = 38, 36
_SYS_CREATE, _SYS_ADD_RULE, _SYS_RESTRICT = 444, 445, 446  # the same on x86_64 and arm64
_FS_EXECUTE, _FS_WRITE, _FS_READ_FILE, _FS_READ_DIR = 1, 2, 4, 8
_FS_ALL = {1: (1 << 13) - 1, 2: (1 << 14) - 1, 3: (1 << 15) - 1, 4: (1 << 15) - 1}  # per ABI; 5+: 1 << 16
_READ = _FS_EXECUTE | _FS_READ_FILE | _FS_READ_DIR


def _libc():
    return ctypes.CDLL(None, use_errno=True)


def limit(memory_mb: int, cpu_s: int, file_mb: int, processes: int = 64) -> None:
    """Resource limits of this process and all it starts (soft = hard: they cannot be raised)."""
    settings = [(resource.RLIMIT_AS, memory_mb * 2**20), (resource.RLIMIT_CPU, cpu_s),
                (resource.RLIMIT_FSIZE, file_mb * 2**20), (resource.RLIMIT_CORE, 0)]
    if hasattr(resource, "RLIMIT_NPROC") and os.getuid() != 0:  # per user: what runs now, plus some
        settings.append((resource.RLIMIT_NPROC, len(_user_pids()) + processes))
    for which, value in settings:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(which, (value, value))


def landlock_abi() -> int:
    """The kernel's Landlock ABI version; 0 where there is none."""
    if not sys.platform.startswith("linux"):
        return 0
    try:
        libc = _libc()
        libc.syscall.restype = ctypes.c_long
        abi = libc.syscall(_SYS_CREATE, None, ctypes.c_size_t(0), ctypes.c_uint32(1))
    except (OSError, AttributeError):
        return 0
    return max(int(abi), 0)


def confine(read: list[Path], write: list[Path]) -> int:
    """Landlock this process (and its children, for good): returns the ABI used, 0 if unavailable."""
    abi = landlock_abi()
    if abi <= 0:
        return 0
    libc = _libc()
    libc.syscall.restype = ctypes.c_long
    fs_all = _FS_ALL.get(abi, (1 << 16) - 1)
    net = 3 if abi >= 4 else 0         # bind and connect TCP: nowhere
    scoped = 3 if abi >= 6 else 0      # abstract unix sockets and signals: only inside
    attr = (ctypes.c_uint64 * 3)(fs_all, net, scoped)
    size = 8 if abi < 4 else (16 if abi < 6 else 24)
    fd = libc.syscall(_SYS_CREATE, ctypes.byref(attr), ctypes.c_size_t(size), ctypes.c_uint32(0))
    if fd < 0:
        return 0

    class PathBeneath(ctypes.Structure):
        _pack_ = 1
        _fields_ = [("allowed_access", ctypes.c_uint64), ("parent_fd", ctypes.c_int32)]

    def allow(path: Path, access: int) -> None:
        try:
            pfd = os.open(path, os.O_PATH | os.O_CLOEXEC)
        except OSError:
            return
        try:
            if not path.is_dir():
                access &= _FS_EXECUTE | _FS_WRITE | _FS_READ_FILE | (1 << 14) | (1 << 15)
            rule = PathBeneath(access & fs_all, pfd)
            libc.syscall(_SYS_ADD_RULE, ctypes.c_int(fd), ctypes.c_int(1), ctypes.byref(rule), ctypes.c_uint32(0))
        finally:
            os.close(pfd)

    try:
        for p in read:
            allow(Path(p), _READ)
        for p in write:
            allow(Path(p), fs_all)
        if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
            return 0
        if libc.syscall(_SYS_RESTRICT, ctypes.c_int(fd), ctypes.c_uint32(0)) != 0:
            return 0
    finally:
        os.close(fd)
    return abi


# --------------------------------------------------------------------------------------
# The grader's side.

def subreaper(on: bool) -> None:
    """Orphans of the student's processes are re-parented to this process instead of init."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            _libc().prctl(_PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0)


def make_cgroup(token: str) -> Path | None:
    """A cgroup (v2) of its own for the submission, where this process may make one; else None."""
    try:
        line = next(ln for ln in Path("/proc/self/cgroup").read_text().splitlines() if ln.startswith("0::"))
    except (OSError, StopIteration):
        return None
    for root in (Path("/sys/fs/cgroup"), Path("/sys/fs/cgroup/unified")):
        base = root / line[3:].lstrip("/")
        if (base / "cgroup.procs").is_file():
            group = base / f"freereg-grade-{token}"
            try:
                group.mkdir()
            except OSError:
                return None
            if (group / "cgroup.kill").exists():
                return group
            with contextlib.suppress(OSError):
                group.rmdir()
            return None
    return None


def _stat(pid: int) -> tuple[int, int, int] | None:
    """(ppid, process group, session) of a live process; None when gone or a zombie."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2:].split()
    if fields[0] in ("Z", "X"):
        return None
    return int(fields[1]), int(fields[2]), int(fields[3])


STUDENT_USER = "nobody"  # who runs the students' code when the grader runs as root


def _can_run_python(uid: int, gid: int) -> bool:
    """Whether ``uid`` can start this Python and import NumPy (a Python under /root cannot be run by others)."""
    import subprocess

    import numpy

    site = os.path.dirname(os.path.dirname(os.path.realpath(numpy.__file__)))
    try:
        code = f"import sys; sys.path[:0] = [{site!r}]; import numpy"
        return subprocess.run([sys.executable, "-I", "-S", "-c", code], user=uid, group=gid, extra_groups=[],
                              cwd="/", env={"PATH": "/usr/bin:/bin"}, stdin=subprocess.DEVNULL, capture_output=True,
                              timeout=60).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


_IDS: dict[str, tuple[int, int] | None] = {}


def student_ids() -> tuple[int, int] | None:
    """``(uid, gid)`` the student's process runs as when the grader is root: :data:`STUDENT_USER`'s,
    where that user can run this Python (checked once). None when the grader is not root, or when
    no such user can run it: then the student's process, still uid 0, drops every capability itself
    (:func:`drop_capabilities`) and its Landlock rules leave out root's files (``/etc/shadow``, other
    processes' ``/proc`` entries), so it can read no more than an unprivileged user could."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return None
    if "ids" not in _IDS:
        import pwd

        try:
            entry = pwd.getpwnam(STUDENT_USER)
            ids = (entry.pw_uid, entry.pw_gid)
        except KeyError:
            ids = None
        _IDS["ids"] = ids if ids and _can_run_python(*ids) else None
    return _IDS["ids"]


_PR_CAPBSET_DROP, _CAP_VERSION_3 = 24, 0x20080522


def drop_capabilities() -> bool:
    """Drop every capability of this process for good (bounding set, effective, permitted, inheritable):
    uid 0 without them cannot load kernel modules, use raw sockets, override file permissions or
    trace others. True when the process holds none afterwards."""
    if not sys.platform.startswith("linux"):
        return False  # no capabilities to drop elsewhere: root's process is refused (student.main)
    try:
        libc = _libc()
        prctl, capset = libc.prctl, libc.capset
    except (OSError, AttributeError):
        return False
    for cap in range(64):
        prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0)  # fails (EINVAL) past the last capability: fine

    class Header(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

    class Data(ctypes.Structure):
        _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]

    data = (Data * 2)()
    if capset(ctypes.byref(Header(_CAP_VERSION_3, 0)), data) != 0:
        return False
    with contextlib.suppress(OSError):
        status = Path("/proc/self/status").read_text()
        return all(int(line.split()[1], 16) == 0 for line in status.splitlines()
                   if line.startswith(("CapEff:", "CapPrm:", "CapBnd:")))
    return True


def _user_pids(uids: set[int] | None = None) -> list[int]:
    """The live processes of ``uids`` (default: this process's user and, as root, the students' user)."""
    if uids is None:
        uids = {os.getuid()}
        if os.getuid() == 0:
            uids |= {ids[0]} if (ids := student_ids()) else set()
    pids = []
    if not os.path.isdir("/proc"):  # no /proc (macOS): the session and group kill are what there is
        return pids
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                if os.stat(f"/proc/{entry}").st_uid in uids:
                    pids.append(int(entry))
    return pids


def _has_marker(pid: int, marker: str) -> bool:
    try:
        return f"{MARKER_ENV}={marker}".encode() in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return False


def leftovers(sid: int, marker: str) -> list[int]:
    """The processes of a submission still alive (see the module's docstring)."""
    me, my_sid = os.getpid(), os.getsid(0)
    table = {pid: st for pid in _user_pids() if pid != me and (st := _stat(pid))}
    found = {pid for pid, (ppid, pgid, psid) in table.items()
             if psid == sid or pgid == sid or (ppid == me and psid != my_sid) or _has_marker(pid, marker)}
    grown = True
    while grown:  # and everything they started
        more = {pid for pid, (ppid, _, _) in table.items() if ppid in found and pid not in found}
        found |= more
        grown = bool(more)
    return sorted(found)


def end_all(pid: int, marker: str, cgroup: Path | None = None, rounds: int = 50) -> int:
    """Kill the student's process ``pid`` (a session leader) and all it left; returns how many
    other processes were found and killed. Reaps the adopted ones."""
    with contextlib.suppress(OSError):
        os.killpg(pid, signal.SIGKILL)
    if cgroup is not None:
        with contextlib.suppress(OSError):
            (cgroup / "cgroup.kill").write_text("1")
    killed: set[int] = set()
    for _ in range(rounds):
        found = [p for p in leftovers(pid, marker) if p != pid]
        if not found:
            break
        for p in found:
            with contextlib.suppress(OSError):
                os.kill(p, signal.SIGKILL)
        killed |= set(found)
        time.sleep(0.02)
    for p in killed:  # adopted orphans are our children now: reap them
        for _ in range(100):
            try:
                if os.waitpid(p, os.WNOHANG)[0]:
                    break
            except OSError:  # not our child (or gone): nothing to reap
                break
            time.sleep(0.01)
    if cgroup is not None:
        for _ in range(50):
            try:
                cgroup.rmdir()
                break
            except OSError:
                time.sleep(0.02)
    return len(killed)
