"""Task learning over a frozen latent prior (hybrid-latent paper section 6.3, appendix C, Tables
6-8): ``motok control train --task navigation|inbetween|hmd --prior PRIOR``.

PPO (``motok.control.rl.ppo``, the same update as the expert's) trains the high-level policy of
``motok.control.highlevel.policy`` on a task of ``motok.control.tasks`` with the task's reward alone;
the prior's decoder turns each high-level action into PD targets and is never trained. The
defaults follow Tables 6-8 where this machine allows (clip 0.1, lr 5e-5, horizon 16, gamma 0.99,
lambda 0.95); the network and batch sizes are the CPU recipe's.

The runner (``motok.control.rl.runner``) does seeding, checkpoints, exact resume, metrics,
provenance and the MJCF hash; the bundle (kind ``control-task``) links the prior it was trained
over (relative and absolute path, weights hash) and records the task, its config and the
high-level action space.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.atomic import write_json
from motok.checkpoint import read_meta, register_kind
from motok.config import from_dict
from motok.control.rl import runner
from motok.control.priors.distill import KIND as PRIOR_KIND
from motok.control.priors.distill import DistillConfig, load_prior, split_state
from motok.control.tasks.imitation_eval import policy_device
from motok.control.priors.generate import check_codebooks
from motok.control.highlevel.policy import HighLevelNetConfig, LatentActionMap, action_space, build_high_level
from motok.control.tasks.nav_eval import idle_matching
from motok.control.rl.networks import ActorCritic
from motok.control.rl.ppo import PPO, PPOConfig
from motok.control.priors.model import LatentPrior
from motok.control.rl.rollout import Collector, as_tensor
from motok.control.tasks import registry
from motok.control.mdp.task_env import TaskEnv
from motok.distributed import Dist
from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import Humanoid
from motok.sim.reference import ReferenceLibrary

KIND = "control-task"
register_kind(KIND, (1,))
BAR = (("ret", "episode_return", "{:.1f}"), ("len", "episode_seconds", "{:.2f}s"), ("r", "r_task", "{:.3f}"))
SUMMARY = ("episode_return", "episode_seconds", "r_task", "samples_per_s")


def paper_ppo() -> PPOConfig:
    """Tables 6-8: clip 0.1, lr 5e-5, horizon 16, gamma 0.99, lambda 0.95."""
    return PPOConfig(horizon=16, epochs=6, minibatch_size=1024, gamma=0.99, lam=0.95, clip=0.1, lr=5e-5,
                     entropy_coef=0.01, max_grad_norm=1.0)


@dataclass
class TaskTrainConfig:
    seed: int = 0
    iterations: int = 2000
    task: str = "navigation"  # one of motok.control.tasks.registry.TASKS
    codebooks: int | None = None  # active codebooks M of a residual prior (None: all)
    save_every: int = 50
    eval_every: int = 0  # iterations between task evaluations logged as eval_* (0: never)
    eval_episodes: int = 64
    deterministic_eval: bool = True  # evaluate with the most likely action (argmax codes, the mean offset)
    torch_threads: int = 1  # during rollouts: MuJoCo has the cores
    update_threads: int = 0  # during the PPO update (0: torch_threads)
    env: SimConfig = field(default_factory=lambda: SimConfig(num_envs=128))
    tasks: registry.TaskConfigs = field(default_factory=registry.TaskConfigs)
    ppo: PPOConfig = field(default_factory=paper_ppo)
    net: HighLevelNetConfig = field(default_factory=HighLevelNetConfig)

    def check(self) -> None:
        registry.check(self.task)


def task_mdp(cfg: TaskTrainConfig, hum: Humanoid, lib: ReferenceLibrary, model: LatentPrior, scale: float,
             seed: int, sim: SimConfig | None = None) -> TaskEnv:
    """Physics + the task + the frozen prior's decoder as the action map."""
    env = HumanoidEnv(hum, sim or cfg.env)
    if env.on_device:  # the library, the episode state and the draws where the physics is
        lib, rng = lib.to(env.torch_device), torch.Generator(device=env.torch_device).manual_seed(seed)
    else:
        rng = np.random.default_rng(seed)
    task = registry.make(cfg.task, cfg.tasks, env, lib, rng)
    return TaskEnv(env, task, LatentActionMap(model, check_codebooks(model, cfg.codebooks), scale))


