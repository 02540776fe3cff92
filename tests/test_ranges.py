"""Numbers in range: every numeric field of every config dataclass and every numeric command-line
option refuses NaN, infinities, out-of-range and wrong-typed values with a one-line error that
names it, or accepts a value its declared range documents as valid. The dataclasses and options
are found by walking the code, so a new one without a range fails here."""

from __future__ import annotations

import ast
import dataclasses
import importlib
import math
import pkgutil
import typing
from pathlib import Path

import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import motok
from motok.config import ConfigError, load_config, to_dict
from motok.errors import MotokError
from motok.ranges import Range, check_config, field_ranges, range_of

MOTOK = Path(motok.__file__).parent
# What a user can type for a number that means nothing, as YAML (--set) and as a command-line word.
BAD_WORDS = [".nan", ".inf", "-.inf", "0", "-1", "-0.5", "1e300", "100000000000000000000000000000", "abc", "[1, 2]",
             "true"]
BAD_CLI_WORDS = ["nan", "inf", "-inf", "0", "-1", "-0.5", "1e300", "100000000000000000000000000000", "abc"]


# --------------------------------------------------------------------------- the configs

def _modules():
    for m in pkgutil.walk_packages([str(MOTOK)], "motok."):
        if not m.name.startswith(("motok.cli", "motok.__main__")):
            yield m.name


LOADERS = ("load_config", "resolve_config", "resume_config")  # what fills a config class from a recipe


def _loaded_config_classes() -> set[type]:
    """The classes motok fills from recipes: the first argument of every ``load_config(CLS, ...)``,
    ``resolve_config(CLS, ...)`` and ``run(load_config, CLS, ...)`` in the code that names a
    dataclass, resolved in the module that makes the call."""
    found = set()
    for path in MOTOK.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and node.args and isinstance(node.func, ast.Name):
                args = node.args
                if node.func.id == "run" and isinstance(args[0], ast.Name) and args[0].id in LOADERS:
                    args = args[1:]
                elif node.func.id not in LOADERS:
                    continue
                if args and isinstance(args[0], ast.Name):
                    found.add((path, args[0].id))
    classes = set()
    for path, name in found:
        # imported inside the function or at the top of the file, or defined there
        imports = [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.ImportFrom)
                   and any(a.name == name for a in n.names)]
        mod = imports[0].module if imports else ".".join(path.relative_to(MOTOK.parent).with_suffix("").parts)
        cls = getattr(importlib.import_module(mod), name, None)
        if isinstance(cls, type) and dataclasses.is_dataclass(cls):  # not a variable such as ``cls``
            classes.add(cls)
    return classes


def _every_config_class() -> set[type]:
    roots = _loaded_config_classes()
    for name in _modules():
        mod = importlib.import_module(name)
        for v in vars(mod).values():
            if isinstance(v, type) and dataclasses.is_dataclass(v) and v.__name__.endswith("Config") \
                    and v.__module__ == name:
                roots.add(v)
    return roots


def _nested(cls):
    for f in dataclasses.fields(cls):
        tp = typing.get_type_hints(cls)[f.name]
        for a in (tp, *typing.get_args(tp)):
            if dataclasses.is_dataclass(a):
                yield f.name, a


def _paths(cls, prefix=""):
    """``(dotted path, owning class, field)`` of every numeric field reachable from ``cls``."""
    for name, (rng, tp) in field_ranges(cls).items():
        yield prefix + name, cls, name
    for name, sub in _nested(cls):
        yield from _paths(sub, f"{prefix}{name}.")


ROOTS = sorted(_every_config_class(), key=lambda c: (c.__module__, c.__name__))
FIELDS = [(root, path, owner, name) for root in ROOTS for path, owner, name in _paths(root)]


def test_the_walk_finds_the_recipe_configs():
    names = {f"{c.__module__}.{c.__name__}" for c in _loaded_config_classes()}
    assert {"motok.control.expert.model.ExpertConfig", "motok.control.priors.model.DistillConfig",
            "motok.control.highlevel.policy.TaskTrainConfig", "motok.tokenizer.model.TrainConfig",
            "motok.gpt.model.TrainConfig", "motok.eval.evaluator.EvaluatorConfig", "motok.eval.protocol.T2MConfig",
            "motok.data.preprocess.PreprocessConfig"} <= names
    assert len(FIELDS) > 300


def test_every_numeric_field_declares_its_range():
    missing = sorted({f"{owner.__name__}.{name}" for _, _, owner, name in FIELDS
                      if field_ranges(owner)[name][0] is None})
    assert not missing, f"declare a range (In[TYPE, 'spec']) for {missing}"


