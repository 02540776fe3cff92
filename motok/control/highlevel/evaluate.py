"""A task policy on its task: the task's own evaluation (``motok control eval --task T --run
RUN``, and the ``eval_*`` metrics logged while training), and a video of one episode with the
task's markers."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.config import load_config, to_dict
from motok.control import runs
from motok.control.highlevel.policy import TaskTrainConfig, load_task_run, task_mdp
from motok.control.mdp.task_env import TaskEnv
from motok.control.priors.model import LatentPrior
from motok.control.rl.networks import ActorCritic
from motok.control.rl.rollout import as_tensor
from motok.control.tasks import registry
from motok.control.tasks.imitation import policy_device
from motok.errors import UserError
from motok.ranges import checked  # numbers in range for callers from Python too
from motok.sim.env import SimConfig


def policy_fn(ac: ActorCritic, deterministic: bool):
    """``act(obs, goal) -> actions`` (numpy) for the task evaluations."""
    device = policy_device(ac)

    def act(obs: np.ndarray, goal: np.ndarray) -> np.ndarray:
        return ac.act(as_tensor(np.concatenate([obs, goal], 1)).to(device), deterministic)[1].cpu().numpy()
    return act


def evaluate_policy(cfg: TaskTrainConfig, hum, lib, model: LatentPrior, scale: float, ac: ActorCritic,
                    episodes: int, seed: int, render=None) -> dict:
    """The task's own evaluation (``registry.evaluate``) of ``ac`` on ``episodes`` episodes, with
    its own environments and a fixed seed, so two evaluations of one policy agree; ``render``: a
    video of one more episode with the task's markers (targets, keyframes, the head target)."""
    # Evaluations run on host arrays (the task evaluations are numpy), the policy where it is.
    host = {**asdict(cfg.env), "on_device": False}
    sim = SimConfig(**{**host, "num_envs": max(1, min(episodes, cfg.env.num_envs))})
    mdp = task_mdp(cfg, hum, lib, model, scale, seed, sim)
    act = policy_fn(ac, cfg.deterministic_eval)
    res = registry.evaluate(cfg.task, mdp, act, episodes)
    if render is not None:
        one = task_mdp(cfg, hum, lib, model, scale, seed, SimConfig(**{**host, "num_envs": 1}))
        one.task.for_evaluation()  # the video shows what the evaluation plays; render_episode resets first
        res["video"] = render_episode(one, act, render, f"{cfg.task} over the {model.kind} prior")
    return res


def render_episode(mdp: TaskEnv, act, out, title: str) -> str:
    """One episode of a 1-environment ``mdp`` to a video, with the task's ``markers()`` and, on
    each frame, its ``caption()`` after the title."""
    from motok.sim.render import render_trajectory

    task = mdp.task
    obs, goal = mdp.reset()
    qpos, marks, captions = [mdp.env.qpos[0].copy()], [], []

    def mark():
        m, c = task.markers(), task.caption()
        if m is not None:
            marks.append(m[0])
        if c is not None:
            captions.append(f"{title}: {c[0]}")

    mark()
    while True:
        obs, goal, _, term, trunc, _ = mdp.step(act(obs, goal))
        qpos.append(mdp.env.qpos[0].copy())
        mark()
        if term[0] or trunc[0]:
            break
    path, backend = render_trajectory(mdp.env.hum, np.stack(qpos), out, mdp.env.control_hz, title=captions or title,
                                      markers=np.stack(marks) if marks else None, marker_radius=task.marker_radius,
                                      marker_rgba=task.marker_rgba)
    return f"{path} ({backend})"


def with_task_settings(cfg: TaskTrainConfig, sets: list[str]) -> TaskTrainConfig:
    """``cfg`` with ``tasks.NAME.KEY=VALUE`` overrides (``--set``): an evaluation under other task
    settings than the training's (a switching schedule, more keyframes). Only ``tasks.*``: the
    network, the physics and the prior are the run's."""
    bad = [s for s in sets if not s.strip().startswith("tasks.")]
    if bad:
        raise UserError(f"--set on an evaluation changes task settings only (tasks.NAME.KEY=VALUE), not {bad}")
    if not sets:
        return cfg
    new = load_config(TaskTrainConfig, overrides=sets, base=to_dict(cfg))
    read = registry.settings_read(new.task, new.tasks)
    unread = [s for s in sets if s.strip().split("=", 1)[0].split(".")[1] not in read]
    if unread:
        raise UserError(f"--set {unread[0]}: a {new.task!r} policy reads only "
                        f"{', '.join(f'tasks.{n}' for n in read)}; that setting would change nothing")
    return new


@checked(episodes=">= 1", seed=">= 0")
def evaluate_run(run, *, episodes: int = 256, seed: int = 0, data=None, clips: str | None = None,
                 split: str | None = None, render=None, device: str | None = None, task: str | None = None,
                 sets: list[str] | None = None) -> dict:
    """``motok control eval --task T --policy RUN``: the task's evaluation of the policy in ``run``
    on ``episodes`` episodes (start states from its clips, or those of ``data`` / ``clips`` /
    ``split``), written to ``RUN/eval_TASK[_SPLIT].json`` with the checkpoint and provenance.
    ``task``, when given, must be the run's (checked before any work); ``sets``: ``tasks.*``
    overrides of the run's task settings (:func:`with_task_settings`)."""
    run = Path(run)
    loaded = load_task_run(run)
    loaded = (with_task_settings(loaded[0], sets or []), *loaded[1:])
    res, src = evaluate_loaded(run, loaded, episodes=episodes, seed=seed, data=data, clips=clips,
                               split=split, render=render, device=device, task=task)
    prov = Provenance(command=command_line(), config={"run": str(run), "episodes": episodes, "seed": seed,
                                                        "clips": clips, "split": split, "sets": sets or []},
                      inputs=hash_inputs([src]))
    res["provenance"] = json.loads(prov.to_json())
    path = run / (f"eval_{res['task']}" + (f"_{split}" if split else "") + ".json")
    runs.write_evaluation(path, res)
    res["written"] = str(path)
    return res


@checked(episodes=">= 1", seed=">= 0")
def evaluate_loaded(run, loaded: tuple, *, episodes: int = 256, seed: int = 0, data=None, clips: str | None = None,
                    split: str | None = None, render=None, device: str | None = None,
                    task: str | None = None) -> tuple[dict, Path | str]:
    """The evaluation of :func:`evaluate_run` on a task run already loaded (``loaded``: what
    :func:`~motok.control.highlevel.policy.load_task_run` returns for ``run``), in memory: the
    report (without provenance) and the dataset its start states came from."""
    cfg, hum, ac, model, scale, meta = loaded
    if task is not None and task != cfg.task:
        raise UserError(f"{run} is a {cfg.task!r} policy, not {task!r}")
    cfg.env.on(device)
    src, lib = runs.run_library(run, meta, hum, cfg.env.control_hz, data, clips, split)
    res = evaluate_policy(cfg, hum, lib, model, scale, ac, episodes, seed, render=render)
    res = registry.spec(cfg.task).report(res, src, lib)
    res = {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in res.items()}  # JSON: per-step arrays as lists
    res = {"kind": "control-task-eval", "schema_version": 1, "task": cfg.task, "episodes": episodes, **res,
           "checkpoint": {**runs.checkpoint_info(meta), "prior": meta["extra"]["prior_info"],
                          "high_level_action": meta["extra"]["high_level_action"]}}
    return res, src
