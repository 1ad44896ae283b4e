"""File readers shared by the loaders: RGB images, 16-bit depth PNGs, pose files, point clouds.

Every reader raises ``FileNotFoundError`` or ``ValueError`` naming the file and what was
expected, so a broken dataset tree is diagnosed at the first bad file.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageFile

from freereg_lib.geometry import cameras


def _exists(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"missing file: {path}")
    return path


def _truncated(path: Path) -> str:
    """Why the JPEG / PNG at ``path`` is cut short, or ``""`` when it is whole.

    OpenCV decodes a truncated JPEG without an error (the missing rows come out grey), so
    the end of the file is checked: a JPEG's end-of-image marker ``FF D9``, a PNG's ``IEND``
    chunk. A file without it at its end (some cameras append data after the image) is
    decoded by PIL with truncated images refused, which settles it.
    """
    with open(path, "rb") as f:
        head = f.read(8)
        f.seek(0, 2)
        f.seek(max(0, f.tell() - 4096))
        tail = f.read()
    if head[:3] == b"\xff\xd8\xff":
        kind, end = "JPEG", b"\xff\xd9"
    elif head == b"\x89PNG\r\n\x1a\n":
        kind, end = "PNG", b"IEND"
    else:
        return ""
    if end in tail.rstrip(b"\x00"):
        return ""

    old, ImageFile.LOAD_TRUNCATED_IMAGES = ImageFile.LOAD_TRUNCATED_IMAGES, False
    try:
        with Image.open(path) as im:
            im.load()
    except Exception as exc:  # PIL raises OSError (truncated) or SyntaxError / ValueError (corrupt)
        return f"a truncated {kind} (no {'end-of-image marker FF D9' if kind == 'JPEG' else 'IEND chunk'}; {exc})"
    finally:
        ImageFile.LOAD_TRUNCATED_IMAGES = old
    return ""


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as ``(H, W, 3) uint8`` RGB, its pixels as stored.

    A truncated JPEG or PNG is refused (OpenCV would silently return an image whose missing
    part is grey), naming the file. An EXIF orientation tag is **not** applied (OpenCV would
    rotate the photo but never its depth map, whose PNG has no such tag): intrinsics and depth
    describe the stored pixel grid, so both views stay as stored.
    """
    path = _exists(path)
    cut = _truncated(path)
    if cut:
        raise ValueError(f"{path} is {cut}: the file was cut short (an interrupted copy or download); copy it again")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ValueError(f"cannot decode image {path} (expected a PNG or JPEG RGB image)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


# What real datasets write where a depth sensor measured nothing: 0 everywhere, and the largest
# 16-bit value 65535 in 7-Scenes (part of 3DMatch) and in some ScanNet / 3DMatch exports.
INVALID_DEPTH = 65535
# Plausible median depth (m) of one depth frame of an indoor RGB-D dataset.
INDOOR_DEPTH_RANGE = (0.1, 20.0)
# Longest plausible translation (m) of a camera pose of an indoor dataset (world frames of
# 3DMatch, 7-Scenes, ScanNet scenes span a few metres to a few tens of metres).
INDOOR_MAX_TRANSLATION = 100.0


def depth_units_hint(median: float, expected: tuple[float, float], depth_scale: float | None = None) -> str:
    """Why a median depth (m) outside ``expected = (lo, hi)`` is likely in other units."""
    lo, hi = expected
    centre = np.sqrt(lo * hi)
    k = int(np.round(np.log10(median / centre) / 3)) * 3 if median > 0 else 0
    k = k or (3 if median > hi else -3)
    if k == 3:
        what = "millimetres read as metres"
    elif k == -3:
        what = "metres divided by 1000 once too often (or kilometres)"
    else:
        what = f"values off by a factor 10^{k}"
    scale = "" if depth_scale is None else (
        f"; depth_scale (raw value per metre) is {depth_scale:g}, try {depth_scale * 10.0 ** k:g}")
    return f"it looks like {what}{scale}"


def read_depth(path: str | Path, depth_scale: float = 1000.0, invalid: int | None = None,
               expected: tuple[float, float] | None = None) -> np.ndarray:
    """A 16-bit depth PNG as ``(H, W) float64`` metres (raw value / ``depth_scale``; 0 = none).

    ``invalid``: a raw value that marks "no measurement" besides 0 (``INVALID_DEPTH`` = 65535 in
    7-Scenes / 3DMatch / ScanNet), read as 0 (a hole) rather than 65.5 m. ``expected``: the
    ``(lo, hi)`` range in metres the median of the valid depths must fall in (the dataset's
    scene depths); outside it the file is refused with a units hint (e.g. millimetres read
    as metres: a wrong ``depth_scale``). A truncated PNG is refused naming the file.
    """
    path = _exists(path)
    cut = _truncated(path)
    if cut:
        raise ValueError(f"{path} is {cut}: the file was cut short (an interrupted copy or download); copy it again")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2:
        raise ValueError(f"cannot read {path} as a single-channel 16-bit depth PNG")
    if raw.dtype == np.uint8:
        raise ValueError(f"{path} is an 8-bit image, not a 16-bit depth PNG (depth in units of 1/{depth_scale:g} m); "
                         "an 8-bit picture of depth is a visualisation and has lost the metric values")
    depth = raw.astype(np.float64) / depth_scale
    if invalid is not None:
        depth[raw == invalid] = 0.0
    if expected is not None:
        valid = depth[depth > 0]
        if valid.size:
            median = float(np.median(valid))
            if not expected[0] <= median <= expected[1]:
                raise ValueError(
                    f"{path}: the median depth {median:.4g} m is outside the {expected[0]:g}..{expected[1]:g} m "
                    f"expected for this dataset; {depth_units_hint(median, expected, depth_scale)}")
    return depth


def read_pose_txt(path: str | Path, max_translation: float | None = None) -> np.ndarray:
    """A 4 x 4 pose written as 4 rows of 4 numbers, checked and made rigid.

    The rotation is replaced by its nearest rotation when it is off orthonormal by up to
    ``cameras.ORTHO_FIX`` (1e-2; 7-Scenes / 3DMatch pose files are orthonormal only to ~3e-4).
    Above ``cameras.ORTHO_WARN`` (1e-4) that is said in a ``RuntimeWarning`` naming the file,
    once per folder (a scene's pose files are all written alike). Refused, naming the file:
    not 4 x 4 numbers, a transposed pose (translation in the bottom row), a last row other
    than ``0 0 0 1``, a reflection or a matrix farther from a rotation, and (with
    ``max_translation`` in metres) a translation longer than that (millimetres read as metres).
    """
    path = _exists(path)
    try:
        T = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"cannot read {path} as a 4 x 4 pose of numbers: {exc}") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{path} does not hold a finite 4 x 4 pose (got shape {T.shape})")
    return checked_pose(T, path, max_translation)


