"""The library's reference functions as the student's process sees them: deliberately wrong.

How the grader tells a solution that computes the exercise from one that calls the
library's reference (``features.fuse`` for ``student_fuse``, ...), without running or
tracing anything in the student's process: there, every reference function of every
exercise returns a **secretly altered** answer. The alteration is keyed by a secret the grader
draws for each grading run and by the value itself (:func:`perturb`), so it is deterministic
(the grader reproduces it) but cannot be calibrated away on a known input. The grader then
compares each answer with the true reference (computed in its own, untouched process) and
with what a call of the altered reference gives (:func:`altered`, in the grader): an answer
that is the altered one and not the true one comes from the reference: the exercise is
``refused`` and scores 0. Wherever the call happens (a thread, after ``sys.setprofile(None)``,
through an alias, ``importlib.reload`` or a fresh import) it gets the altered answer, because
the alteration is compiled into the module's own code when it loads (:func:`install`), not
patched over it. What this does not catch: a solution that copies the library's code, or
loads its files by path. That is copying, as from a classmate; compare submissions for it.
"""
from __future__ import annotations

import ast
import contextlib
import dataclasses
import hashlib
import importlib
import importlib.abc
import importlib.machinery
import sys
from typing import Any, Callable, Iterable

import numpy as np

HOOK = "__freereg_graded_reference__"


def _seed(secret: str, x: Any) -> int:
    h = hashlib.blake2b(secret.encode(), digest_size=8)
    if isinstance(x, np.ndarray):
        h.update(str((x.dtype.str, x.shape)).encode())
        h.update(np.ascontiguousarray(x).tobytes())
    else:
        h.update(repr(x).encode())
    return int.from_bytes(h.digest(), "little")


def perturb(x: Any, secret: str) -> Any:
    """``x`` altered beyond every grading tolerance, deterministically from ``secret`` and ``x``.

    Floats move by 1-3 % of their size plus 0.01-0.03 (zeros too, NaN stays NaN), integers
    grow by 1-3, bools are flipped (arrays: a random half, at least one), containers and
    dataclasses (``pose.PoseResult``) are altered item by item; strings and ``None`` stay.
    """
    if isinstance(x, (bool, np.bool_)):
        return not x
    if isinstance(x, (int, np.integer)):
        return type(x)(x + 1 + _seed(secret, x) % 3)
    if isinstance(x, (float, np.floating)):
        r = np.random.default_rng(_seed(secret, x))
        return type(x)(x * (1 + r.uniform(0.01, 0.03)) + r.choice([-1, 1]) * r.uniform(0.01, 0.03))
    if isinstance(x, np.ndarray):
        r = np.random.default_rng(_seed(secret, x))
        if x.dtype.kind == "b":
            flip = r.random(x.shape) < 0.5
            if x.size and not flip.any():
                flip.flat[0] = True
            return x ^ flip
        if x.dtype.kind in "iu":
            return (x + r.integers(1, 4, x.shape)).astype(x.dtype)
        if x.dtype.kind == "f":
            sign = r.choice([-1.0, 1.0], x.shape)
            return (x * (1 + r.uniform(0.01, 0.03, x.shape)) + sign * r.uniform(0.01, 0.03, x.shape)).astype(x.dtype)
        return x
    if isinstance(x, (tuple, list)):
        return type(x)(perturb(v, secret) for v in x)
    if isinstance(x, dict):
        return {k: perturb(v, secret) for k, v in x.items()}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return dataclasses.replace(x, **{f.name: perturb(getattr(x, f.name), secret)
                                         for f in dataclasses.fields(x) if f.init})
    return x


# --------------------------------------------------------------------------------------
# The student's side: the reference modules compiled with their answers altered.

class _Returns(ast.NodeTransformer):
    """``return X`` -> ``return __freereg_graded_reference__(X)`` in one function (not nested ones)."""

    def visit_FunctionDef(self, node):  # nested functions keep their returns
        return node

    visit_AsyncFunctionDef = visit_Lambda = visit_ClassDef = visit_FunctionDef

    def visit_Return(self, node):
        value = node.value or ast.Constant(None)
        call = ast.Call(ast.Name(HOOK, ast.Load()), [value], [])
        return ast.copy_location(ast.Return(call), node)


def rewrite(source: str, names: Iterable[str]) -> ast.Module:
    """The module's syntax tree with the answers of its top-level functions ``names`` altered."""
    tree = ast.parse(source)
    names = set(names)
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name in names:
            node.body = [_Returns().visit(stmt) for stmt in node.body]
    return ast.fix_missing_locations(tree)


class _Loader(importlib.machinery.SourceFileLoader):
    def __init__(self, fullname: str, path: str, names: set[str], hook: Callable[[Any], Any]):
        super().__init__(fullname, path)
        self.names, self.hook = names, hook

    def get_code(self, fullname):  # never the cached bytecode: always the altered source
        source = self.get_data(self.path).decode("utf-8")
        return compile(rewrite(source, self.names), self.path, "exec", dont_inherit=True)

    def exec_module(self, module):
        module.__dict__[HOOK] = self.hook
        super().exec_module(module)


class _Finder(importlib.abc.MetaPathFinder):
    def __init__(self, targets: dict[str, set[str]], hook: Callable[[Any], Any]):
        self.targets, self.hook = targets, hook

    def find_spec(self, fullname, path, target=None):
        if fullname not in self.targets:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if spec.origin and spec.origin.endswith(".py"):
                    spec.loader = _Loader(fullname, spec.origin, self.targets[fullname], self.hook)
                return spec
        return None


def install(refs: Iterable[str], secret: str) -> None:
    """In the student's process, before any student code: every reference ``"module.function"``
    of ``freereg_lib`` answers altered from here on, however it is reached."""
    targets: dict[str, set[str]] = {}
    for dotted in refs:
        module, name = dotted.rsplit(".", 1)
        targets.setdefault(f"freereg_lib.{module}", set()).add(name)
    sys.meta_path.insert(0, _Finder(targets, lambda value: perturb(value, secret)))
    for name in targets:
        if name in sys.modules:  # loaded before (by the runner itself): load it again, altered
            importlib.reload(sys.modules[name])
    for name in targets:  # then the packages that re-export its names (``features.fuse``)
        package = name.rpartition(".")[0]
        if package in sys.modules and package != "freereg_lib":
            importlib.reload(sys.modules[package])


# --------------------------------------------------------------------------------------
# The grader's side: what a call of the altered reference answers.

@contextlib.contextmanager
def altered(refs: Iterable[str], secret: str):
    """In the grader (no student code there): the references answer altered while inside, as
    they do in the student's process (library functions that call them go through them too)."""
    saved = []
    try:
        for dotted in refs:
            module, name = dotted.rsplit(".", 1)
            mod = importlib.import_module(f"freereg_lib.{module}")
            original = getattr(mod, name)
            saved.append((mod, name, original))

            def wrapper(*args, _f=original, **kwargs):
                return perturb(_f(*args, **kwargs), secret)

            setattr(mod, name, wrapper)
            package = sys.modules.get(mod.__name__.rpartition(".")[0])
            if package is not None and getattr(package, name, None) is original:  # a re-export
                saved.append((package, name, original))
                setattr(package, name, wrapper)
        yield
    finally:
        for mod, name, original in reversed(saved):
            setattr(mod, name, original)
