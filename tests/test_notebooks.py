"""The notebooks as a product: committed clean, parametrised, and runnable with other parameters.

* Every notebook under ``notebooks/`` is committed with outputs stripped, a ``python3``
  kernelspec and a first code cell tagged ``parameters`` that papermill can read.
* Each notebook runs through papermill with non-default parameters (another seed, fewer pairs,
  the tiny backend at 5 DDIM steps for 01, the embedded ICL sample for 02 and 04, a demo-layout pair for 04) into a temporary
  ``out_dir`` / ``figures_dir``; the tables it writes (CSV) and figures (PNG) must be there,
  and the metric columns of the tables must hold finite numbers; no Markdown cell of the
  executed copy states a number or a claim its outputs contradict (:mod:`freereg_lib.report.prose`), in
  notebook 00's a number and a glue name planted into its Markdown are flagged, the contradicted sentences
  of tests/test_prose.py's ``PLANTED`` are read against the run's ``check:`` lines, and every exercise
  (the answer key's solution cells) passes its check cell, unskipped.
* ``python -m freereg_lib reproduce --quick`` prints a Markdown table of FMR / IR / IN / RR.

The default-parameter runs are ``pytest --nbmake notebooks/`` (see the Makefile).
"""
from __future__ import annotations

import copy
import math
import re
import runpy
import sys
from pathlib import Path

import pandas as pd
import pytest

nbformat = pytest.importorskip("nbformat")
papermill = pytest.importorskip("papermill")

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
EXPECTED = [
    "00_preliminaries.ipynb",
    "01_diffusion_features.ipynb",
    "02_geometric_features.ipynb",
    "03_fusion.ipynb",
    "04_benchmark.ipynb",
    "05_your_data.ipynb",
    "06_appendix.ipynb",
    "07_paper_figures.ipynb",
]
ALL = sorted(set(EXPECTED) | {p.name for p in NOTEBOOKS.glob("*.ipynb")})
# Every notebook's parameters cell declares these (the conventions of notebooks/).
COMMON_PARAMS = ("backend", "dataset", "n_pairs", "seed", "device", "out_dir", "figures_dir")
METRIC_COLUMNS = ("FMR", "IR", "IN", "RR")

# Non-default runs: another seed and fewer pairs everywhere, the tiny backend at 5 DDIM steps for 01,
# the stub instead of the default micro backend for 02, 03 and 04 (nbmake runs their defaults), the
# embedded ICL frames for 02 and 04. ``knobs`` only shorten a run and are passed only when
# the notebook declares them; ``params`` must all be declared.
RUNS = {
    "00_preliminaries": dict(params={"seed": 3, "n_pairs": 1}, knobs={"corrupt_fraction": 0.5}),
    "01_diffusion_features": dict(
        params={"backend": "tiny", "seed": 1, "n_pairs": 1, "config_overrides": {"ddim_steps": 5}},
        knobs={"t_hats": [150, 50], "ransac_iters": 2000},
    ),
    "02_geometric_features": dict(
        params={"backend": "stub", "dataset": "icl", "seed": 1, "n_pairs": 1},
        knobs={"mono_errors": [0.0, 0.27], "sweep_ransac_iters": 2000},
    ),
    "03_fusion": dict(
        params={"backend": "stub", "seed": 1, "n_pairs": 1},
        knobs={"weights": [1.0, 0.5, 0.0], "ransac_iters": 5000},
    ),
    # Two pairs in one batch and the USAC PnP, through config_overrides.
    "04_benchmark": dict(params={"backend": "stub", "dataset": "icl", "seed": 1, "n_pairs": 2,
                                 "config_overrides": {"pair_batch": 2, "pnp_method": "usac"}},
                         knobs={"ransac_iters": 5000}),
    # The outdoor scenes, compared with KITTI-DC, through the feature cache (the default micro
    # backend falls back to the stub outdoors).
    "04_benchmark-outdoor-cached": dict(
        params={"dataset": "synthetic_outdoor", "seed": 2, "n_pairs": 1, "cache_dir": "<tmp>/cache"},
        knobs={"ransac_iters": 5000, "n_failure_cases": 1},
    ),
    # The official demo's layout (written by the test: a rendered room, its own cameras), as
    # dataset="demo": config_for("demo") and the loader through the notebook.
    "04_benchmark-demo": dict(
        params={"backend": "stub", "dataset": "demo", "data_root": "<tmp>/demo", "seed": 1, "n_pairs": 1},
        knobs={"ransac_iters": 5000, "n_failure_cases": 1}, setup="demo",
    ),
    # One's own data: the ICL pair written as the demo layout and as loose files, smaller.
    "05_your_data": dict(params={"seed": 1, "n_pairs": 1},
                         knobs={"ransac_iters": 3000, "n_views": 2, "scale": 0.25}),
    # The appendix with the stub (no DDIM there: its rows do not move with the iterations).
    "06_appendix": dict(params={"backend": "stub", "seed": 1, "n_pairs": 1},
                        knobs={"ddim_steps_list": [5, 20], "ransac_iters": 2000}),
    # The paper's pictures with the stub: a synthetic pair for sections 1-3, one ICL pair (FreeReg-G).
    "07_paper_figures": dict(params={"backend": "stub", "n_pairs": 1}, knobs={"ransac_iters": 2000}),
}


