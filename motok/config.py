"""Configs are dataclasses, filled from a YAML recipe and then ``--set key=value`` overrides.

Unknown keys are errors (a typo in a recipe must not silently train the default), nested
dataclasses are addressed with dots (``--set optim.lr=1e-4``), and values are parsed as YAML
so numbers, booleans and lists come out typed. Every number is then checked against the range its
field declares (``In[float, "> 0"]``, :mod:`motok.ranges`), so a NaN learning rate or a negative
iteration count stops here, with the field's name, instead of deep inside a training.

A config whose key was renamed lists ``RENAMED_KEYS = {"old": "new"}`` (a ``ClassVar``): the old
key still works, in a recipe, a ``--set`` or a stored config, with a note naming the new one.
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from motok.errors import MotokError
from motok.progress import info
from motok.ranges import check_config

T = TypeVar("T")


class ConfigError(MotokError, ValueError):
    pass


def to_dict(cfg) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def _coerce(value, tp, where: str):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping for {tp.__name__}, got {value!r}")
        return from_dict(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            value = [value]
        inner = args[0] if args else Any
        out = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return out if origin is list else tuple(out)
    if tp is float:
        if isinstance(value, str):  # YAML 1.1 reads 1e-3 (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, (str, int, float)):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return str(value)
    return value


def _renamed(cls, d: dict, where: str) -> dict:
    """``d`` with the old keys of ``cls`` (and of its nested configs) replaced by the new ones."""
    if not dataclasses.is_dataclass(cls) or not isinstance(d, dict):
        return d
    table = getattr(cls, "RENAMED_KEYS", {})
    hints = typing.get_type_hints(cls)
    out = {}
    for k, v in d.items():
        if k in table:
            if table[k] in d:
                raise ConfigError(f"{where}: give {table[k]!r} or its old spelling {k!r}, not both")
            info(f"[yellow]note:[/] {where}: key {k} is now {table[k]} (the old spelling works until the next "
                 f"release)")
            k = table[k]
        out[k] = _renamed(hints[k], v, f"{where}.{k}") if k in hints and isinstance(v, dict) else v
    return out


def from_dict(cls: type[T], d: dict, where: str = "config") -> T:
    """``cls`` from the mapping ``d``. A key of ``cls.KEYS_ADDED`` that ``d`` lacks (a config saved
    before the key existed) takes the value listed there, the one that reproduces what that config
    did, not the key's default, which may be a newer protocol's."""
    d = _renamed(cls, d, where)
    if isinstance(d, dict):
        for k, v in getattr(cls, "KEYS_ADDED", {}).items():
            if k not in d:
                d[k] = copy.deepcopy(v)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} for {cls.__name__}; known: {sorted(names)}")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in d.items()}
    return cls(**kwargs)


def parse_override(item: str) -> tuple[list[str], Any]:
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected key=value")
    key, raw = item.split("=", 1)
    try:
        value = yaml.safe_load(raw) if raw != "" else ""
    except yaml.YAMLError:
        value = raw
    return key.strip().split("."), value


def load_config(cls: type[T], recipe: str | Path | None = None, overrides=(), base: dict | None = None) -> T:
    """Defaults of ``cls`` <- ``base`` <- the recipe file <- ``--set`` overrides."""
    d: dict[str, Any] = to_dict(cls()) if base is None else copy.deepcopy(base)
    where = "config"
    if recipe is not None:
        path = Path(recipe)
        if not path.exists():
            raise ConfigError(f"recipe {path} does not exist")
        try:
            loaded = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {e}") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: a recipe must be a mapping of config keys")
        _merge(d, _renamed(cls, loaded, str(path)))
        where = str(path)
    for item in overrides:
        keys, value = parse_override(item)
        keys = _renamed_path(cls, keys, f"--set {item}")
        node = d
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                raise ConfigError(f"--set {item!r}: {k!r} is not a nested section")
            node = node[k]
        node[keys[-1]] = value
    return checked(from_dict(cls, d, where))


def checked(cfg: T) -> T:
    """``cfg`` if every number in it is in its field's range, else one error naming each field
    out of range, its value and the range."""
    problems = check_config(cfg)
    if problems:
        raise ConfigError("; ".join(problems))
    return cfg


def _renamed_path(cls, keys: list[str], where: str) -> list[str]:
    """A dotted ``--set`` key with its renamed parts replaced."""
    out = []
    for k in keys:
        k = next(iter(_renamed(cls, {k: None}, where))) if dataclasses.is_dataclass(cls) else k
        out.append(k)
        cls = typing.get_type_hints(cls).get(k) if dataclasses.is_dataclass(cls) else None
    return out


def _merge(dst: dict, src: dict) -> None:
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            _merge(dst[k], v)
        else:
            dst[k] = v
