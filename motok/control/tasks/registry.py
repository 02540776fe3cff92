"""The tasks a high-level policy learns (``motok control train --task NAME``): each a config, a
task class on the :class:`~motok.control.mdp.task_env.Task` protocol and an evaluation function
``evaluate(mdp, act, episodes) -> dict`` (the paper's metrics for that task). A task may also
have ``markers() -> (N, K, 3)``, world points a video draws (targets, keyframes, a head target)."""

from __future__ import annotations

from dataclasses import dataclass, field

from motok.control.tasks.nav_eval import evaluate_navigation
from motok.control.tasks.episodes import evaluate_hmd, evaluate_inbetween
from motok.control.tasks.hmd import HMDTask, HMDTaskConfig
from motok.control.tasks.inbetween import InbetweenTask, InbetweenTaskConfig
from motok.control.tasks.navigation import NavigationTask, NavigationTaskConfig
from motok.errors import UserError

TASKS = {
    "navigation": (NavigationTask, evaluate_navigation),  # appendix C.3
    "inbetween": (InbetweenTask, evaluate_inbetween),  # C.1
    "hmd": (HMDTask, evaluate_hmd),  # C.2
}


@dataclass
class TaskConfigs:
    """Every task's settings; the recipe's ``task:`` names the one in use (``tasks.navigation.speed=...``)."""

    navigation: NavigationTaskConfig = field(default_factory=NavigationTaskConfig)
    inbetween: InbetweenTaskConfig = field(default_factory=InbetweenTaskConfig)
    hmd: HMDTaskConfig = field(default_factory=HMDTaskConfig)


def check(name: str) -> None:
    if name not in TASKS:
        raise UserError(f"task must be one of {', '.join(TASKS)}, not {name!r}")


def make(name: str, cfgs: TaskConfigs, env, lib, rng):
    check(name)
    return TASKS[name][0](getattr(cfgs, name), env, lib, rng)


def evaluate(name: str, mdp, act, episodes: int) -> dict:
    check(name)
    return TASKS[name][1](mdp, act, episodes)
