"""Notebook parameters: typed for ``papermill --help-notebook``, checked in the
first code cell with one line naming the parameter.

* Every parameter of every notebook has a type papermill reads, and its default conforms to it.
* ``check_parameters`` refuses a list given as a string, an unknown backend, a misspelt injected
  name (with a suggestion) and a bool where a number is due; accepts ints for floats and None
  for Optional.
* Under papermill, a wrong-typed and a misspelt parameter stop the notebook in its first code
  cell after the parameters, naming the parameter (one kernel each, on the cheapest notebook).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from freereg_lib.report import params as P

nbformat = pytest.importorskip("nbformat")
papermill = pytest.importorskip("papermill")

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
BOOKS = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))


def _parameters_cell(path: Path):
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    return code[0], code[1]


@pytest.mark.parametrize("path", BOOKS, ids=lambda p: p.stem)
def test_every_parameter_has_a_type_papermill_shows_and_its_default_conforms(path):
    inferred = papermill.inspect_notebook(str(path))
    untyped = [n for n, p in inferred.items() if p["inferred_type_name"] in ("None", "", None)]
    assert not untyped, f"{path.name}: parameters without a type annotation: {untyped}"
    cell, first = _parameters_cell(path)
    namespace: dict = {}
    exec(cell.source, namespace)  # the annotations must not need an import (quoted where they would)
    spec = namespace["__annotations__"]
    assert set(spec) == set(inferred), f"{path.name}: papermill reads {sorted(inferred)}, the kernel {sorted(spec)}"
    for name, tp in spec.items():
        assert P.describe(P.parse_type(tp)) == inferred[name]["inferred_type_name"].strip("\"'"), name
    assert P.check_parameters(namespace, injected=[]).keys() == spec.keys()
    # The first code cell after the parameters checks them before anything else runs.
    body = [n for n in ast.parse(first.source).body if not isinstance(n, (ast.Import, ast.ImportFrom))]
    assert "quiet_kernel()" in ast.unparse(body[0]) and "check_parameters(globals())" in ast.unparse(body[1]), \
        f"{path.name}: the first code cell must set the kernel up and check the parameters first"


def _papermill(*args: str):
    """``papermill ARGS`` run in this process (its command line, without a second interpreter
    importing papermill again): the exit status and what it printed or raised."""
    import logging

    from click.testing import CliRunner
    from papermill.cli import papermill as command

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        result = CliRunner().invoke(command, list(args), catch_exceptions=True)
    finally:  # the command's logging.basicConfig, bound to the runner's stream, is undone
        root.handlers[:], root.level = handlers, level
    return result.exit_code, result.output + ("" if result.exception is None else repr(result.exception))


def test_help_notebook_prints_a_type_for_every_parameter():
    rc, stdout = _papermill("--help-notebook", str(NOTEBOOKS / "04_benchmark.ipynb"))
    assert rc == 0, stdout
    listed = [ln.split(":")[0].strip() for ln in stdout.splitlines() if "(default " in ln]
    assert len(listed) >= 15 and "variants" in listed
    assert "variants: list[list[str]] (default" in stdout and "n_pairs: Optional[int] (default 6)" in stdout
    assert "(None)" not in stdout and "unknown type" not in stdout


SPEC = {"backend": "str", "layers": "list[int]", "w": "float", "device": "Optional[str]",
        "variants": "list[list[str]]", "overrides": "dict", "n_pairs": "Optional[int]"}
GOOD = {"backend": "micro", "layers": [0, 4, 6], "w": 0.5, "device": None,
        "variants": [["FreeReg", "pnp"]], "overrides": {}, "n_pairs": 3}


def test_check_parameters_accepts_good_values():
    assert P.check_parameters(GOOD, SPEC, injected=["layers", "w"]) == GOOD
    assert P.check_parameters({**GOOD, "w": 1, "n_pairs": None, "device": "cuda:0", "backend": "STUB"},
                              SPEC, injected=[])["w"] == 1


@pytest.mark.parametrize("change, words", [
    ({"layers": "[0, 4, 6]"}, ["'layers'", "list[int]", "the string '[0, 4, 6]'", "-y \"layers: [0, 4, 6]\""]),
    ({"layers": [0, "4"]}, ["'layers'", "list[int]"]),
    ({"backend": "stbu"}, ["'backend'", "'stbu'", "micro"]),
    ({"w": True}, ["'w'", "float"]),
    ({"n_pairs": 2.5}, ["'n_pairs'", "Optional[int]"]),
    ({"variants": [["FreeReg", 1]]}, ["'variants'", "list[list[str]]"]),
    ({"overrides": "pair_batch=4"}, ["'overrides'", "dict", "-y \"overrides: {...}\""]),
])
def test_check_parameters_names_the_bad_one(change, words):
    with pytest.raises(P.ParameterError) as info:
        P.check_parameters({**GOOD, **change}, SPEC, injected=list(change))
    message = str(info.value)
    assert "\n" not in message
    for w in words:
        assert w in message, message
    assert info.value._render_traceback_() == [f"ParameterError: {message}"]  # IPython prints one line


def test_a_misspelt_injected_name_is_refused_with_a_suggestion():
    with pytest.raises(P.ParameterError, match=r"unknown parameter 'n_pair'.*did you mean 'n_pairs'"):
        P.check_parameters({**GOOD, "n_pair": 2}, SPEC, injected=["backend", "n_pair"])
    history = ["", "backend: str = 'x'", "# Parameters\nn_pair = 2\nlayers = [0]\n", "check_parameters(globals())"]
    assert P.injected_names(history) == ["n_pair", "layers"]
    assert P.injected_names(["x = 1", "# not papermill\ny = 2"]) == []


def _run(stem: str, tmp_path: Path, *args: str) -> tuple[int, str, Path]:
    out = tmp_path / f"{stem}.out.ipynb"
    rc, log = _papermill(str(NOTEBOOKS / f"{stem}.ipynb"), str(out), "-k", "python3", "--cwd", str(NOTEBOOKS),
                         "--no-progress-bar", "-p", "out_dir", str(tmp_path / "o"), "-p", "figures_dir",
                         str(tmp_path / "f"), *args)
    return rc, log, out


@pytest.mark.parametrize("args, words", [
    (("-p", "noise_steps", "[0,50]"), ["'noise_steps'", "list[int]", "-y"]),
    (("-p", "n_pair", "2"), ["unknown parameter 'n_pair'", "did you mean 'n_pairs'"]),
])
def test_papermill_stops_in_the_first_code_cell_naming_the_parameter(tmp_path, args, words):
    rc, log, out = _run("00_preliminaries", tmp_path, *args)
    assert rc != 0 and "ParameterError" in log, log[-2000:]
    nb = nbformat.read(out, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code" and "injected-parameters" not in c.metadata.get("tags", [])]
    errors = [k for k, c in enumerate(code) if any(o.output_type == "error" for o in c.outputs)]
    assert errors == [1], f"the error must be in the first code cell after the parameters, found in {errors}"
    error = next(o for o in code[1].outputs if o.output_type == "error")
    assert error.ename == "ParameterError"
    for w in words:
        assert w in error.evalue, error.evalue
    assert all(c.execution_count is None for c in code[2:]), "cells after the check ran"