_WARNED_POSE_FOLDERS: set[str] = set()


def checked_pose(T: np.ndarray, path: str | Path, max_translation: float | None = None) -> np.ndarray:
    """The pose ``T`` read from ``path`` through :func:`~freereg_lib.geometry.cameras.check_pose`
    (see :func:`read_pose_txt`), errors and the warning naming the file."""

    out = cameras.check_pose(T, str(path), max_translation=max_translation, warn=False)
    ortho = cameras.orthonormality(np.asarray(T, dtype=np.float64)[:3, :3])
    folder = str(Path(path).resolve().parent)
    if ortho > cameras.ORTHO_WARN and folder not in _WARNED_POSE_FOLDERS:
        _WARNED_POSE_FOLDERS.add(folder)
        warnings.warn(f"{path}: R is orthonormal only to {ortho:.1e} (max |R^T R - I|, above "
                      f"{cameras.ORTHO_WARN:g}); re-orthonormalised (the nearest rotation, by SVD; up to "
                      f"{cameras.ORTHO_FIX:g} is accepted). Further pose files in {folder} are fixed the same "
                      "way without a warning", RuntimeWarning, stacklevel=3)
    return out


def read_redwood_log(path: str | Path) -> dict[int, np.ndarray]:
    """A Redwood ``.log`` trajectory: per entry a header ``id id id+1`` and a 4 x 4 pose.

    Returns ``{frame_id: T_world_cam}``.
    """
    path = _exists(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) % 5:
        raise ValueError(f"{path}: {len(lines)} non-empty lines, a .log file has 5 per pose")
    poses = {}
    for k in range(0, len(lines), 5):
        try:
            frame = int(lines[k][0])
            poses[frame] = np.array(lines[k + 1 : k + 5], dtype=np.float64)
        except ValueError as exc:
            raise ValueError(f"{path}, entry at non-empty line {k + 1}: expected a header 'id id id+1' and "
                             f"4 rows of 4 numbers ({exc})") from None
        if poses[frame].shape != (4, 4) or not np.all(np.isfinite(poses[frame])):
            raise ValueError(f"{path}, frame {frame}: expected 4 rows of 4 finite numbers")
    return poses


