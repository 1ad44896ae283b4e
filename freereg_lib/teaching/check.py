"""The notebooks' check cells (:class:`exercise_check`) and the one rule a solution must keep.

The rule: a solution is graded on its own, in a process with NumPy and the standard library
only (:mod:`.student`), so its cell may not use ``freereg_lib`` (:func:`library_use`) nor the
notebook's variables. The check cells say so in the notebook, before the grader does. This
module goes into the students' handout; it imports only the standard library.
"""
from __future__ import annotations

import ast
import builtins
import dis
import linecache
import sys
from types import CodeType
from typing import Any

LIBRARY = "freereg_lib"
GRADED_WITH = "solutions are graded with NumPy and the standard library only (freereg_lib is not there)"


def library_use(source: str) -> str | None:
    """Where ``source`` imports or names ``freereg_lib`` (``"line 3: import freereg_lib.features"``); else None."""
    try:
        tree = ast.parse(source)
    except SyntaxError:
        return None
    prose = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}  # docstrings may name it
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and LIBRARY in node.value \
                and id(node) not in prose:
            return f"line {node.lineno} names {LIBRARY} ({node.value[:60]!r})"
        hit = next((n for n in names if n.split(".")[0] == LIBRARY), None)
        if hit:
            return f"line {node.lineno} imports {hit}"
    return None


def _globals_used(code: CodeType) -> set[str]:
    names = {i.argval for i in dis.get_instructions(code) if i.opname in ("LOAD_GLOBAL", "LOAD_NAME")}
    for const in code.co_consts:
        if isinstance(const, CodeType):
            names |= _globals_used(const)
    return names


def _cell_names(source: str) -> set[str]:
    """The names a cell binds at its top level (functions, classes, assignments, imports)."""
    bound: set[str] = set()
    for node in ast.parse(source).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            bound |= {(a.asname or a.name).split(".")[0] for a in node.names}
        else:
            bound |= {n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    return bound


def graded_alone(function: Any, env: dict) -> str | None:
    """Why ``function`` (defined in a notebook whose globals are ``env``) would fail when graded
    alone, or None: its cell uses freereg_lib, or it reads a name of the notebook."""
    code = getattr(function, "__code__", None)
    if code is None:
        return None
    source = "".join(linecache.getlines(code.co_filename))  # the cell, where IPython keeps it
    use = library_use(source) if source else None
    if use:
        return f"its cell uses {LIBRARY} ({use}): {GRADED_WITH}"
    try:
        own = _cell_names(source) if source else None
    except SyntaxError:
        own = None
    for name in sorted(_globals_used(code)):
        if name == "np" or hasattr(builtins, name) or name not in env or (own is not None and name in own):
            continue
        origin = getattr(env[name], "__module__", None) or getattr(env[name], "__name__", "")
        if str(origin).startswith(LIBRARY):
            return f"uses {name} from {LIBRARY}: {GRADED_WITH}"
        if own is not None:
            return (f"uses the notebook's {name}: when graded, only its solution cell runs (with numpy as np), "
                    "so define or import what it needs there")
    return None


class exercise_check:  # noqa: N801 - used as a statement: ``with exercise_check("student_fuse"):``
    """The body of a ``check`` cell: an unsolved exercise reports itself instead of stopping Run All.

    ``with exercise_check("student_fuse"): <the checks>`` first makes sure the function can be
    graded on its own (:func:`graded_alone`; if not, an ``AssertionError`` says why), then runs
    the checks. When one of the named functions is still the student version's stub (it raises
    ``NotImplementedError`` naming itself), the rest of the block is skipped and one line says
    so, and the notebook goes on with the library's reference (no later cell calls the
    student's function). A wrong answer or any other error still stops the notebook.
    """

    def __init__(self, *functions: str) -> None:
        if not functions or not all(isinstance(f, str) and f.startswith("student_") for f in functions):
            raise ValueError(f"exercise_check: unknown exercise(s) {functions}; the names start with student_")
        self.functions = functions
        self.skipped: str | None = None  # the exercise whose stub stopped the check, if any
        self._env = sys._getframe(1).f_globals

    def __enter__(self) -> "exercise_check":
        for name in self.functions:
            problem = graded_alone(self._env.get(name), self._env)
            if problem:
                raise AssertionError(f"{name} {problem}")
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None or not issubclass(exc_type, NotImplementedError):
            return False
        name = next((f for f in self.functions if f in str(exc)), None)
        if name is None:
            return False
        self.skipped = name
        print(f"EXERCISE NOT DONE: {name} still raises NotImplementedError, so this check is skipped. "
              f"The rest of the notebook does not use {name}: it runs on the library's reference.\n  {exc}")
        return True