def _path(name: str) -> Path:
    path = NOTEBOOKS / name
    if not path.is_file():
        pytest.skip(f"{path.relative_to(ROOT)} is not written yet")
    return path


# --------------------------------------------------------------------------------------
# Committed state.

@pytest.mark.parametrize("name", ALL)
def test_notebook_is_committed_clean_with_a_parameters_cell_first(name):
    path = _path(name)
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert nb.metadata.get("kernelspec", {}).get("name") == "python3", f"{name}: kernelspec must be python3"
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code, f"{name} has no code cell"
    assert "parameters" in code[0].metadata.get("tags", []), f"{name}: the first code cell must be tagged `parameters`"
    tagged = [k for k, c in enumerate(code) if "parameters" in c.metadata.get("tags", [])]
    assert tagged == [0], f"{name}: exactly one `parameters` cell, the first code cell (found at code cells {tagged})"
    dirty = [k for k, c in enumerate(code) if c.get("outputs") or c.get("execution_count") is not None]
    assert not dirty, f"{name}: code cells {dirty} carry outputs or execution counts; strip them before committing"
    # papermill must read every line of the cell (a line it cannot parse is silently not a parameter).
    declared = set(papermill.inspect_notebook(str(path)))
    assignments = {re.split(r"[:=]", line)[0].strip() for line in code[0].source.splitlines()
                   if "=" in line.split("#")[0] and not line.startswith((" ", "\t", "#"))}
    assert assignments <= declared, f"{name}: papermill cannot parse parameter(s) {sorted(assignments - declared)}"
    missing = [p for p in COMMON_PARAMS if p not in declared]
    assert not missing, f"{name}: the parameters cell lacks {missing}"


def test_benchmark_declares_the_batch_runner_parameters():
    declared = set(papermill.inspect_notebook(str(_path("04_benchmark.ipynb"))))
    assert {"backend", "dataset", "data_root", "n_pairs", "seed", "device", "out_dir", "figures_dir",
            "shard", "cache_dir"} <= declared


# --------------------------------------------------------------------------------------
# Papermill runs with non-default parameters.

def _finite_metric_problems(csv: Path) -> tuple[list[str], int]:
    """Problems with the FMR / IR / IN / RR columns of one CSV, and its number of fully finite rows.

    A row of a side-by-side table that only the paper has (all our metrics empty) is allowed;
    a row we computed must have every one of our metric columns finite.
    """
    table = pd.read_csv(csv)
    cols = [c for c in METRIC_COLUMNS if c in table.columns]
    if not cols or table.empty:
        return [], 0
    values = table[cols].apply(pd.to_numeric, errors="coerce")
    ours = values.notna().any(axis=1)
    finite = values.apply(lambda col: col.map(lambda v: math.isfinite(v) if pd.notna(v) else False))
    bad = ours & ~finite.all(axis=1)
    problems = [f"{csv.name} row {i}: {values.loc[i].to_dict()}" for i in table.index[bad]]
    return problems, int((ours & finite.all(axis=1)).sum())


@pytest.mark.parametrize("run", list(RUNS))
def test_notebook_runs_with_other_parameters(run, tmp_path):
    stem = run.split("-")[0]
    path = _path(f"{stem}.ipynb")
    spec = RUNS[run]
    declared = set(papermill.inspect_notebook(str(path)))
    params = {k: (v.replace("<tmp>", str(tmp_path)) if isinstance(v, str) else v) for k, v in spec["params"].items()}
    undeclared = sorted(set(params) - declared)
    assert not undeclared, f"{stem} does not declare {undeclared}; it declares {sorted(declared)}"
    params.update({k: v for k, v in spec["knobs"].items() if k in declared})
    out_dir, figures_dir = tmp_path / "out", tmp_path / "figures"
    params.update(out_dir=str(out_dir), figures_dir=str(figures_dir))
    if spec.get("setup") == "demo":
        from test_loaders import make_demo

        make_demo(tmp_path / "demo", rgb_size=(120, 160), dpt_size=(60, 80))

    executed = tmp_path / f"{stem}.executed.ipynb"
    papermill.execute_notebook(
        str(path), str(executed), parameters=params,
        kernel_name="python3", cwd=str(NOTEBOOKS), progress_bar=False, shutdown_kernel="immediate",
    )
    executed_nb = nbformat.read(executed, as_version=4)
    _check_prose(executed_nb, stem)
    _check_exercises(executed_nb)

    tables = sorted(out_dir.glob("*.csv"))
    assert tables, f"{stem} wrote no CSV table into out_dir"
    problems, finite_rows = [], 0
    for csv in tables:
        p, n = _finite_metric_problems(csv)
        problems += p
        finite_rows += n
    assert not problems, f"{stem}: non-finite metrics:\n" + "\n".join(problems)
    if stem != "00_preliminaries":  # 00 re-runs no benchmark table; the others do
        assert finite_rows > 0, f"{stem}: no table row with finite {METRIC_COLUMNS} in {[t.name for t in tables]}"

    figures = sorted(figures_dir.glob("*.png"))
    assert figures, f"{stem} wrote no figure into figures_dir"
    for fig in figures:
        assert fig.name.startswith(stem[:3]), f"{fig.name}: figure names start with the notebook's number"
        data = fig.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000, f"{fig.name} is not a drawn PNG"

    if stem == "04_benchmark":
        _check_benchmark_outputs(out_dir, params)


