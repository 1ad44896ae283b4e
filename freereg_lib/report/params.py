"""The notebooks' papermill parameters: their declared types, and one check of what a run was given.

Each notebook's ``parameters`` cell declares every parameter with a type annotation papermill
reads (``papermill --help-notebook`` prints it), e.g. ::

    backend: str = "micro"              # "micro" | "stub" | "tiny" | "real"
    layers: list[int] = [0, 4, 6]       # FreeReg's decoder layers
    device: "Optional[str]" = None      # quoted: papermill's parser takes no "|", and the kernel
                                        # does not evaluate a quoted annotation

The notebook's first code cell calls :func:`check_parameters` on its own globals. It stops the
run there, with one line naming the parameter, when

* a value does not have its declared type (a list of layers given with ``-p`` arrives as the
  string ``"[0, 4, 6]"``; lists and dicts go with ``-y``);
* a value is not one of the known choices (an unknown backend, dataset, solver, ...);
* papermill injected a name the notebook does not declare (a misspelt parameter: papermill
  itself only warns "Passed unknown parameter" and runs on with the default);
* a value that sets a :class:`~freereg_lib.config.FreeRegConfig` field (same name, a name of
  :data:`CONFIG_ALIASES`, or a key of ``config_overrides``) lies outside the range the field
  declares (:func:`freereg_lib.config.range_problem`, the check ``FreeRegConfig`` runs itself).

The same cell calls :func:`quiet_kernel` first, so the executed copies read well: progress bars
as text (tqdm's widget bars are saved at 0 % by papermill) and no Open3D "WebVisualizer" banner.

This module owns those rules (:func:`known_choices`, the annotation grammar of :func:`parse_type`),
:class:`ParameterError` and the kernel set-up; the notebooks own their declarations.
"""
from __future__ import annotations

import difflib
import functools
import os
import re
import typing
from typing import Any, Iterable, Mapping, Optional, Union

# The papermill comment that opens the cell it injects (tagged ``injected-parameters``).
INJECTED_HEADER = "# Parameters"


def quiet_kernel() -> None:
    """Set a notebook kernel up for readable executed copies (call it before Open3D is imported).

    * ``tqdm.auto`` (used by this library, diffusers and transformers) gives text progress bars,
      which papermill records as they end, instead of widgets, which it records at 0 %;
    * Open3D's import does not print its "Jupyter environment detected. Enabling Open3D
      WebVisualizer." banner nor start its WebRTC backend (``OPEN3D_DISABLE_WEB_VISUALIZER``).
    """
    os.environ.setdefault("OPEN3D_DISABLE_WEB_VISUALIZER", "true")
    import tqdm.auto
    import tqdm.autonotebook
    import tqdm.std

    for module in (tqdm.auto, tqdm.autonotebook):
        module.tqdm, module.trange = tqdm.std.tqdm, tqdm.std.trange


@functools.cache
def known_choices() -> dict[str, tuple[str, ...]]:
    """Parameters whose value must be one of a few strings (None passes where the type allows it).

    Read on first use, not at import: the dataset names come from :mod:`freereg_lib.data.sources`,
    whose import loads Open3D, which must wait for :func:`quiet_kernel`.
    """
    from freereg_lib.data.sources import EMBEDDED, ON_DISK, SYNTHETIC
    from freereg_lib.models import _ALIASES, BACKENDS

    return {
        "backend": tuple(BACKENDS) + tuple(_ALIASES),
        "dataset": SYNTHETIC + EMBEDDED + ON_DISK,
        "solver": ("kabsch", "pnp"),
        "kabsch_scoring": ("official", "open3d"),
        "geometric_method": ("fpfh", "fcgf"),
    }


# Parameters that set a FreeRegConfig field under another name (a list: one value per run).
CONFIG_ALIASES: dict[str, str] = {"t_hats": "t_hat", "w_fused": "fusion_w", "weights": "fusion_w",
                                  "sweep_ransac_iters": "ransac_iters"}


def range_problem(name: str, value: Any) -> str:
    """Why parameter ``name`` = ``value`` lies outside the range of the config field it sets
    (``""`` when it does not, or sets none): one line from :func:`freereg_lib.config.range_problem`."""
    from freereg_lib.config import field_range
    from freereg_lib.config import range_problem as field_problem

    if value is None:
        return ""
    if name == "config_overrides" and isinstance(value, dict):
        return next((f"config_overrides: {p}" for k, v in value.items() if (p := field_problem(str(k), v))), "")
    if field_range(name) is not None:
        return field_problem(name, value)
    field = CONFIG_ALIASES.get(name)
    if field is None:
        return ""
    for v in value if isinstance(value, (list, tuple)) else [value]:
        problem = field_problem(field, v)
        if problem:
            return f"{name} sets {field}: {problem}"
    return ""


class ParameterError(ValueError):
    """A notebook parameter with a wrong type, an unknown value or a misspelt name.

    In a notebook it prints as one line, without a traceback (IPython's ``_render_traceback_``).
    """

    def _render_traceback_(self) -> list[str]:
        return [f"ParameterError: {self}"]


_TYPES: dict[str, Any] = {"str": str, "int": int, "float": float, "bool": bool, "dict": dict, "list": list,
                          "tuple": tuple, "None": type(None), "Optional": Optional, "Union": Union, "Any": Any}


