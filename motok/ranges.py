"""The valid range of every number a user can set, declared once, beside the setting.

A config field says its range in its annotation, ``lr: In[float, "> 0"] = 3e-4``; the loader
(:func:`motok.config.load_config`) checks every field with :func:`check_config` after building
the config, and a numeric command-line option declares the same kind of range
(:func:`motok.cli.common.number_option`), checked by :meth:`Range.problem` at parse time. Either
way a value outside its range is refused before any work, with the setting's name, the value and
the range, instead of training on NaN or reporting a success rate computed with a negative
distance.

A range is written as ``"> 0"``, ``">= 1"``, ``"<= 0"``, ``"[0, 1]"``, ``"(0, 1]"``, ``"[0, 1)"``,
``"(0, 1)"`` or ``"any"`` (any finite number). Every range refuses NaN and infinities: no setting
means anything by them. Integers must also fit in 64 bits, which torch and numpy need. ``None``
passes wherever the field's type allows it (it means "derive it", documented per field). A list of
numbers has the range of each element.

This module imports nothing heavy: the command line reads it while parsing.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import typing
from typing import Annotated, Any

INT64 = 2 ** 63  # integers beyond this overflow torch and numpy's int64

_BOUND = re.compile(r"^\s*(>=|<=|>|<)\s*(\S+)\s*$")
_INTERVAL = re.compile(r"^\s*([\[(])\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*([\])])\s*$")


@dataclasses.dataclass(frozen=True)
class Range:
    """A range of valid numbers, parsed from its spec (see the module's docstring)."""
    spec: str

    @functools.cached_property
    def _bounds(self) -> tuple[float, bool, float, bool]:
        """``(low, low_inclusive, high, high_inclusive)``, open ends at infinity."""
        s = self.spec.strip()
        if s == "any":
            return -math.inf, False, math.inf, False
        if m := _BOUND.match(s):
            op, x = m.group(1), float(m.group(2))
            if op.startswith(">"):
                return x, op == ">=", math.inf, False
            return -math.inf, False, x, op == "<="
        if m := _INTERVAL.match(s):
            return float(m.group(2)), m.group(1) == "[", float(m.group(3)), m.group(4) == "]"
        raise ValueError(f"not a range: {self.spec!r}")

    def __post_init__(self):
        self._bounds  # a typo in a declaration fails when the module is imported, not when a user hits it

    def __str__(self) -> str:
        s = self.spec.strip()
        return s if s == "any" or s[0] in "<>" else f"in {s}"

    def contains(self, v) -> bool:
        lo, lo_in, hi, hi_in = self._bounds
        if not math.isfinite(v):
            return False
        return (v > lo or (lo_in and v == lo)) and (v < hi or (hi_in and v == hi))

    def problem(self, v) -> str | None:
        """Why ``v`` is refused (``"must be > 0"``), or None when it is in range."""
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return f"must be a number {self}" if str(self) != "any" else "must be a number"
        if isinstance(v, int) and not -INT64 <= v < INT64:
            return "is too large (integers must fit in 64 bits)"
        if not math.isfinite(v):
            return "must be a finite number" + ("" if str(self) == "any" else f" {self}")
        if not self.contains(v):
            return f"must be {self}"
        return None


class In:
    """``In[float, "> 0"]``: the annotation of a field whose values must be in a range. It is
    ``Annotated[float, Range("> 0")]``, so everything that reads the plain type (the loader's
    coercion, type checkers) still sees ``float``."""

    def __class_getitem__(cls, params):
        tp, spec = params
        return Annotated[tp, Range(spec)]


ANY = Range("any")  # what a float field without a declared range gets: at least a finite number


def _numeric(tp) -> bool:
    """Whether values of the (plain) type ``tp`` are numbers, or lists or tuples of numbers."""
    if tp in (int, float):
        return True
    if typing.get_origin(tp) is dict:
        return False
    return any(_numeric(a) for a in typing.get_args(tp) if a not in (type(None), Ellipsis))


def field_ranges(cls) -> dict[str, tuple[Range | None, Any]]:
    """``name -> (declared range or None, plain type)`` of the numeric fields of dataclass ``cls``."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = {}
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        rng = None
        if typing.get_origin(tp) is Annotated:
            rng = next((m for m in tp.__metadata__ if isinstance(m, Range)), None)
            tp = typing.get_args(tp)[0]
        if _numeric(tp):
            out[f.name] = (rng, tp)
    return out


def range_of(within: str) -> Range:
    """The range ``within`` names: a spec (``"> 0"``) or a config field, ``"module:Class.a.b"``
    (the range field ``b`` of the dataclass of field ``a`` of ``Class`` declares). Importing the
    module happens here, when an option is checked, so ``motok --help`` stays cheap."""
    if ":" not in within:
        return Range(within)
    import importlib

    module, path = within.split(":")
    *parents, name = path.split(".")
    cls = getattr(importlib.import_module(module), parents[0])
    for p in parents[1:]:
        tp = typing.get_type_hints(cls)[p]
        cls = next(a for a in (tp, *typing.get_args(tp)) if dataclasses.is_dataclass(a))
    rng = field_ranges(cls)[name][0]
    if rng is None:
        raise LookupError(f"{within} declares no range")
    return rng


def _values(v):
    return list(v) if isinstance(v, (list, tuple)) else [v]


def check_config(cfg, where: str = "") -> list[str]:
    """Every numeric field of the dataclass ``cfg`` and of the dataclasses inside it against its
    range; returns one ``dotted.name: value must be ...`` per problem (empty: all valid)."""
    problems = []
    ranges = field_ranges(type(cfg))
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        name = f"{where}.{f.name}" if where else f.name
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            problems += check_config(v, name)
        elif f.name in ranges and v is not None:
            rng = ranges[f.name][0] or ANY
            for i, x in enumerate(_values(v)):
                if (why := rng.problem(x)) is not None:
                    problems.append(f"{name}{f'[{i}]' if isinstance(v, (list, tuple)) else ''}: {x!r} {why}")
    return problems


def checked(**within: str):
    """Decorate a library entry point so that the numeric arguments named in ``within`` are checked
    when it is called, against the range a command-line option would name (a spec, ``"> 0"``, or
    a config field, as :func:`motok.cli.common.number_option` takes): a caller from Python gets
    the same refusal as one from the shell, a :class:`motok.errors.UserError` naming the function,
    the argument, the value and the range, before any work. ``None`` (left to the run or the
    recipe) is not checked; neither are defaults, which are in range."""
    import inspect

    def wrap(fn):
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def call(*args, **kw):
            given = sig.bind_partial(*args, **kw).arguments
            for name, spec in within.items():
                v = given.get(name)
                if v is None:
                    continue
                if type(v).__module__ == "numpy" and getattr(v, "ndim", None) == 0:
                    v = v.item()  # a numpy scalar is the number it holds
                if (why := range_of(spec).problem(v)) is not None:
                    from motok.errors import UserError
                    raise UserError(f"{fn.__name__}: {name}={v!r} {why}")
            return fn(*args, **kw)
        return call
    return wrap
