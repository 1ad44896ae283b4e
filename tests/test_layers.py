"""The library's layers, read from its folders and checked on the import graph.

``freereg_lib`` holds the method in sub-packages that are its layers, lowest first:
``config`` (one module), ``geometry``, ``data``, ``models``, ``features``, ``pipeline``. A module
imports only from its own layer and the layers below it. Beside the method sit the tools, which
the method never imports: ``report`` (the notebooks' figures and parameters), ``commands`` (what a
user runs from a shell), ``training`` (the micro models' training and evaluation) and ``teaching``
(the grader). Every folder of ``freereg_lib`` must be one of these, so a new one is placed
knowingly.

The graph is read from the source with ``ast`` (nothing is imported): every ``import`` and
``from ... import`` of a ``freereg_lib`` module, at module level or inside a function, is an edge.
An import of a module's own parent package is not (Python runs the parents first anyway).
"""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIB = ROOT / "freereg_lib"
MAX_LINES = 600
METHOD = ("config", "geometry", "data", "models", "features", "pipeline")  # lowest first
TOOLS = ("report", "commands", "training", "teaching")
METHOD_MAX_LINES = 10_000
# The synthetic worlds (data/synthetic) stand in for datasets the user does not have: data generators in
# the data layer, not FreeReg's method, so they are held to a budget of their own.
WORLDS_DIR = LIB / "data" / "synthetic"
WORLDS_MAX_LINES = 1_600
# Imports a method module may make inside a function: optional or heavy dependencies that a
# reader of the geometry should not pay for (the real models' libraries, torch, Open3D).
LAZY_OK = {"torch", "torchvision", "diffusers", "transformers", "tokenizers", "safetensors", "huggingface_hub",
           "accelerate", "open3d"}