def test_every_default_is_in_its_range():
    for root in ROOTS:
        assert check_config(root()) == [], root


def _set(root, path, raw: str):
    """``load_config`` of ``root`` with ``--set path=raw``: the config, or the error."""
    try:
        return load_config(root, None, [f"{path}={raw}"])
    except MotokError as e:
        return e


def _value(cfg, path):
    for k in path.split("."):
        cfg = getattr(cfg, k)
    return cfg


def _accepted(owner, name, v) -> bool:
    rng = field_ranges(owner)[name][0]
    return v is None or all(rng.problem(x) is None for x in (v if isinstance(v, (list, tuple)) else [v]))


def test_every_field_refuses_what_is_out_of_its_range_by_name():
    """Each canonical bad value through --set, into every numeric field of every config: a
    one-line error naming the field, or a value the field's range documents as valid."""
    wrong = []
    for root, path, owner, name in FIELDS:
        for raw in BAD_WORDS:
            got = _set(root, path, raw)
            if isinstance(got, MotokError):
                msg = str(got)
                if name not in msg or "\n" in msg:
                    wrong.append(f"{root.__name__} {path}={raw}: {msg!r}")
            elif not _accepted(owner, name, _value(got, path)):
                wrong.append(f"{root.__name__} {path}={raw}: accepted {_value(got, path)!r}")
    assert not wrong, "\n".join(wrong[:20])


NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-2 ** 70, max_value=2 ** 70),
                    st.sampled_from([0, -1, 0.0, -0.0, 1e-320, 2 ** 63, -2 ** 63 - 1]))
VALUES = st.one_of(NUMBERS, st.text(max_size=4), st.booleans(), st.none(), st.lists(NUMBERS, max_size=3))


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(FIELDS), VALUES)
def test_any_value_in_any_field_is_in_range_or_refused_by_name(field, value):
    root, path, owner, name = field
    d = to_dict(root())
    node = d
    *parents, leaf = path.split(".")
    for k in parents:
        node = node[k]
    node[leaf] = value
    try:
        cfg = load_config(root, None, base=d)
    except MotokError as e:
        assert name in str(e) and "\n" not in str(e), (path, value, str(e))
        return
    assert _accepted(owner, name, _value(cfg, path)), (path, value)


def test_the_issue_cases_name_the_field():
    from motok.control.expert.model import ExpertConfig

    for sets, says in ((["iterations=-5"], "iterations: -5 must be >= 1"),
                       (["task.termination_distance=nan"],
                        "task.termination_distance: nan must be a finite number > 0"),
                       (["ppo.lr=nan"], "ppo.lr: nan must be"), (["ppo.lr=.inf"], "ppo.lr: inf must be"),
                       (["ppo.gamma=1.5"], "ppo.gamma: 1.5 must be in [0, 1]"),
                       (["seed=100000000000000000000000"], "seed: 100000000000000000000000 is too large")):
        with pytest.raises(ConfigError, match=None) as e:
            load_config(ExpertConfig, None, sets)
        assert says in str(e.value), (sets, str(e.value))


@pytest.mark.parametrize("spec,inside,outside", [
    ("> 0", [1e-300, 5], [0, -1, math.nan, math.inf]), (">= 1", [1, 10 ** 6], [0, 0.5, -math.inf]),
    ("[0, 1)", [0, 0.999], [1, -0.1]), ("(0, 1]", [1, 0.5], [0, 1.01]), ("any", [-1e300, 0], [math.nan, math.inf]),
    ("<= 0", [0, -3], [1e-9]),
])
def test_range_specs(spec, inside, outside):
    r = Range(spec)
    assert all(r.problem(v) is None for v in inside) and all(r.problem(v) for v in outside)
    assert r.problem("1") and r.problem(True)  # text and booleans are not numbers


def test_a_malformed_spec_fails_at_import():
    with pytest.raises(ValueError, match="not a range"):
        Range("positive")


# --------------------------------------------------------------------------- the options

def _numeric_options():
    from motok.cli.conventions import walk
    from motok.cli.main import app

    root = typer.main.get_command(app)
    for path, cmd in walk(root):
        for p in cmd.params:
            td = getattr(p, "type_descriptor", None)
            if td is None:
                continue
            args = [a for a in typing.get_args(td.annotation) if a is not type(None)] or [td.annotation]
            if args[0] in (int, float):
                yield path, cmd, p


OPTIONS = list(_numeric_options())