def read_points(path: str | Path, drop_nonfinite: bool = True) -> np.ndarray:
    """A point cloud file as ``(N, 3) float64``: ``.ply`` (ASCII or binary), ``.npy`` (an
    ``(N, 3)`` array, or ``(N, k >= 3)`` whose first three columns are x, y, z) or a text
    file ``.xyz`` / ``.txt`` / ``.pts`` (one point a line, x y z first).

    Points with NaN or inf are dropped with a warning naming the count (with
    ``drop_nonfinite=False`` they are kept, and :meth:`~freereg_lib.data.pair.Pair.validate`
    refuses them). A missing file raises ``FileNotFoundError``; an unreadable or empty one
    ``ValueError``, each naming the file.
    """
    path = _exists(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        pts = read_ply_points(path)
    elif suffix in (".npy", ".xyz", ".txt", ".pts"):
        try:
            pts = np.load(path, allow_pickle=False) if suffix == ".npy" else np.loadtxt(path, ndmin=2)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"cannot read the points of {path}: {exc}") from None
        if pts.ndim != 2 or pts.shape[1] < 3 or not np.issubdtype(pts.dtype, np.number):
            raise ValueError(f"{path} holds an array of shape {pts.shape} {pts.dtype}; expected (N, 3) numbers "
                             "(or (N, k >= 3) with x, y, z first)")
        pts = np.asarray(pts[:, :3], dtype=np.float64)
    else:
        raise ValueError(f"{path}: unknown point cloud format {suffix!r}; expected .ply, .npy, .xyz, .txt or .pts")
    if len(pts) == 0:
        raise ValueError(f"{path} holds no point (an empty point cloud)")
    keep = np.isfinite(pts).all(axis=1)
    if drop_nonfinite and not keep.all():
        if not keep.any():
            raise ValueError(f"{path}: all {len(pts)} points are NaN or inf")
        warnings.warn(f"{path}: dropped {int((~keep).sum())} of {len(pts)} points that are NaN or inf",
                      RuntimeWarning, stacklevel=2)
        pts = pts[keep]
    return pts


_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
              "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
              "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8"}


def read_ply_points(path: str | Path) -> np.ndarray:
    """The ``x y z`` of the vertices of a ``.ply`` file (ASCII or binary), ``(N, 3) float64``.

    Read here rather than with Open3D, whose reader returns uninitialised memory instead of
    an error when a file is malformed. The vertex element must come first (as every point
    cloud writer puts it); anything unreadable raises ``ValueError`` naming the file.
    """
    path = _exists(path)
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[data.index(b"\n", end) + 1:]
    fmt = next((ln.split()[1] for ln in header if ln.startswith("format ")), "")
    elements = [ln.split() for ln in header if ln.startswith(("element ", "property "))]
    if not elements or elements[0][:2] != ["element", "vertex"]:
        raise ValueError(f"{path}: the first element must be 'vertex'")
    count, props = int(elements[0][2]), []
    for words in elements[1:]:
        if words[0] == "element":
            break
        if words[1] == "list" or words[1] not in _PLY_TYPES:
            raise ValueError(f"{path}: unsupported vertex property {' '.join(words)!r}")
        props.append((words[2], _PLY_TYPES[words[1]]))
    if not {"x", "y", "z"} <= {n for n, _ in props}:
        raise ValueError(f"{path}: vertices have no x, y, z properties")
    if count == 0:
        raise ValueError(f"{path} holds no vertex (an empty point cloud)")
    only_vertices = sum(words[0] == "element" for words in elements) == 1
    try:
        if fmt == "ascii":
            lines = [ln for ln in body.decode("ascii").splitlines() if ln.strip()]
            if only_vertices and len(lines) > count:
                raise ValueError(f"the header declares {count} vertices but the body holds {len(lines)} lines of "
                                 "them (a header count left smaller than its body would read part of the cloud)")
            table = np.loadtxt(lines[:count], ndmin=2)
            cols = [n for n, _ in props]
            xyz = table[:, [cols.index("x"), cols.index("y"), cols.index("z")]]
        elif fmt in ("binary_little_endian", "binary_big_endian"):
            order = "<" if fmt == "binary_little_endian" else ">"
            dtype = np.dtype([(n, order + t) for n, t in props])
            if only_vertices and len(body) >= (count + 1) * dtype.itemsize:
                raise ValueError(f"the header declares {count} vertices but the body holds "
                                 f"{len(body) // dtype.itemsize} ({len(body)} bytes of {dtype.itemsize}; a header count "
                                 "left smaller than its body would read part of the cloud)")
            rec = np.frombuffer(body, dtype=dtype, count=count)
            xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
        else:
            raise ValueError(f"unknown format {fmt!r}")
    except ValueError as exc:
        raise ValueError(f"cannot read the vertices of {path}: {exc}") from None
    if len(xyz) != count or len(xyz) == 0:
        raise ValueError(f"{path}: expected {count} vertices, read {len(xyz)}")
    return np.asarray(xyz, dtype=np.float64)
