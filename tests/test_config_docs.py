"""Every config field says what it is where it is declared: a trailing ``# comment`` on its line, a
comment line directly above it, or a string literal directly below it (an attribute docstring).

The configs checked are those the commands load from recipes and ``--set`` (the roots below), every
dataclass reachable from them through their fields' types, and every dataclass of the package named
``...Config`` or ``...Schedule``, so a config no command loads yet is held to the same rule.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import io
import textwrap
import tokenize
import typing
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "motok"

# What the commands load (motok/cli: load_config, resolve_config, and the configs saved in bundles).
ROOTS = (
    "motok.data.preprocess:PreprocessConfig",  # motok preprocess
    "motok.tokenizer.model:TrainConfig",  # motok tokenize train
    "motok.gpt.model:TrainConfig",  # motok gpt train
    "motok.eval.evaluator:EvaluatorConfig",  # motok eval train-evaluator
    "motok.eval.protocol:T2MConfig",  # motok eval t2m
    "motok.eval.labels:LabelsConfig",  # motok eval labels
    "motok.sim.humanoid:HumanoidConfig",  # motok sim build-humanoid
    "motok.sim.env:SimConfig",  # the env section of every physics run
    "motok.control.expert.model:ExpertConfig",  # motok control expert train
    "motok.control.priors.model:DistillConfig",  # motok control distill
    "motok.control.highlevel.policy:TaskTrainConfig",  # motok control train
    "motok.control.highlevel.perturb:PerturbConfig",  # motok control perturb
)
# Built by make_dataclass, with no source to read: one field per task, each the task's own config
# (checked through its type), documented once where the class is built.
GENERATED = {"motok.control.tasks.registry.TaskConfigs"}


def _load(spec: str) -> type:
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


def _named_configs() -> list[str]:
    """``module:Class`` of every dataclass in the package named ``...Config`` or ``...Schedule``."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.parse(path.read_text()).body:
            if (isinstance(node, ast.ClassDef) and node.name.endswith(("Config", "Schedule"))
                    and any("dataclass" in ast.unparse(d) for d in node.decorator_list)):
                out.append(f"{module}:{node.name}")
    return out


def _dataclasses_in(tp) -> list[type]:
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return [tp]
    return [c for arg in typing.get_args(tp) for c in _dataclasses_in(arg)]


def config_classes() -> list[type]:
    """The roots, the named configs, and every dataclass reachable from them (bases included)."""
    seen: dict[str, type] = {}
    todo = [_load(s) for s in (*ROOTS, *_named_configs())]
    while todo:
        cls = todo.pop()
        key = f"{cls.__module__}.{cls.__qualname__}"
        if key in seen:
            continue
        seen[key] = cls
        todo.extend(b for b in cls.__mro__[1:] if dataclasses.is_dataclass(b))
        for tp in typing.get_type_hints(cls).values():
            todo.extend(_dataclasses_in(tp))
    return [seen[k] for k in sorted(seen)]


def undocumented(cls: type) -> list[str]:
    """``module.Class.field`` of each field ``cls`` declares itself that has no comment on its
    line(s), no comment line directly above and no string literal directly below."""
    own = set(cls.__dict__.get("__annotations__", {})) & {f.name for f in dataclasses.fields(cls)}
    src = textwrap.dedent(inspect.getsource(cls))
    tokens = list(tokenize.generate_tokens(io.StringIO(src).readline))
    comments = {t.start[0] for t in tokens if t.type == tokenize.COMMENT}
    comment_lines = {t.start[0] for t in tokens if t.type == tokenize.COMMENT and t.line.lstrip().startswith("#")}
    body = next(n for n in ast.parse(src).body if isinstance(n, ast.ClassDef)).body
    missing = []
    for i, st in enumerate(body):
        if not (isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name) and st.target.id in own):
            continue
        after = body[i + 1] if i + 1 < len(body) else None
        if (comments & set(range(st.lineno, st.end_lineno + 1)) or st.lineno - 1 in comment_lines
                or isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)):
            continue
        missing.append(f"{cls.__module__}.{cls.__qualname__}.{st.target.id}")
    return missing


def test_the_walk_reaches_the_configs_the_commands_load():
    names = {f"{c.__module__}.{c.__qualname__}" for c in config_classes()}
    for spec in ROOTS:
        assert spec.replace(":", ".") in names
    # Reached through field types only: nested sections and the per-task configs.
    assert {"motok.optim.OptimConfig", "motok.control.rl.ppo.PPOConfig",
            "motok.control.tasks.navigation.NavigationTaskConfig"} <= names


def test_every_config_field_is_documented_where_it_is_declared():
    missing = [m for cls in config_classes() if f"{cls.__module__}.{cls.__qualname__}" not in GENERATED
               for m in undocumented(cls)]
    assert not missing, f"{len(missing)} config field(s) without a comment or docstring:\n" + "\n".join(missing)


def test_the_check_sees_each_documentation_style_and_its_absence():
    @dataclasses.dataclass
    class Probe:
        trailing: int = 1  # a trailing comment
        # a comment line above
        above: int = 2
        below: int = 3
        """an attribute docstring"""
        bare: int = 4
        after_trailing: int = 5  # (the line above this one's field ends in a comment: not a comment line)
        follows: int = 6
        multi: tuple = (
            1,  # a comment inside the declaration
        )

    assert undocumented(Probe) == [f"{__name__}.{Probe.__qualname__}.{n}" for n in ("bare", "follows")]