def _label(p):
    return max((o for o in p.opts if o.startswith("-")), key=len)


def test_every_numeric_option_declares_its_range():
    assert len(OPTIONS) > 50
    missing = [f"{' '.join(path)} {_label(p)}" for path, _, p in OPTIONS if not hasattr(p.callback, "within")]
    assert not missing, f"use number_option(..., within=...) for {missing}"
    for _, _, p in OPTIONS:
        range_of(p.callback.within)  # a field it names exists and declares a range


def _parse(cmd, p, word: str):
    """What parsing ``OPT word`` alone does: "ok" (accepted; other options may be missing), or
    "refused" (exit 2 from the range check, or a value of the wrong type)."""
    try:
        cmd.make_context(cmd.name, [_label(p), word], resilient_parsing=False)
    except typer.Exit as e:
        assert e.exit_code == 2
        return "refused"
    except typer.BadParameter as e:
        return "ok" if type(e).__name__ == "MissingParameter" else "refused"
    except Exception as e:  # a usage error about another option: this one parsed
        if "Missing" in type(e).__name__ or "Usage" in type(e).__name__:
            return "ok"
        raise
    return "ok"


def _integer(p) -> bool:
    return int in (p.type_descriptor.annotation, *typing.get_args(p.type_descriptor.annotation))


def _number(word: str, integer: bool):
    """``word`` as the option's type reads it, or None when it is not one."""
    try:
        return int(word) if integer else float(word)
    except ValueError:
        return None


@pytest.mark.parametrize("word", BAD_CLI_WORDS)
def test_every_numeric_option_refuses_what_is_out_of_range(word, capsys):
    wrong = []
    for path, cmd, p in OPTIONS:
        got = _parse(cmd, p, word)
        v = _number(word, _integer(p))
        valid = v is not None and range_of(p.callback.within).problem(v) is None
        if got != ("ok" if valid else "refused"):
            wrong.append(f"{' '.join(path)} {_label(p)} {word}: {got}")
    assert not wrong, wrong
    capsys.readouterr()


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(OPTIONS), st.data())
def test_any_number_on_any_option_is_in_range_or_refused(option, data):
    path, cmd, p = option
    v = data.draw(st.integers(-10 ** 25, 10 ** 25) if _integer(p) else st.floats(allow_nan=True, allow_infinity=True))
    got = _parse(cmd, p, repr(v))
    valid = range_of(p.callback.within).problem(v) is None
    assert got == ("ok" if valid else "refused"), (path, _label(p), v)


@pytest.mark.parametrize("args,says", [
    (["control", "expert", "eval", "--expert", ".", "--distance", "nan"], "--distance nan must be a finite number > 0"),
    (["control", "expert", "eval", "--expert", ".", "--distance", "-1"], "--distance -1.0 must be > 0"),
    (["eval", "motion-matching", "-d", ".", "--motions", ".", "--threshold", "-1"], "--threshold -1.0 must be > 0"),
    (["control", "generate", "--prior", ".", "-o", "x.h5", "--seconds", "nan"], "--seconds nan must be a finite"),
    (["control", "train", "--prior", ".", "-o", "run", "--codebooks", "0"], "--codebooks 0 must be >= 1"),
    (["gpt", "sample", "-g", ".", "--text", "a walk", "-o", "x.h5", "--seconds", "abc"],
     "Invalid value for '--seconds'"),
])
def test_the_issue_cases_are_one_line_errors(args, says, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    from motok.cli.main import app

    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and says in lines[0], r.output
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "run").exists()


@pytest.mark.parametrize("call, says", [
    (lambda: __import__("motok.control.expert.evaluate", fromlist=["x"]).evaluate_run("no-run", distance=math.nan),
     "evaluate_run: distance=nan must be a finite number > 0"),
    (lambda: __import__("motok.control.expert.evaluate", fromlist=["x"]).evaluate_run("no-run", distance=-1.0),
     "evaluate_run: distance=-1.0 must be > 0"),
    (lambda: motok.generate(None, "a person walks", temperature=math.nan),
     "generate: temperature=nan must be a finite number > 0"),
    (lambda: motok.generate(None, "a person walks", num_samples=-1), "generate: num_samples=-1 must be >= 1"),
    (lambda: motok.generate(None, "a person walks", seconds=-2.0), "generate: seconds=-2.0 must be > 0"),
])
def test_library_entry_points_refuse_numbers_out_of_range(call, says):
    # the same ranges as the options, checked before anything is read (there is no run "no-run")
    with pytest.raises(MotokError) as e:
        call()
    assert str(e.value) == says