class TaskTrainer:
    """PPO on a task through the frozen prior; one ``step`` is one collect-and-update iteration."""

    def __init__(self, cfg: TaskTrainConfig, hum: Humanoid, lib: ReferenceLibrary, prior_cfg: DistillConfig,
                 model: LatentPrior, d: Dist | None = None):
        d = d or Dist()
        cfg.check()
        self.cfg, self.hum, self.lib, self.model = cfg, hum, lib, model
        torch.manual_seed(cfg.seed)
        self.mdp = m = task_mdp(cfg, hum, lib, model, prior_cfg.action.scale, runner.rank_seed(cfg.seed, d.rank))
        device = m.env.torch_device if m.env.on_device else None  # policy, frozen prior and buffers there
        model.to(device)
        self.ac = build_high_level(cfg.net, model, m.obs_dim, m.goal_dim, cfg.codebooks).to(device)
        self.ppo = PPO(self.ac, cfg.ppo, cfg.iterations)
        self.collector = Collector(m, self.ac, cfg.ppo.horizon)
        self.samples_per_iteration = cfg.ppo.horizon * m.num_envs * d.world
        self.iteration, self.samples, self.wall = 0, 0, 0.0

    def model_state(self) -> dict[str, torch.Tensor]:
        return {f"ac.{k}": v for k, v in self.ac.state_dict().items()}

    def train_state(self) -> dict:
        return {**runner.counters(self), "ppo_opt": self.ppo.opt.state_dict()}

    def rank_state(self) -> dict:
        return runner.task_rng_state(self.mdp)

    def load(self, model: dict, shared: dict | None, rank: dict | None) -> None:
        self.ac.load_state_dict(split_state(model, "ac."))
        if shared is None:
            return
        runner.load_counters(self, shared)
        self.ppo.opt.load_state_dict(shared["ppo_opt"])
        runner.load_task_rng(self.mdp, rank)

    def start_segment(self) -> None:
        self.collector.start()

    def spec(self) -> dict:
        e = self.mdp.env
        return {"obs_dim": e.obs_dim, "goal_dim": self.mdp.goal_dim, "task": self.cfg.task,
                "high_level_action": action_space(self.model, self.cfg.codebooks),
                "observation": "Eq. 7 s then the task goal, normalised by ac.norm.{mean,var,count}",
                "normaliser": ["ac.norm.mean", "ac.norm.var", "ac.norm.count"], "control_hz": e.control_hz,
                "clips": list(self.lib.names)}

    def step(self) -> dict:
        t0 = time.perf_counter()
        ro, last_value, stats = self.collector.collect()
        t1 = time.perf_counter()
        with runner.torch_threads(self.cfg.update_threads or self.cfg.torch_threads):
            stats.update(self.ppo.update(ro, last_value, self.iteration))
        return runner.finish_step(self, stats, t0, t1)


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
        if hasattr(one.task, "set_keyframe_count"):  # in-betweening: the video shows the evaluated keyframe count
            one.task.set_keyframe_count(one.task.cfg.eval_keyframes)  # render_episode resets first
        res["video"] = render_episode(one, act, render, f"{cfg.task} over the {model.kind} prior")
    return res


def render_episode(mdp: TaskEnv, act, out, title: str) -> str:
    """One episode of a 1-environment ``mdp`` to a video, the task's ``markers()`` drawn if it has them."""
    from motok.sim.render import render_trajectory

    obs, goal = mdp.reset()
    qpos, marks = [mdp.env.qpos[0].copy()], []
    markers = getattr(mdp.task, "markers", None)
    if markers is not None:
        marks.append(markers()[0])
    while True:
        obs, goal, _, term, trunc, _ = mdp.step(act(obs, goal))
        qpos.append(mdp.env.qpos[0].copy())
        if markers is not None:
            marks.append(markers()[0])
        if term[0] or trunc[0]:
            break
    path, backend = render_trajectory(mdp.env.hum, np.stack(qpos), out, mdp.env.control_hz, title=title,
                                      markers=np.stack(marks) if marks else None,
                                      marker_radius=getattr(mdp.task, "marker_radius", 0.12))
    return f"{path} ({backend})"


def train(cfg: TaskTrainConfig, run, prior_run, lib: ReferenceLibrary, *, resume: bool = False,
          until: int | None = None, data=None, command: str | None = None) -> dict:
    """Train (or resume) a high-level policy for ``cfg.task`` over the prior in ``prior_run``."""
    pcfg, hum, model, _ = load_prior(prior_run)
    cfg.check()
    if cfg.env.control_hz is None:
        cfg.env.control_hz = pcfg.env.control_hz
    cfg.env.same_world(pcfg.env, f"the prior {prior_run}")

    def eval_hook(tr: TaskTrainer) -> dict:
        res = evaluate_policy(cfg, hum, lib, model, pcfg.action.scale, tr.ac, cfg.eval_episodes, cfg.seed + 12345)
        return {f"eval_{k}": float(v) for k, v in res.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}

    return runner.train(lambda d: TaskTrainer(cfg, hum, lib, pcfg, model, d), cfg, run, hum, kind=KIND,
                        resume=resume, until=until, data=data, command=command,
                        extra=runner.link_record("prior", prior_run, PRIOR_KIND), evaluate=eval_hook,
                        label=f"{cfg.task} over {model.kind}", fields=BAR, summary_keys=SUMMARY)


