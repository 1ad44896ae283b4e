import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: see Makefile
# `make test` runs two pytest workers (-n 2); torch's OpenMP threads of two processes on two
# cores spin against each other (two at once took 8.5x the time of one after the other; one
# thread each, 0.5x: benchmarks/README.md, "Threads of parallel kernels"). Notebook kernels
# started by the tests inherit this.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import json
from pathlib import Path

import numpy as np
import pytest

from freereg_lib.geometry import cameras

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
# The batch runner's job notebook is run by the batch tests; under `--nbmake` it is not a test itself.
collect_ignore_glob = ["fixtures/*.ipynb"]


def _kill_kernels_after_nbmake_runs() -> None:
    """nbmake's kernels are killed once their notebook has run, as papermill's are here
    (``shutdown_kernel="immediate"``) and in ``freereg_lib.commands.batch``: a graceful exit
    tears down torch, diffusers and Open3D, ~1 s of CPU a kernel, and now and then waits 2.5 s
    more for the kernel to go. nbmake has no option for it, so its client gets the default."""
    try:
        import nbclient
        import nbmake.nb_run
    except ImportError:
        return

    class KilledAfterRun(nbclient.NotebookClient):
        def __init__(self, *args, **kwargs):
            kwargs.setdefault("shutdown_kernel", "immediate")
            super().__init__(*args, **kwargs)

    nbmake.nb_run.NotebookClient = KilledAfterRun


_kill_kernels_after_nbmake_runs()


# `make test` runs two workers (`-n 2 --dist loadfile`) with the scheduler below: a file's tests stay
# on one worker (they share module fixtures, e.g. the real-frame rows), except the notebook runs of
# test_notebooks.py, each its own unit; units go out longest first by the seconds recorded in
# tests/durations.json (`pytest --record-durations ...` rewrites it), unknown ones last. xdist's own
# order (most tests first) left the one-test notebooks, the longest units, for the end, and the ten
# notebook runs of test_notebooks.py, as one unit, ran last on one worker while the other sat idle.
ALONE = ("test_notebooks.py::test_notebook_runs_with_other_parameters", "test_notebooks.py::test_reproduce_quick")
DURATIONS = Path(__file__).resolve().parent / "durations.json"


def unit_of(nodeid: str) -> str:
    return nodeid if any(key in nodeid for key in ALONE) else nodeid.split("::", 1)[0]


def pytest_addoption(parser):
    parser.addoption("--record-durations", action="store_true",
                     help=f"write each scheduling unit's seconds to {DURATIONS.name}")


def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") != "loadfile":
        return None
    from collections import OrderedDict

    from xdist.scheduler import LoadScopeScheduling

    seconds = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}

    class LongestFirstQueue(OrderedDict):
        def popitem(self, last: bool = True):
            if last or not self:
                return super().popitem(last)
            unit = max(self, key=lambda u: seconds.get(u, 0.0))  # the first of equals: collection order
            return unit, self.pop(unit)

    class LongestFirst(LoadScopeScheduling):
        def __init__(self, config, log=None):
            super().__init__(config, log)
            self.workqueue = LongestFirstQueue()

        def _split_scope(self, nodeid: str) -> str:
            return unit_of(nodeid)

    return LongestFirst(config, log)


_recorded: dict[str, float] = {}


def pytest_runtest_logreport(report):
    if report.when in ("setup", "call", "teardown"):
        unit = unit_of(report.nodeid)
        _recorded[unit] = _recorded.get(unit, 0.0) + report.duration


def pytest_sessionfinish(session):
    if session.config.getoption("record_durations") and not hasattr(session.config, "workerinput"):
        DURATIONS.write_text(json.dumps({u: round(s, 1) for u, s in sorted(_recorded.items())}, indent=0) + "\n")