MAX_LAZY = 60


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, name: str) -> set[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.add(module)
            found |= {f"{module}.{alias.name}" for alias in node.names}
    return found


def import_graph() -> dict[str, set[str]]:
    """``{module: modules of freereg_lib it imports}`` for freereg_lib/ and benchmarks/."""
    files = {_module_name(p): p for top in ("freereg_lib", "benchmarks") for p in (ROOT / top).rglob("*.py")}
    graph = {}
    for name, path in files.items():
        edges = {m for m in _imports(path, name) if m in files and m != name}
        graph[name] = {m for m in edges if not name.startswith(m + ".")}  # a parent package runs first anyway
    return graph


def layer_of(module: str) -> str | None:
    """The first folder (or top-level module) under freereg_lib: its layer or tool."""
    parts = module.split(".")
    return parts[1] if parts[0] == "freereg_lib" and len(parts) > 1 else None


def method_files() -> list[Path]:
    return sorted(p for p in LIB.rglob("*.py") if p.relative_to(LIB).parts[0].removesuffix(".py") in METHOD)


def test_every_folder_is_a_layer_or_a_tool():
    found = {p.name for p in LIB.iterdir() if p.is_dir() and not p.name.startswith("__")}
    modules = {p.stem for p in LIB.glob("*.py")}
    assert found <= set(METHOD) | set(TOOLS), f"place these folders in METHOD or TOOLS: {found - set(METHOD) - set(TOOLS)}"
    assert modules == {"__init__", "__main__", "config"}, f"top-level modules belong in a layer: {modules}"
    for folder in found:
        doc = ast.get_docstring(ast.parse((LIB / folder / "__init__.py").read_text(encoding="utf-8")))
        assert doc and len(doc) > 80, f"freereg_lib/{folder}/__init__.py must say what it is and what it imports"


def test_the_graph_sees_the_known_edges():
    graph = import_graph()
    assert "freereg_lib.models.micro.diffusion" in graph["freereg_lib.models.torch_backends"]
    assert "freereg_lib.models.micro.diffusion" in graph["freereg_lib.training.train_diffusion"]
    assert "freereg_lib.pipeline.steps" in graph["freereg_lib.pipeline.register"]


def _upward(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for m, edges in graph.items():
        src = layer_of(m)
        if src not in METHOD:
            continue
        for i in edges:
            dst = layer_of(i)
            if dst in TOOLS or (dst in METHOD and METHOD.index(dst) > METHOD.index(src)):
                bad.append(f"{m} ({src}) imports {i} ({dst})")
    return sorted(bad)


def test_the_method_imports_only_its_own_layer_and_those_below():
    bad = _upward(import_graph())
    assert bad == [], "an import runs back up a layer (move the shared piece down):\n" + "\n".join(bad)


def test_the_layer_check_catches_an_upward_import():
    graph = {"freereg_lib.geometry.pose": {"freereg_lib.pipeline.steps"},
             "freereg_lib.data.pair": {"freereg_lib.commands.batch"},
             "freereg_lib.pipeline.steps": {"freereg_lib.geometry.pose"}}
    assert len(_upward(graph)) == 2


def test_inside_models_only_the_backends_module_imports_the_micro_models():
    """One direction between the model packages: ``models.micro`` builds on the backends' pieces
    (``base``, ``diffusion``, ``zoedepth``, ``fcgf``, ``weightcheck``); only ``torch_backends``
    (and the package ``__init__`` above it) build backends from the micro models."""
    graph = import_graph()
    top = {"freereg_lib.models", "freereg_lib.models.torch_backends"}
    bad = [f"{m} imports {i}" for m, edges in graph.items() if m.startswith("freereg_lib.models.micro")
           for i in edges if i in top]
    bad += [f"{m} imports {i}" for m, edges in graph.items()
            if m.startswith("freereg_lib.models.") and not m.startswith("freereg_lib.models.micro") and m not in top
            for i in edges if i.startswith("freereg_lib.models.micro") or i in top]
    assert sorted(bad) == [], "\n".join(sorted(bad))


def test_tools_never_import_each_other_across_training_and_teaching():
    graph = import_graph()
    bad = sorted(f"{m} imports {i}" for m, edges in graph.items() for i in edges
                 if {layer_of(m), layer_of(i)} == {"training", "teaching"})
    assert bad == [], "\n".join(bad)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_the_cycle_finder_finds_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle_anywhere():
    circles = _cycles(import_graph())
    assert circles == [], "import circles (move the shared piece down a layer):\n" + "\n".join(
        " <-> ".join(c) for c in circles)


DATASET_LOADERS = ("common", "pairlists", "demo", "icl", "kitti", "scannet", "threedmatch")


def test_the_dataset_loaders_never_import_the_registry():
    graph = import_graph()
    pkg = "freereg_lib.data.datasets"
    loaders = [m for m in graph if m.startswith(pkg + ".") and m.rpartition(".")[2] != "registry"]
    assert {f"{pkg}.{n}" for n in DATASET_LOADERS} <= set(loaders), loaders
    bad = sorted(f"{m} imports {i}" for m in loaders for i in graph[m] if i in (f"{pkg}.registry", pkg))
    assert bad == [], "the registry sits above the loaders it lists:\n" + "\n".join(bad)
    assert graph[f"{pkg}.registry"] >= {f"{pkg}.{n}" for n in ("demo", "kitti", "scannet", "threedmatch")}


def test_no_python_file_over_600_lines():
    over = {}
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in (".venv", ".git", "runs") or "site-packages" in rel.parts:
            continue
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > MAX_LINES:
            over[rel.as_posix()] = n
    assert over == {}, f"split by responsibility, not by size: {over}"


def test_the_method_is_thin():
    lines = sum(len(p.read_text(encoding="utf-8").splitlines()) for p in method_files() if WORLDS_DIR not in p.parents)
    assert lines <= METHOD_MAX_LINES, f"the method's packages hold {lines} lines (at most {METHOD_MAX_LINES})"


def test_the_synthetic_worlds_are_thin():
    lines = sum(len(p.read_text(encoding="utf-8").splitlines()) for p in WORLDS_DIR.rglob("*.py"))
    assert 0 < lines <= WORLDS_MAX_LINES, f"the synthetic worlds hold {lines} lines (at most {WORLDS_MAX_LINES})"


def _lazy_imports(path: Path) -> list[str]:
    """The top-level packages imported inside a function of ``path``."""
    found = []
    for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for n in ast.walk(fn):
                if isinstance(n, ast.Import):
                    found += [a.name.split(".")[0] for a in n.names]
                elif isinstance(n, ast.ImportFrom):
                    found.append("." if n.level else (n.module or "").split(".")[0])
    return found


def test_imports_inside_functions_are_only_for_heavy_optional_dependencies():
    lazy = {p.relative_to(ROOT).as_posix(): _lazy_imports(p) for p in method_files()}
    wrong = {f: sorted(set(m) - LAZY_OK) for f, m in lazy.items() if set(m) - LAZY_OK}
    assert wrong == {}, f"import these at the module's head: {wrong}"
    n = sum(len(m) for m in lazy.values())
    assert n < MAX_LAZY, f"{n} imports inside functions in the method (fewer than {MAX_LAZY})"


# A library module that finds the repository from its own file: climbing out of the package
# (parents[2], parent.parent.parent from a sub-package) or naming the tests or figures folders.
_OUT_OF_PACKAGE = re.compile(r"Path\(__file__\)[^\n]*?((?:\.parent)+)(?!s)|Path\(__file__\)[^\n]*?parents\[(\d+)\]")


def test_the_path_check_catches_a_climb_out_of_the_package():
    assert [m.group(1) for m in _OUT_OF_PACKAGE.finditer('R = Path(__file__).resolve().parent.parent')] == [".parent.parent"]
    assert [m.group(2) for m in _OUT_OF_PACKAGE.finditer('R = Path(__file__).resolve().parents[2] / "x"')] == ["2"]


def test_no_library_module_reads_a_repository_path():
    bad = []
    for path in sorted(LIB.rglob("*.py")):
        depth = len(path.relative_to(LIB).parts) - 1  # folders between the file and freereg_lib/
        text = path.read_text(encoding="utf-8")
        for m in _OUT_OF_PACKAGE.finditer(text):
            ups = m.group(1).count(".parent") if m.group(2) is None else int(m.group(2)) + 1
            if ups > depth + 1:  # depth + 1 steps up from the file is freereg_lib/ itself
                bad.append(f"{path.relative_to(ROOT)}: {m.group(0)}")
        if path.relative_to(LIB).parts[0] in ("commands", "training"):
            continue  # command lines set the defaults, relative to the folder they run in
        for literal in re.findall(r"[\"'](?:tests|figures)/|/ *[\"'](?:tests|figures)[\"']|Path\([\"'](?:tests|figures)", text):
            bad.append(f"{path.relative_to(ROOT)}: names {literal}")
    assert bad == [], "paths are arguments; the commands set their defaults:\n" + "\n".join(bad)


def _python(code: str) -> str:
    """``code`` run by a fresh interpreter (nothing imported before it); its stdout."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_importing_the_pipeline_loads_no_tool():
    code = ("import sys, freereg_lib.pipeline\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'papermill', "
            "'nbconvert', 'nbformat') or m.startswith(('freereg_lib.training', 'freereg_lib.teaching', "
            "'freereg_lib.commands', 'freereg_lib.report')))\n"
            "print('\\n'.join(bad))")
    out = _python(code)
    assert out.strip() == "", f"import freereg_lib.pipeline loaded: {out}"


def test_the_short_names_are_the_layer_modules_loaded_on_first_use():
    code = ("import sys, freereg_lib\n"
            "assert 'freereg_lib.report.plots' not in sys.modules\n"
            "from freereg_lib import cameras, plots, register\n"
            "import freereg_lib.geometry.cameras as c, freereg_lib.report.plots as p, freereg_lib.pipeline.register as r\n"
            "assert (cameras, plots, register) == (c, p, r)\n"
            "import importlib\n"
            "assert all(importlib.import_module(m) for m in freereg_lib.SHORT_NAMES.values())\n"
            "try:\n    freereg_lib.nothing\nexcept AttributeError as e:\n    print(e)\n")
    assert "has no attribute 'nothing'" in _python(code)
    for short, module in __import__("freereg_lib").SHORT_NAMES.items():
        assert module.rsplit(".", 1)[1] == short and layer_of(module) in METHOD + TOOLS, (short, module)
