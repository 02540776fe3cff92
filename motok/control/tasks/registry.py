"""The table of tasks a high-level policy learns over a frozen prior (``motok control train --task
NAME``, ``motok control eval --task NAME --policy RUN``, a recipe's ``tasks:`` section).

Every file of this folder but :data:`HELPERS` and the imitation task is a task, and declares
``SPEC``, a :class:`TaskSpec`: its config, its task class, its evaluation, and what a full
evaluation adds from the dataset. A new task is one file here plus a recipe: the command line,
:class:`TaskConfigs` and the trainer read this table. Listing the names reads the folder only (the
command line's help must not import torch or MuJoCo); a task's module is imported when its spec
is asked for.
"""

from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass, field, make_dataclass
from functools import cache
from pathlib import Path
from typing import Callable

from motok.errors import UserError

HELPERS = ("registry", "episodes")  # files of this folder that are not tasks
# The expert's and the priors' task, learned by `control expert train` and `control distill` and
# evaluated with `control eval --task imitation --prior`, not over a prior.
IMITATION = "imitation"


def _as_is(res: dict, data, lib) -> dict:
    return res


def _own_only(cfg) -> tuple[str, ...]:
    return ()


@dataclass(frozen=True)
class TaskSpec:
    """One task as the trainer, the evaluations and the command line see it."""

    name: str  # the task's name: --task NAME, tasks.NAME in a recipe, the file's name
    config: type  # its settings, a dataclass (the recipe's tasks.NAME section)
    task: type  # its Task class, built by its build(config, env, library, rng, every task's config)
    evaluate: Callable  # evaluate(mdp, act, episodes) -> dict: the task's metrics over whole episodes
    report: Callable = _as_is  # report(result, data, library) -> result: what a full evaluation adds from the dataset
    # The active codebooks M the paper learns the task with over a residual prior (Tables 6-8), the
    # default of a run's ``codebooks``; None: all of the prior's (a task the paper does not have).
    codebooks: int | None = None
    # The other tasks whose settings (tasks.NAME) it reads, from its own config: a multitask's
    # sub-tasks, compose's navigation. What an evaluation's --set may change besides its own.
    reads: Callable = _own_only


def settings_read(name: str, cfgs) -> list[str]:
    """The ``tasks.NAME`` sections the task ``name`` reads, with every task's settings ``cfgs``."""
    return [name, *spec(name).reads(getattr(cfgs, name))]


def names() -> list[str]:
    """The tasks a policy learns over a prior, from this folder's files alone (nothing imported)."""
    here = str(Path(__file__).parent)
    return sorted(m.name for m in pkgutil.iter_modules([here])
                  if not m.name.startswith("_") and m.name not in (*HELPERS, IMITATION))


def check(name: str) -> None:
    if name not in names():
        raise UserError(f"task must be one of {', '.join(names())}, not {name!r}")


@cache
def spec(name: str) -> TaskSpec:
    """The ``SPEC`` of the task ``name``."""
    check(name)
    found = getattr(importlib.import_module(f"{__package__}.{name}"), "SPEC", None)
    if not isinstance(found, TaskSpec) or found.name != name:
        raise TypeError(f"{__package__}.{name} must declare SPEC = TaskSpec({name!r}, ...)")
    return found


@cache
def _task_configs() -> type:
    cls = make_dataclass("TaskConfigs", [(n, spec(n).config, field(default_factory=spec(n).config)) for n in names()])
    cls.__module__ = __name__
    return cls


def __getattr__(attr: str):
    # TaskConfigs: every task's settings, one field per task (``tasks.navigation.speed=...``); the
    # recipe's ``task:`` names the one in use. Built on first use: it imports every task.
    if attr == "TaskConfigs":
        return _task_configs()
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")


def make(name: str, cfgs, env, lib, rng):
    """The task ``name`` with its settings from ``cfgs`` (a :class:`TaskConfigs`)."""
    return spec(name).task.build(getattr(cfgs, name), env, lib, rng, cfgs)


def evaluate(name: str, mdp, act, episodes: int) -> dict:
    return spec(name).evaluate(mdp, act, episodes)
