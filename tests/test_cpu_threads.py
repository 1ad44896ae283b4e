"""``cpu_threads``: the model calls run on the configured torch thread count, whatever the
caller's, and restore the caller's after; at one thread the maps do not depend on it."""
import numpy as np
import pytest
import torch

from freereg_lib import pipeline
from freereg_lib.config import config_for
from freereg_lib.data import synthetic
from freereg_lib.models import get_backend
from freereg_lib.models.base import cpu_threads


@pytest.fixture
def caller_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_cpu_threads_sets_and_restores(caller_threads):
    torch.set_num_threads(2)
    with cpu_threads("cpu", 1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with cpu_threads("cpu", 0):  # torch's own count: untouched
        assert torch.get_num_threads() == 2
    with cpu_threads(torch.device("cuda"), 1):  # another device: untouched (no CUDA needed)
        assert torch.get_num_threads() == 2


def test_model_calls_run_on_the_configured_threads(caller_threads):
    seen = []
    backend = get_backend("micro", config_for("3dmatch", cpu_threads=1))
    backend._zoe = type("Spy", (), {"batch": lambda self, ims: seen.append(torch.get_num_threads()) or []})()
    torch.set_num_threads(2)
    backend.mono_depth_batch([np.zeros((8, 8, 3), np.uint8)])
    assert seen == [1] and torch.get_num_threads() == 2


def test_maps_do_not_depend_on_the_callers_thread_count(caller_threads):
    assert config_for("3dmatch").cpu_threads == 1
    # 4 DDIM steps, not 20: every step's kernels run at the caller's count as at 20, at a fifth
    # of the CPU; a thread-dependent sum would show after one step.
    cfg = config_for("3dmatch", ddim_steps=4)
    assert cfg.cpu_threads == 1
    backend = get_backend("micro", cfg)
    pair = synthetic.make_pair(seed=3)
    view = pipeline.depth_view(pair, cfg)
    outs = []
    for caller in (2, 1):
        torch.set_num_threads(caller)
        outs.append(pipeline.diffusion_maps_batch([pair], [view], backend, cfg.layers)[0])
    for a, b in zip(*outs):
        for layer in a:
            assert np.array_equal(a[layer], b[layer])
