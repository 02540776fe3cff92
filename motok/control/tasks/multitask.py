"""One high-level policy for several tasks at once (the hybrid-latent paper's future work: a single
controller over the frozen prior for navigation, in-betweening, head tracking and steering).

Each environment carries one sub-task at a time; the sub-tasks are the registry's own tasks, built
with their own settings (the recipe's ``tasks.NAME`` sections, the same ones the per-task recipes
set) and stepping the one shared physics:

* **assignment**: environment ``i`` carries sub-task ``assigned[i]``, fixed for the run:
  ``weights`` (equal when unset: round robin) split the environments by largest remainder with
  at least one each, in an order shuffled by the task's generator (the seed). A fixed split, not
  a draw at every reset, so every rollout batch holds every sub-task and each sub-task's share of
  the samples is its share of the environments, whatever its episode length;
* **goal**: ``[one-hot of the active sub-task (K), slot of sub-task 1, ..., slot of sub-task K]``,
  every sub-task's goal in its own slot (its ``goal_dim`` numbers), the slots of the inactive
  sub-tasks zero. Separate slots, not one padded slot shared by all: a column then always means
  the same quantity, so its running normalisation and the first layer's weights on it serve one
  sub-task. A one-hot, not a learned task embedding: the policy's first layer times the one-hot
  *is* a learned embedding (one weight column per task), so the policy network is unchanged and
  any prior's high-level policy reads it (:func:`goal_layout`);
* **reward, episode end**: the active sub-task's own (its ``reward_key`` term, its termination and
  truncation). Sub-tasks have different lengths (8 s navigation, 4 s windows, 5 s head
  trajectories, 10 s steering) and failure tests (a fall, the body or head off the reference):
  each environment's episode is its sub-task's episode, ended by that sub-task's tests, and the
  environment restarts in its assigned sub-task. Every sub-task steps all environments (its
  terms are vectorised over them); only the active one's outcome is used, the others' episode
  state runs on unused (reference lookups clamp at a clip's end);
* **switching** (``switch``, zero-shot): at the given times into an episode every environment
  switches to the named sub-task, which takes over from the character's current state
  (``Task.join``: a navigation target around the root, a steering command); the one-hot and the
  goal change at that step and the new sub-task's tests and clock end the episode from then on.
  Only sub-tasks that can start mid-episode are allowed (``joins_mid_episode``): the reference of
  in-betweening and head tracking starts at their own start state. Switching is an evaluation
  setting (the video and :func:`evaluate_switch`): training plays whole single-task episodes.

Evaluation (:func:`evaluate_multitask`): every sub-task's own evaluation (its ``SPEC.evaluate``,
so the numbers compare with the per-task policies' at the same total samples), with every
environment on that sub-task, keys ``NAME.metric``; then, with ``switch`` set, the switching
episodes (``switch.*``).
"""

from __future__ import annotations

import re
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.task_env import Task, TaskEnv
from motok.control.tasks import registry
from motok.control.tasks.episodes import Act, Step, play_episodes
from motok.errors import UserError
from motok.ranges import In

NAME = "multitask"
SWITCH = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*s\s+(\S+)\s*$")


@dataclass
class MultitaskConfig:
    # the sub-tasks (registry names), each with its settings from the recipe's tasks.NAME section
    tasks: list[str] = field(default_factory=lambda: ["navigation", "inbetween", "hmd", "steering"])
    weights: In[list[float] | None, "> 0"] = None  # share of the environments per sub-task, in `tasks` order; None: equal
    # evaluation and video: "SECONDS NAME" entries, at which time into an episode every environment switches
    # to the sub-task NAME (zero-shot: the policy was trained on single-task episodes)
    switch: list[str] = field(default_factory=lambda: ["4s steering"])

    def __post_init__(self):
        if not self.tasks:
            raise UserError("multitask: tasks must name at least one task")
        if len(set(self.tasks)) != len(self.tasks) or NAME in self.tasks:
            raise UserError(f"multitask: tasks must be distinct tasks other than {NAME}, got {self.tasks}")
        if self.weights is not None and (len(self.weights) != len(self.tasks) or min(self.weights) <= 0):
            raise UserError(f"multitask: weights must be {len(self.tasks)} positive numbers (one per task), "
                            f"got {self.weights}")
        self.schedule()

    def schedule(self) -> list[tuple[float, str]]:
        """``switch`` as ``(seconds, name)`` pairs in time order."""
        out = []
        for entry in self.switch:
            m = SWITCH.match(entry)
            if m is None or m.group(2) not in self.tasks:
                raise UserError(f"multitask: switch entries are 'SECONDS NAME' with NAME one of {self.tasks}, "
                                f"got {entry!r}")
            out.append((float(m.group(1)), m.group(2)))
        return sorted(out)