def parse_type(annotation: Any) -> Any:
    """The type an annotation names: a type, or a string such as ``"Optional[list[int]]"``."""
    if not isinstance(annotation, str):
        return annotation
    try:
        return eval(annotation, {"__builtins__": {}}, dict(_TYPES))  # names of _TYPES only
    except Exception as exc:
        raise ParameterError(f"cannot read the type annotation {annotation!r} ({exc})") from None


def conforms(value: Any, tp: Any) -> bool:
    """Whether ``value`` has type ``tp`` (``str``, ``int``, ``float``, ``bool``, ``Optional``, ``list[...]``,
    ``dict[...]``, ``Any``). An int is a float; a bool is not a number."""
    if tp is Any:
        return True
    if tp is type(None) or tp is None:
        return value is None
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Union:
        return any(conforms(value, a) for a in args)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            return False
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(value) == len(args) and all(conforms(v, a) for v, a in zip(value, args))
        return not args or all(conforms(v, args[0]) for v in value)
    if origin is dict:
        return isinstance(value, dict) and (not args or all(conforms(k, args[0]) and conforms(v, args[1])
                                                            for k, v in value.items()))
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp in (list, tuple):
        return isinstance(value, (list, tuple))
    if isinstance(tp, type):
        return isinstance(value, tp)
    return True


def describe(tp: Any) -> str:
    """A type as the parameters cell writes it (``list[int]``, ``Optional[str]``)."""
    if tp is type(None):
        return "None"
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Union:
        rest = [a for a in args if a is not type(None)]
        inner = describe(rest[0]) if len(rest) == 1 else " | ".join(map(describe, rest))
        return f"Optional[{inner}]" if len(rest) < len(args) else inner
    if origin is not None:
        return f"{origin.__name__}[{', '.join(describe(a) for a in args)}]"
    return getattr(tp, "__name__", str(tp))


def _is_container(tp: Any) -> bool:
    origin = typing.get_origin(tp)
    if origin is Union:
        return any(_is_container(a) for a in typing.get_args(tp))
    return origin in (list, tuple, dict) or tp in (list, tuple, dict)


def injected_names(history: Iterable[str] | None = None) -> list[str]:
    """The names papermill injected into this kernel (empty outside papermill).

    Read from the cells the kernel ran (IPython's ``In``, or ``history``): papermill's injected
    cell starts with ``# Parameters`` and holds one ``name = value`` line per parameter.
    """
    if history is None:
        try:
            from IPython import get_ipython
        except ImportError:  # pragma: no cover - IPython comes with the notebook stack
            return []
        shell = get_ipython()
        history = shell.user_ns.get("In", []) if shell is not None else []
    names: list[str] = []
    for source in history:
        if isinstance(source, str) and source.lstrip().startswith(INJECTED_HEADER):
            names += re.findall(r"^([A-Za-z_]\w*)\s*=", source, flags=re.MULTILINE)
    return list(dict.fromkeys(names))


def check_parameters(namespace: Mapping[str, Any], spec: Mapping[str, Any] | None = None,
                     injected: Iterable[str] | None = None,
                     choices: Mapping[str, Iterable[str]] | None = None) -> dict[str, Any]:
    """Check a notebook's parameters; raise :class:`ParameterError` naming the first bad one.

    Args:
        namespace: the notebook's globals (``globals()``), holding the parameter values.
        spec: ``{name: type}``; default: the annotations of the parameters cell
            (``namespace["__annotations__"]``; a string annotation is read by :func:`parse_type`).
        injected: the names papermill injected; default: read from the kernel's history
            (:func:`injected_names`). Each must be declared in ``spec``.
        choices: ``{name: allowed values}`` for string parameters; default :func:`known_choices`.

    Returns ``{name: value}`` of the declared parameters.
    """
    if spec is None:
        spec = dict(namespace.get("__annotations__", {}))
    types = {name: parse_type(tp) for name, tp in spec.items()}
    choices = known_choices() if choices is None else choices
    injected = injected_names() if injected is None else list(injected)
    for name in injected:
        if name not in types:
            close = difflib.get_close_matches(name, list(types), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ParameterError(f"unknown parameter {name!r}: this notebook declares {', '.join(types)}{hint}")
    values = {}
    for name, tp in types.items():
        if name not in namespace:
            raise ParameterError(f"parameter {name!r} is declared but has no value")
        value = namespace[name]
        values[name] = value
        if not conforms(value, tp):
            got = f"the string {value!r}" if isinstance(value, str) else f"{value!r} ({type(value).__name__})"
            msg = f"parameter {name!r} must be {describe(tp)}, got {got}"
            if _is_container(tp) and isinstance(value, str):
                example = value if value.strip()[:1] in ("[", "{") else ("{...}" if "dict" in describe(tp) else "[...]")
                msg += f"; pass lists and dicts as YAML with -y, e.g. papermill ... -y \"{name}: {example}\""
            raise ParameterError(msg)
        allowed = tuple(choices.get(name, ()))
        if allowed and value is not None:
            key = value.lower().replace("-", "_") if isinstance(value, str) else value
            if key not in allowed:
                raise ParameterError(f"parameter {name!r} is {value!r}; expected one of {', '.join(allowed)}")
        problem = range_problem(name, value)
        if problem:
            raise ParameterError(f"parameter {name!r}: {problem}")
    return values
