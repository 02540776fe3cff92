"""The thrown-ball perturbation test of the hybrid-latent paper (Bae et al. 2025, section 6.3.3):
while a policy does its task, a ball (10 cm radius, 4.2 kg) is thrown at the character every
0.3 s from a random point 1 m away at 10-20 m/s; the policy never saw one in training
(zero-shot). :func:`perturb` counts

* **launched** balls and **hits** (balls that touched the humanoid, each counted once:
  :func:`motok.sim.balls.detect_hits`);
* **falls**: the head going below ``fall_height`` (0.5 m), counted once per fall;
* **recoveries**: hits after which the head is above ``fall_height`` ``recovery_seconds`` (3 s)
  later (the paper's "recovered"; with a task whose fall ends the episode, as navigation's, that
  is "not fallen within 3 s": a fallen character cannot get up again). A hit whose episode is
  *terminated* within the window, by a fall or a failure, is not recovered. A hit less than 3 s
  before the episode's time limit (the task's ``step_limit()``) is **censored**,
  whatever follows it: only its falls could be seen, so counting them would bias the rate low;
  so is one whose run ends within the window;
* the task's own measures: episodes ended by truncation rather than termination (``success``,
  motok's usual meaning), the main reward per step, and for tasks that report
  ``target_ends``/``target_reached`` (navigation) the share of targets reached, counted as
  :func:`motok.control.tasks.navigation.evaluate_navigation` counts them.

The MDP's humanoid must be a ball model (:func:`motok.sim.balls.build_ball_model`); its reference
library can stay the plain humanoid's (same body, same humanoid state). The pool holds
``ceil(flight_seconds / period) + 1`` balls per environment by default; each launch takes the
oldest, so a ball stays in the world ``pool * period`` s (0.9 s) before it is thrown again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from motok.control.tasks.episodes import episode_quota
from motok.control.mdp.task_env import TaskEnv
from motok.errors import UserError
from motok.ranges import In, checked  # checked: numbers in range for callers from Python too
from motok.sim.balls import ball_states, detect_hits, find_balls, humanoid_capsules, launch_balls, park_balls, set_balls


@dataclass
class PerturbConfig:
    radius: In[float, "> 0"] = 0.1  # m; must match the ball model's
    mass: In[float, "> 0"] = 4.2  # kg; must match the ball model's
    period: In[float, "> 0"] = 0.3  # s between throws at one character (rounded to control steps)
    distance: In[float, "> 0"] = 1.0  # m, horizontal, from the root to the throw's start
    speed: In[tuple[float, float], ">= 0"] = (10.0, 20.0)  # m/s, uniform
    height_range: In[tuple[float, float], ">= 0"] = (0.5, 1.5)  # m above the floor, the throw's start
    aim: str = "root"  # "root", or "body": a random body of the humanoid for each ball
    gravity_compensation: bool = True  # aim the ballistic arc (5 cm of drop over 1 m at 10 m/s)
    flight_seconds: In[float, "> 0"] = 0.5  # how long a ball must stay in the world: it arrives within 0.1 s
    pool_size: In[int | None, ">= 1"] = None  # balls per environment; None: ceil(flight_seconds / period) + 1
    recovery_seconds: In[float, "> 0"] = 3.0  # s: a hit is recovered if the head is above fall_height this long after
    fall_height: In[float, "> 0"] = 0.5  # m, head height
    min_dv: In[float, ">= 0"] = 0.05  # m/s: a velocity change beyond gravity's that means a contact
    # m: how near the humanoid the ball's path must pass for the contact to be a hit
    contact_slack: In[float, ">= 0"] = 0.05
    seed: In[int, ">= 0"] = 0  # the throws' draws

    def __post_init__(self):
        if self.aim not in ("root", "body"):
            raise UserError(f"perturb: aim must be 'root' or 'body', not {self.aim!r}")
        for name in ("period", "distance", "flight_seconds", "recovery_seconds", "radius", "mass"):
            if not getattr(self, name) > 0:
                raise UserError(f"perturb: {name} must be > 0, got {getattr(self, name)}")
        if self.pool_size is not None and self.pool_size < 1:
            raise UserError(f"perturb: pool_size must be >= 1, got {self.pool_size}")

    @property
    def pool(self) -> int:
        return int(self.pool_size or math.ceil(self.flight_seconds / self.period - 1e-9) + 1)


def time_limit(task, n: int) -> np.ndarray:
    """``(n,)`` each environment's episode length in control steps (the task's ``step_limit()``)."""
    return np.broadcast_to(np.asarray(task.step_limit(), dtype=np.int64), (n,))


@dataclass
class Windows:
    """Open recovery windows after hits, ``(N, R)``: ``since`` the step of the hit (-1: free),
    ``fell`` whether the head went below the fall height since. Entry ``launch % R`` holds a
    launch's hit, so ``R`` must exceed the launches thrown while one window is open."""

    since: np.ndarray
    fell: np.ndarray
    length: int  # control steps

    @classmethod
    def empty(cls, n: int, r: int, length: int) -> "Windows":
        return cls(np.full((n, r), -1, dtype=np.int64), np.zeros((n, r), dtype=bool), int(length))

    def open(self, envs: np.ndarray, launches: np.ndarray, step: np.ndarray) -> None:
        r = launches % self.since.shape[1]
        self.since[envs, r], self.fell[envs, r] = step, False

    def update(self, step: np.ndarray, down: np.ndarray) -> tuple[int, int, int]:
        """After a control step (``step``, ``down`` per env): ``(resolved, recovered, fell)`` counts
        of the windows that end now; recovered: the head is up at the window's end."""
        open_ = self.since >= 0
        self.fell |= open_ & down[:, None]
        due = open_ & (step[:, None] - self.since >= self.length)
        out = int(due.sum()), int((due & ~down[:, None]).sum()), int((due & self.fell).sum())
        self.since[due] = -1
        return out

    def close(self, ids: np.ndarray) -> tuple[int, int]:
        """Drop the open windows of ``ids`` (an episode's end); ``(open, fell)`` counts."""
        pend = self.since[ids] >= 0
        out = int(pend.sum()), int((pend & self.fell[ids]).sum())
        self.since[ids] = -1
        return out