def assignment(n: int, weights, rng) -> np.ndarray:
    """``(n,)`` sub-task index of each environment: counts in proportion to ``weights`` (largest
    remainder), at least one each when ``n`` allows, placed in an order drawn from ``rng``."""
    w = np.asarray(weights, dtype=np.float64)
    K = len(w)
    base = np.minimum(1, n // K) if n >= K else 0
    quota = (n - base * K) * w / w.sum()
    counts = base + np.floor(quota).astype(np.int64)
    left = n - counts.sum()
    counts[np.argsort(-(quota - np.floor(quota)), kind="stable")[:left]] += 1
    return np.repeat(np.arange(K), counts)[rng.permutation(n)]


def goal_layout(names: list[str], dims: list[int]) -> dict[str, slice]:
    """Where each part of the multitask goal lies: ``"task"`` the one-hot, then one slot per sub-task."""
    out, at = {"task": slice(0, len(names))}, len(names)
    for name, d in zip(names, dims):
        out[name], at = slice(at, at + d), at + d
    return out


class MultitaskTask(Task):
    """Sub-tasks ``subtasks`` on one environment; per environment the ``assigned`` sub-task, the
    ``active`` one (the assigned one, or the one switched to) and ``steps`` since the reset.
    ``outcome[k]``: sub-task ``k``'s ``(rewards, terminated, truncated, info)`` of the last step,
    for all environments (its evaluation reads it through :class:`SubTaskEnv`)."""

    reward_key = "r_task"

    def __init__(self, cfg: MultitaskConfig, env, lib, rng, cfgs=None):
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        cfgs = cfgs if cfgs is not None else registry.TaskConfigs()
        self.names = list(cfg.tasks)
        for name in self.names:
            registry.check(name)
        self.subtasks = [registry.make(name, cfgs, env, lib, rng) for name in self.names]
        self.layout = goal_layout(self.names, [t.goal_dim for t in self.subtasks])
        self.goal_dim = self.layout[self.names[-1]].stop
        hz = env.control_hz
        self.switches = [(max(1, int(round(s * hz))), self.names.index(n)) for s, n in cfg.schedule()]
        for _, k in self.switches:
            if not self.subtasks[k].joins_mid_episode:
                raise UserError(f"multitask: cannot switch to {self.names[k]} mid-episode: its goal follows a "
                                f"reference from its own start state")
        N, S = env.num_envs, lib.starts
        self.assigned = like(S, assignment(N, cfg.weights or [1.0] * len(self.names), rng))
        self.active, self.steps = copy(self.assigned), like(S, np.zeros(N, dtype=np.int64))
        self.switched_at = np.zeros(N, dtype=np.int64)  # the step of the episode's last switch, 0: none (evaluations)
        self.switching = False  # evaluations and videos turn it on (for_evaluation, evaluate_switch)
        self.outcome: list[tuple] = []

    @classmethod
    def build(cls, cfg, env, lib, rng, cfgs=None):
        return cls(cfg, env, lib, rng, cfgs)

    def reset(self, ids, **where) -> None:
        """Each environment of ``ids`` back on its assigned sub-task, which resets it."""
        ids = np.atleast_1d(np.asarray(ids.cpu() if is_tensor(ids) else ids, dtype=np.int64))
        self.active[ids], self.steps[ids], self.switched_at[ids] = self.assigned[ids], 0, 0
        mine = np.asarray(self.assigned[ids].cpu() if is_tensor(self.assigned) else self.assigned[ids])
        for k, sub in enumerate(self.subtasks):
            if (mine == k).any():  # the sub-task's ids as the environment takes them (host or device)
                sub.reset(like(self.steps, ids[mine == k]) if is_tensor(self.steps) else ids[mine == k], **where)

    def goal(self):
        x = xp(self.env.bodies.pos)
        parts = [x.stack([self.active == k for k in range(len(self.names))], -1) * 1.0]
        for k, sub in enumerate(self.subtasks):
            parts.append(x.where((self.active == k)[:, None], sub.goal(), 0.0))
        return x.concatenate(parts, -1)

    def update(self, diverged, invalid):
        self.steps += 1
        self.outcome = [sub.update(diverged, invalid) for sub in self.subtasks]
        x = xp(diverged)
        r, term, trunc = x.zeros_like(diverged * 1.0), x.zeros_like(diverged), x.zeros_like(diverged)
        for k, (rew, te, tr, _) in enumerate(self.outcome):
            on = self.active == k
            r = x.where(on, rew[self.subtasks[k].reward_key], r)
            term, trunc = x.where(on, te, term), x.where(on, tr, trunc)
        info = {"task": copy(self.active), "episode_steps": copy(self.steps), "switched": self.switched_at > 0,
                "diverged": diverged, "invalid_action": invalid}
        if self.switching:
            going = ~(term | trunc)
            for at, k in self.switches:
                due = np.flatnonzero(np.asarray(going & (self.steps == at)))
                if len(due):
                    self.active[due], self.switched_at[due] = k, at
                    self.subtasks[k].join(due)
        return {"r_task": r}, term, trunc, info

    def step_limit(self):
        out = np.zeros(self.env.num_envs, dtype=np.int64)
        for k, sub in enumerate(self.subtasks):
            out = np.where(np.asarray(self.active) == k, np.broadcast_to(np.asarray(sub.step_limit()), out.shape), out)
        return out

    def markers(self) -> np.ndarray:
        """Every sub-task's markers side by side, those of the inactive ones not drawn (NaN)."""
        on = np.asarray(self.active)
        parts = []
        for k, sub in enumerate(self.subtasks):
            m = sub.markers()
            if m is not None:
                parts.append(np.where((on == k)[:, None, None], np.asarray(m, dtype=np.float64), np.nan))
        return np.concatenate(parts, 1) if parts else None

    @property
    def marker_radius(self) -> np.ndarray:
        """``(K,)``: each marker drawn at its own sub-task's size."""
        return np.concatenate([np.broadcast_to(sub.marker_radius, sub.markers().shape[1:2]) for sub in self.subtasks
                               if sub.markers() is not None])

    @property
    def marker_rgba(self) -> np.ndarray:
        """``(K, 4)``: each marker in its own sub-task's colour."""
        return np.concatenate([np.broadcast_to(np.asarray(sub.marker_rgba, dtype=np.float64),
                                               sub.markers().shape[1:2] + (4,))
                               for sub in self.subtasks if sub.markers() is not None])

    def caption(self) -> list[str]:
        return [self.names[int(k)] for k in np.asarray(self.active)]

    def for_evaluation(self) -> None:
        """Switching on and every sub-task on its evaluation settings (a video of what is measured)."""
        self.switching = True
        for sub in self.subtasks:
            sub.for_evaluation()

    @contextmanager
    def only(self, k: int | None, switching: bool = False):
        """Every environment on sub-task ``k`` (None: on its assigned one) and ``switching`` as given,
        for the duration."""
        before = (copy(self.assigned), self.switching)
        if k is not None:
            self.assigned[:] = k
        self.switching = switching
        try:
            yield
        finally:
            self.assigned, self.switching = before


class SubTaskEnv(TaskEnv):
    """The multitask MDP ``mdp`` seen by sub-task ``k``'s own evaluation: ``task`` is the sub-task
    and a step's rewards, ends and ``info`` are its own; the observation and goal the policy reads
    stay the multitask's. Every environment must carry sub-task ``k`` (:meth:`MultitaskTask.only`)."""

    def __init__(self, mdp: TaskEnv, k: int):
        super().__init__(mdp.env, mdp.task.subtasks[k], mdp.action_map)
        self.outer, self.k = mdp, k

    @property
    def goal_dim(self) -> int:
        return self.outer.goal_dim

    def reset(self, ids=None, **where):
        return self.outer.reset(ids, **where)

    def launch(self, actions, threaded: bool = True) -> None:
        self.outer.launch(actions, threaded)

    def finish(self):
        obs, goal, *_ = self.outer.finish()
        return (obs, goal, *self.outer.task.outcome[self.k])


def _flat(name: str, res: dict) -> dict:
    return {f"{name}.{k}": v for k, v in res.items()}


def _scoped(name: str, res: dict) -> dict:
    return {k[len(name) + 1:]: v for k, v in res.items() if k.startswith(name + ".")}


def evaluate_switch(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """``episodes`` episodes on the assigned sub-tasks with ``switch`` on. Returns ``switched_share``
    (episodes that reached a switch), ``reward_before`` / ``reward_after`` (the active sub-task's
    reward per step before and after the first switch), ``failed_after_share`` (switched episodes
    the new sub-task's failure test ended: a fall) and ``seconds_after_mean`` (time played after
    the switch)."""
    mt = mdp.task
    c = dict(switched=0, failed=0, before=0.0, nb=0, after=0.0, na=0, seconds=0.0)

    def on_step(s: Step) -> None:
        info, live = s.info, s.live
        on = np.asarray(info["switched"])
        r = np.asarray(s.rewards["r_task"])
        c["before"] += float(r[live & ~on].sum())
        c["nb"] += int((live & ~on).sum())
        c["after"] += float(r[live & on].sum())
        c["na"] += int((live & on).sum())
        done = s.counted[on[s.counted]]
        c["switched"] += len(done)
        c["failed"] += int(np.asarray(s.terminated)[done].sum())
        c["seconds"] += float((np.asarray(info["episode_steps"])[done] - mt.switched_at[done]).sum()) * mdp.dt

    with mt.only(None, switching=True):
        play_episodes(mdp, act, episodes, on_step)
    n = max(c["switched"], 1)
    return {"episodes": int(episodes), "switched_share": c["switched"] / int(episodes),
            "reward_before": c["before"] / max(c["nb"], 1), "reward_after": c["after"] / max(c["na"], 1),
            "failed_after_share": c["failed"] / n, "seconds_after_mean": c["seconds"] / n}


def evaluate_multitask(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """Each sub-task's own evaluation on ``episodes`` episodes, every environment on it (keys
    ``NAME.metric``), then the switching episodes (``switch.*``) when ``switch`` is set; every
    environment is reset afterwards."""
    mt = mdp.task
    if not isinstance(mt, MultitaskTask):
        raise UserError(f"evaluate_multitask needs a TaskEnv around a MultitaskTask, got {type(mt).__name__}")
    out = {"tasks": list(mt.names)}
    try:
        for k, name in enumerate(mt.names):
            with mt.only(k):
                out |= _flat(name, registry.evaluate(name, SubTaskEnv(mdp, k), act, episodes))
        if mt.switches:
            out |= _flat("switch", evaluate_switch(mdp, act, episodes))
    finally:
        mdp.reset()
    return out


def report(res: dict, data, lib) -> dict:
    """Each sub-task's own additions from the dataset (navigation's idle-phase motion matching)."""
    for name in res["tasks"]:
        sub = registry.spec(name).report(_scoped(name, res), data, lib)
        res = {k: v for k, v in res.items() if not k.startswith(name + ".")} | _flat(name, sub)
    return res


# Two active codebooks: head tracking's (Table 7), the most any of the four tasks is learned with in the
# paper (in-betweening and navigation 1, Tables 6 and 8): one action space serves them all.
SPEC = registry.TaskSpec(NAME, MultitaskConfig, MultitaskTask, evaluate_multitask, report, codebooks=2,
                         reads=lambda cfg: tuple(cfg.tasks))
