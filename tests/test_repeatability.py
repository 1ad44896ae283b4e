"""The same seed gives the same bytes: ``pairs.csv`` of two runs in separate processes, on a
synthetic pair and an ICL pair, with the default 50k-iteration solvers (the official Kabsch-RANSAC
samples from a seeded NumPy generator; OpenCV's PnP-RANSAC seeds itself the same way each call).

Kabsch runs on both pairs, PnP on the ICL pair only: each solver and each data source is in the
comparison, and a 50k-iteration PnP call (~1.7 s of CPU, it never stops early on these matches)
on the synthetic pair as well checked the same seeding once more."""
import subprocess
import sys
import textwrap

_RUN = textwrap.dedent("""
    import sys
    from freereg_lib import config_for, pipeline
    from freereg_lib.data import sources
    from freereg_lib.models import get_backend

    scoring, out = sys.argv[1], sys.argv[2]
    rows = []
    # The solvers, their iteration counts and their seeds are the defaults.
    for dataset, variants in (("synthetic_indoor", [("FreeReg", "kabsch")]),
                              ("icl", [("FreeReg-G", "kabsch"), ("FreeReg-G", "pnp")])):
        cfg = config_for(dataset, keypoint_grid=(12, 16), kabsch_scoring=scoring)
        assert cfg.ransac_iters == 50_000 and cfg.kabsch_confidence == 1.0
        pairs = list(sources.iter_pairs(dataset, 1, seed=3))
        rows += pipeline.run_pairs(pairs, get_backend("stub", cfg), cfg, variants, progress=False)
    pipeline.rows_frame(rows).to_csv(out, index=False)
""")


def test_pairs_csv_is_byte_identical_across_processes(tmp_path, monkeypatch, scoring="official"):
    # Two processes: a fresh interpreter, and this worker after whatever tests it ran before (its
    # NumPy, OpenCV and torch state included), which spares a second interpreter's imports.
    outs = [tmp_path / f"pairs{k}.csv" for k in range(2)]
    proc = subprocess.Popen([sys.executable, "-c", _RUN, scoring, str(outs[0])], stderr=subprocess.PIPE, text=True)
    monkeypatch.setattr(sys, "argv", ["-c", scoring, str(outs[1])])
    exec(compile(_RUN, "<repeatability run>", "exec"), {"__name__": "__main__"})
    _, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, err[-2000:]
    first = outs[0].read_bytes()
    assert b"kabsch" in first and b"pnp" in first
    assert all(o.read_bytes() == first for o in outs[1:])