def _check_prose(nb, stem: str) -> None:
    """The executed copy's prose agrees with its outputs; in notebook 00 planted faults are caught."""
    from freereg_lib.report.prose import check_notebook, glue_references, glued_names

    problems = check_notebook(nb, stem)
    assert problems == [], "\n".join(map(str, problems))
    referenced = {n for c in nb["cells"] if c["cell_type"] == "markdown" for n in glue_references(c["source"])}
    assert referenced <= glued_names(nb), f"{stem}: referenced but not glued: {referenced - glued_names(nb)}"
    from test_prose import assert_planted_contradictions_flagged

    assert_planted_contradictions_flagged(nb, stem)  # the quoted contradictions, against this run's checks
    if stem != "00_preliminaries":
        return
    assert referenced
    planted = copy.deepcopy(nb)
    md = {c.get("id"): c for c in planted["cells"] if c["cell_type"] == "markdown"}
    md["c36"]["source"] += "\nWith half the matches corrupted, IR is 0.62 on this pair."
    md["c33"]["source"] += "\nThe feature pass runs at {glue:text}`t_feature`."
    found = [(p.cell_id, p.kind, p.found) for p in check_notebook(planted, stem)]
    assert found == [("c33", "glue", "t_feature"), ("c36", "number", "0.62")], found


def _check_exercises(nb) -> None:
    """Each exercise's check cell (tagged ``check``) ran the answer key's solution and passed: an
    unsolved or failing exercise would print "EXERCISE NOT DONE" or stop the run."""
    from conftest import check_cells

    for cell in check_cells(nb):
        printed = "".join(o.get("text", "") for o in cell.outputs)
        assert cell.execution_count is not None and "EXERCISE NOT DONE" not in printed, (cell.source[:200], printed)


def _check_benchmark_outputs(out_dir: Path, params: dict) -> None:
    from freereg_lib.commands import batch

    rows = batch.read_rows(out_dir)
    assert rows and len({r["pair"] for r in rows}) == params["n_pairs"]
    results = pd.read_csv(out_dir / "results.csv")
    base = results[results["method"] == "Position-only"]  # the baseline row, with each solver of the run
    assert set(base["solver"]) == set(results["solver"]), results
    if params["dataset"] in ("icl", "demo"):  # the stub has no diffusion features for real frames: FreeReg-G only
        assert set(results["method"]) == {"FreeReg-G", "Position-only"}
        assert set(results["solver"]) == {"kabsch", "pnp"}
    else:
        assert set(results["method"]) == {"FreeReg-D", "FreeReg-G", "FreeReg", "Position-only"}
    side = pd.read_csv(out_dir / "table1_side_by_side.csv")
    assert set(side["paper_dataset"]) == {"Kitti-DC" if "outdoor" in params["dataset"] else "3DMatch"}
    md = (out_dir / "table1_side_by_side.md").read_text()
    assert "| method" in md and "RR_paper" in md and "stub" in md
    ladder = pd.read_csv(out_dir / "table9_rr_ladder.csv")
    assert [c for c in ladder.columns if c.startswith("RR@") and not c.endswith("_paper")], "no RR ladder columns"
    for name in ("failed_pairs.csv", "recorded_errors.csv", "config.json"):
        assert (out_dir / name).is_file(), name
    if params.get("cache_dir"):
        assert any(Path(params["cache_dir"]).rglob("*.npz")), "the feature cache stayed empty"


# --------------------------------------------------------------------------------------
# make reproduce, quick form.

def test_reproduce_quick_prints_a_metric_table(monkeypatch, capsys):
    # The command as `python -m` runs it (runpy: its __main__ block, argv, exit status), in this
    # process: a second interpreter spent ~3 s of CPU on the imports this worker already holds.
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(sys, "argv", ["reproduce", "--quick", "--pairs", "1"])
    with pytest.raises(SystemExit) as end:
        runpy.run_module("freereg_lib.commands.reproduce", run_name="__main__", alter_sys=True)
    assert end.value.code == 0
    stdout = capsys.readouterr().out
    lines = stdout.splitlines()
    header = [ln for ln in lines if ln.startswith("|") and all(f" {m} " in ln for m in METRIC_COLUMNS)]
    assert header, f"no Markdown header with {METRIC_COLUMNS} in:\n{stdout[-3000:]}"
    at = lines.index(header[0])
    assert set(lines[at + 1].replace("|", "").strip()) <= set(":- "), "the header is not followed by a Markdown rule"
    body = [ln for ln in lines[at + 2:] if ln.startswith("|")]
    assert body, "the table has no rows"
    assert "stub" in stdout, "the printed table must name its backend"