def perturb(mdp: TaskEnv, act: Callable[[np.ndarray, np.ndarray], np.ndarray], episodes: int,
            cfg: PerturbConfig | None = None, record: list | None = None) -> dict:
    """Run ``act(obs, goal) -> actions`` (numpy, every environment at once) on ``mdp`` from fresh
    episodes until ``episodes`` have ended, throwing balls (module docstring); returns counts and
    rates. The throws draw from their own generator (``cfg.seed``), the task from its own.
    ``record``: a list that receives the model's whole ``qpos`` (balls included) of environment 0
    at every step of its first episode, and its task markers as ``(qpos, markers)`` pairs, for a video."""
    cfg = cfg or PerturbConfig()
    env = mdp.env
    pool = find_balls(env.hum.model)
    if not (math.isclose(pool.radius, cfg.radius) and math.isclose(pool.mass, cfg.mass)):
        raise UserError(f"perturb: the model's balls are {pool.radius} m / {pool.mass} kg, the config's "
                        f"{cfg.radius} m / {cfg.mass} kg; build the model with the config's")
    K = cfg.pool
    if pool.count < K:
        raise UserError(f"perturb: the model has {pool.count} balls per environment and the config needs {K}; "
                        f"rebuild it with count={K}")
    if int(episodes) < 1:
        raise UserError(f"perturb: episodes must be >= 1, got {episodes}")
    N, hz = env.num_envs, env.control_hz
    rng = np.random.default_rng(cfg.seed)
    caps, g = humanoid_capsules(env.hum), env.hum.model.opt.gravity.copy()
    head, J = int(env.hum.skeleton.head), len(env.hum.body_ids)
    every = max(1, int(round(cfg.period * hz)))
    window = max(1, int(round(cfg.recovery_seconds * hz)))
    # Pending recovery windows, one per launch, in a ring: launch L's hit resolves at most
    # K * every + window steps after it, before launch L + R reuses its entry.
    R = (K * every + window) // every + 2
    quota, done = episode_quota(int(episodes), N), np.zeros(N, dtype=np.int64)
    clock, launches = np.zeros(N, dtype=np.int64), np.zeros(N, dtype=np.int64)
    held = np.full((N, K), -1, dtype=np.int64)  # the launch each ball slot holds (-1: parked)
    touched = np.zeros((N, K), dtype=bool)  # that launch has hit already
    fallen = np.zeros(N, dtype=bool)
    win = Windows.empty(N, R, window)
    c = dict(launched=0, hits=0, falls=0, recoveries=0, resolved=0, censored=0, hit_falls=0, steps=0,
             truncated=0, terminated=0, diverged=0, targets=0, reached=0)
    reward = 0.0
    key = mdp.task.reward_key

    def close(ids, censored: bool):
        """End the open windows of ``ids``: cut short (truncated, the run's end) or failed (terminated)."""
        n, fell = win.close(ids)
        if censored:
            c["censored"] += n
        else:
            c["resolved"] += n
            c["hit_falls"] += fell

    obs, goal = mdp.reset()
    park_balls(env, pool, np.arange(N))  # all of the model's, then use the first K
    pool = pool.first(K)

    def keep():
        if record is not None and done[0] == 0:
            m = mdp.task.markers()
            record.append((env.stepper.qpos[0].copy(), m[0] if m is not None else None))

    keep()
    while (done < quota).any():
        live = done < quota
        throw = np.flatnonzero(live & (clock > 0) & (clock % every == 0))
        if len(throw):
            slot = launches[throw] % K  # the oldest ball of the pool
            b = env.bodies
            aim = b.pos[throw, rng.integers(0, J, len(throw))] if cfg.aim == "body" else None
            start, vel = launch_balls(b.pos[throw, 0], rng, cfg.distance, cfg.speed, cfg.height_range, target=aim,
                                      gravity=float(-g[2]) if cfg.gravity_compensation else 0.0)
            set_balls(env, pool, throw, slot, start, vel)
            held[throw, slot], touched[throw, slot] = launches[throw], False
            launches[throw] += 1
            c["launched"] += len(throw)
        before, bodies_before = ball_states(env, pool), env.bodies
        obs, goal, rewards, term, trunc, info = mdp.step(act(obs, goal))
        keep()
        clock += 1
        hit = detect_hits(pool, caps, before, ball_states(env, pool), bodies_before, env.bodies, g, env.dt,
                          cfg.min_dv, cfg.contact_slack) & (held >= 0) & ~touched & live[:, None]
        touched |= hit
        e, k = np.nonzero(hit)
        fits = clock[e] + window <= time_limit(mdp.task, N)[e]
        win.open(e[fits], held[e[fits], k[fits]], clock[e[fits]])
        c["hits"] += len(e)
        c["censored"] += int((~fits).sum())
        down = env.bodies.pos[:, head, 2] < cfg.fall_height
        c["falls"] += int((down & ~fallen & live).sum())
        fallen = down
        n, up, fell = win.update(clock, down)
        c["resolved"], c["recoveries"], c["hit_falls"] = c["resolved"] + n, c["recoveries"] + up, c["hit_falls"] + fell
        reward += float(rewards[key][live].sum())
        c["steps"] += int(live.sum())
        c["diverged"] += int((info.get("diverged", np.zeros(N, dtype=bool)) & live).sum())
        if "target_ends" in info and "target_reached" in info:
            ends = info["target_ends"] & live
            c["targets"] += int(ends.sum())
            c["reached"] += int((ends & info["target_reached"]).sum())
        ended = np.flatnonzero(term | trunc)
        if len(ended):
            counted = ended[live[ended]]
            c["terminated"] += int(term[counted].sum())
            c["truncated"] += int((trunc[counted] & ~term[counted]).sum())
            close(counted[term[counted]], False)
            close(counted[~term[counted]], True)
            win.close(ended)  # environments past their quota: nothing counts
            done[ended] += 1
            obs, goal = mdp.reset(ended)
            park_balls(env, pool, ended)
            clock[ended], launches[ended], held[ended], touched[ended], fallen[ended] = 0, 0, -1, False, False
    close(np.arange(N), True)

    def rate(a, b):
        return a / b if b else float("nan")

    E = int(episodes)
    out = {"episodes": E, "seconds": c["steps"] / hz, "pool_size": K, "period_s": every / hz,
           "launched": c["launched"], "hits": c["hits"], "hit_rate": rate(c["hits"], c["launched"]),
           "falls": c["falls"], "falls_per_episode": c["falls"] / E,
           "hits_resolved": c["resolved"], "hits_censored": c["censored"], "hits_followed_by_fall": c["hit_falls"],
           "recoveries": c["recoveries"], "recovery_rate": rate(c["recoveries"], c["resolved"]),
           "success": c["truncated"] / E, "terminated_share": c["terminated"] / E,
           "mean_reward": rate(reward, c["steps"]), "diverged": c["diverged"]}
    if c["targets"]:
        out.update(targets=c["targets"], reached_share=c["reached"] / c["targets"])
    return out