def load_tool(name: str):
    """The script ``tools/<name>.py`` as a module (the tools folder is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, NOTEBOOKS.parent / "tools" / f"{name}.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    return tool


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def random_pose(rng: np.random.Generator, max_angle_deg: float = 30.0, max_t: float = 1.0) -> np.ndarray:
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(-max_angle_deg, max_angle_deg))
    return cameras.make_pose(cameras.rotation_about(axis, angle), rng.uniform(-max_t, max_t, size=3))


def outlier_problem(seed: int = 0, n: int = 300, outliers: float = 0.6, scale: float = 1.0):
    """``(pts_cam, pts_pc, T)``: ``n`` cloud points seen by a camera at ``T``, the image side divided
    by ``scale`` (a monocular depth that far off), a share ``outliers`` of the partners replaced by
    random points."""
    rng = np.random.default_rng(seed)
    T = cameras.make_pose(cameras.rotation_about([0.2, 1, 0.1], 0.4), [0.3, -0.2, 1.0])
    pts_pc = rng.uniform([-2, -1, 1], [2, 1, 5], size=(n, 3))
    pts_cam = cameras.transform(T, pts_pc) / scale
    bad = rng.random(n) < outliers
    pts_pc[bad] = rng.uniform([-2, -1, 1], [2, 1, 5], size=(int(bad.sum()), 3))
    return pts_cam, pts_pc, T


@pytest.fixture(scope="module")
def torch_one_thread():
    """torch on one thread for a module: the tiny models are overhead-bound, and OpenMP threads
    spin on a busy machine. Use with ``pytestmark = pytest.mark.usefixtures("torch_one_thread")``."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def key_source(name: str, stem: str = "03_fusion") -> str:
    """The answer key's solution cell of notebook ``stem`` that defines the function ``name``."""
    import nbformat

    from freereg_lib.teaching import notebooks as N

    nb = nbformat.read(str(NOTEBOOKS / f"{stem}.ipynb"), as_version=4)
    for cell in nb.cells:
        if N._is_solution(cell) and name in N._defined_functions(cell.source):
            return cell.source
    raise KeyError(name)


def student_notebook(folder, stem: str, *sources: str):
    """A student's ``folder/<stem>.ipynb`` whose solution cells are ``sources``; its path."""
    import nbformat

    nb = nbformat.v4.new_notebook()
    for source in sources:
        cell = nbformat.v4.new_code_cell(source)
        cell.metadata["tags"] = ["solution"]
        nb.cells.append(cell)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{stem}.ipynb"
    nbformat.write(nb, str(path))
    return path


def fusion_key_source(name: str) -> str:
    return key_source(name, "03_fusion")


# A student_fuse that never returns and swallows the grader's time-out (the grader must stop it).
HANGING_FUSE = """
import time
def student_fuse(f_d, f_g, w):
    while True:  # a retry loop that swallows everything, the grader's time-out included
        try:
            time.sleep(0.1)
        except BaseException:
            pass
"""


def fusion_student(folder, *sources: str):
    """A student's ``folder/03_fusion.ipynb`` whose solution cells are ``sources``; its path."""
    return student_notebook(folder, "03_fusion", *sources)


def check_cells(nb):
    """The code cells of ``nb`` tagged as an exercise's check (``teaching.notebooks.CHECK_TAG``)."""
    from freereg_lib.teaching.notebooks import CHECK_TAG

    return [c for c in nb.cells if c.cell_type == "code" and CHECK_TAG in c.metadata.get("tags", [])]


def fill(student, key):
    """The student notebook with the key's solution cells put back (a copy), matched by the
    functions they define, else by their order."""
    import copy

    from freereg_lib.teaching import notebooks as N

    out = copy.deepcopy(student)
    key_cells = [c for c in key.cells if N._is_solution(c)]
    by_names = {tuple(N._defined_functions(c.source)): c.source for c in key_cells}
    for k, cell in enumerate(c for c in out.cells if N._is_solution(c)):
        names = tuple(N._defined_functions(cell.source))
        if names in by_names:
            cell.source = by_names[names]
        elif k < len(key_cells):
            cell.source = key_cells[k].source
    return out