def train_from_prior(cfg: TaskTrainConfig, prior_run, run, *, task: str | None = None, codebooks: int | None = None,
                     data=None, clips: str | None = None, split: str | None = None, resume: bool = False,
                     until: int | None = None) -> dict:
    """``motok control train``: the task and codebooks (command line over recipe), the prior's
    humanoid and its clips (or those of ``data`` matching ``clips``/``split``) as the start
    states and references, then :func:`train`."""
    if task is not None:
        registry.check(task)
        cfg.task = task
    if codebooks is not None:
        cfg.codebooks = codebooks
    prior_run, run = Path(prior_run), Path(run)
    if resume and (run / "bundle.json").exists():
        saved = read_meta(run, KIND)["extra"]["task"]
        if saved != cfg.task:
            raise UserError(f"{run} holds a {saved!r} policy; cannot resume it as {cfg.task!r}")
    pmeta, _, hum = runner.load_run(prior_run, PRIOR_KIND)
    hz = cfg.env.control_hz or pmeta["config"]["env"]["control_hz"]
    src, lib = runner.run_library(prior_run, pmeta, hum, hz, data, clips, split)
    return train(cfg, run, prior_run, lib, resume=resume, until=until, data=src)


def load_task_run(run) -> tuple[TaskTrainConfig, Humanoid, ActorCritic, LatentPrior, float, dict]:
    """``(cfg, humanoid, high-level actor-critic, frozen prior, prior action scale, meta)``."""
    run = Path(run)
    meta, state, hum = runner.load_run(run, KIND)
    cfg = from_dict(TaskTrainConfig, meta["config"])
    cfg.env.portable()  # trained on a GPU or not, used on C MuJoCo unless told otherwise
    pcfg, phum, model, _ = load_prior(runner.linked_path(run, meta, "prior"))
    if runner.mjcf_hash(phum) != meta["extra"]["mjcf_sha256"]:
        raise UserError(f"{run}: its prior now has another humanoid than the one the policy was trained on")
    ex = meta["extra"]
    ac = build_high_level(cfg.net, model, ex["obs_dim"], ex["goal_dim"], cfg.codebooks)
    ac.load_state_dict(split_state(state, "ac."))
    return cfg, hum, ac, model, pcfg.action.scale, meta


def evaluate_run(run, *, episodes: int = 256, seed: int = 0, data=None, clips: str | None = None,
                 split: str | None = None, render=None, device: str | None = None, task: str | None = None) -> dict:
    """``motok control eval --task T --run RUN``: the task's evaluation of the policy in ``run``
    on ``episodes`` episodes (start states from its clips, or those of ``data`` / ``clips`` /
    ``split``), written to ``RUN/eval_TASK[_SPLIT].json`` with the checkpoint and provenance.
    ``task``, when given, must be the run's (checked before any work)."""
    run = Path(run)
    cfg, hum, ac, model, scale, meta = load_task_run(run)
    if task is not None and task != cfg.task:
        raise UserError(f"{run} is a {cfg.task!r} policy, not {task!r}")
    cfg.env.on(device)
    src, lib = runner.run_library(run, meta, hum, cfg.env.control_hz, data, clips, split)
    res = evaluate_policy(cfg, hum, lib, model, scale, ac, episodes, seed, render=render)
    idle = res.pop("idle_bodies", None)
    if idle is not None:  # navigation: how data-like the motion at the target is (issue 16)
        mm = res["idle_motion_matching"] = idle_matching(idle, src, lib.names, lib.fps)
        res.update({f"idle_{k}": mm[k] for k in ("transitions", "distance_mean", "filtered_rate")})
    res = {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in res.items()}  # JSON: per-step arrays as lists
    res = {"kind": "control-task-eval", "schema_version": 1, "task": cfg.task, "episodes": episodes, **res,
           "checkpoint": {**runner.checkpoint_info(meta), "prior": meta["extra"]["prior_info"],
                          "high_level_action": meta["extra"]["high_level_action"]}}
    prov = Provenance(command=command_line(), config={"run": str(run), "episodes": episodes, "seed": seed,
                                                        "clips": clips, "split": split},
                      inputs=hash_inputs([src]))
    res["provenance"] = json.loads(prov.to_json())
    path = run / (f"eval_{cfg.task}" + (f"_{split}" if split else "") + ".json")
    write_json(path, res)
    res["written"] = str(path)
    return res