@checked(episodes=">= 1", seed=">= 0")
def perturb_run(run, *, episodes: int = 64, seed: int = 0, render=None, cfg: PerturbConfig | None = None) -> dict:
    """``motok control perturb --policy RUN``: the thrown-ball test of a trained task policy, zero-shot:
    the same policy, prior and task, on the run's humanoid with a pool of balls added
    (:func:`motok.sim.balls.build_ball_model`, written next to the run); ``render``: a video of
    environment 0's first episode with the balls and the task's markers. Written to
    ``RUN/perturb.json``, or ``RUN/perturb_periodP.json`` for another period than the paper's."""
    import json
    from dataclasses import asdict, replace
    from pathlib import Path

    from motok.artifacts import Provenance, command_line
    from motok.atomic import write_json
    from motok.control import runs
    from motok.control.highlevel.evaluate import policy_fn
    from motok.control.highlevel.policy import load_task_run, task_mdp
    from motok.sim.balls import build_ball_model
    from motok.sim.env import SimConfig
    from motok.sim.humanoid import load_humanoid

    run = Path(run)
    cfg = replace(cfg or PerturbConfig(), seed=seed)
    tcfg, hum, ac, model, scale, meta = load_task_run(run)
    _, lib = runs.run_library(run, meta, hum, tcfg.env.control_hz)
    balls = load_humanoid(build_ball_model(hum, run / "humanoid_balls.xml", cfg.pool, cfg.radius, cfg.mass))
    sim = SimConfig(**{**asdict(tcfg.env), "num_envs": max(1, min(int(episodes), tcfg.env.num_envs))})
    mdp = task_mdp(tcfg, balls, lib, model, scale, seed, sim)
    frames: list = [] if render is not None else None
    res = {"kind": "control-perturb", "schema_version": 1, "task": tcfg.task,
           **perturb(mdp, policy_fn(ac, tcfg.deterministic_eval), episodes, cfg, frames),
           "config": asdict(cfg), "checkpoint": runs.checkpoint_info(meta)}
    if render is not None:
        from motok.sim.render import render_trajectory
        marks = [m for _, m in frames]
        path, backend = render_trajectory(balls, np.stack([q for q, _ in frames]), render, mdp.env.control_hz,
                                          title=f"{tcfg.task}, balls every {cfg.period:g} s",
                                          markers=np.stack(marks) if marks[0] is not None else None,
                                          marker_radius=mdp.task.marker_radius, marker_rgba=mdp.task.marker_rgba)
        res["video"] = f"{path} ({backend})"
    res["provenance"] = json.loads(Provenance(command=command_line(), config={"run": str(run), "episodes": episodes,
                                                                             "seed": seed}).to_json())
    # another period is another test: its own file, so that the paper's 0.3 s result is not overwritten
    out = run / ("perturb.json" if cfg.period == PerturbConfig().period else f"perturb_period{cfg.period:g}.json")
    write_json(out, res)
    res["written"] = str(out)
    return res
