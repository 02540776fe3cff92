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

from dataclasses import replace
from pathlib import Path

import torch

from motok.config import checked, from_dict
from motok.control import runs
from motok.control.highlevel.evaluate import evaluate_policy
from motok.control.highlevel.policy import (KIND, TaskTrainConfig, action_space, build_high_level, task_codebooks,
                                            task_mdp)
from motok.control.priors.model import KIND as PRIOR_KIND
from motok.control.priors.model import DistillConfig, LatentPrior, load_prior
from motok.control.rl import runner
from motok.control.rl.ppo import PPO, PPOConfig
from motok.control.rl.rollout import Collector
from motok.control.tasks import registry
from motok.distributed import Dist
from motok.errors import UserError
from motok.sim.env import SimConfig
from motok.sim.humanoid import Humanoid
from motok.sim.reference import ReferenceLibrary

BAR = (("ret", "episode_return", "{:.1f}"), ("len", "episode_seconds", "{:.2f}s"), ("r", "r_task", "{:.3f}"))
SUMMARY = ("episode_return", "episode_seconds", "r_task", "samples_per_s")


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
        self.ppo = PPO(self.ac, ppo_config(cfg, model), cfg.iterations)
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
        self.ac.load_state_dict(runs.split_state(model, "ac."))
        if shared is not None:
            runner.load_shared(self, shared, rank, ppo_opt=self.ppo.opt)

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
        return runner.timed_step(self, self.collector.collect,
                                 lambda ro, last_value: self.ppo.update(ro, last_value, self.iteration))


def ppo_config(cfg: TaskTrainConfig, model: LatentPrior) -> PPOConfig:
    """``cfg.ppo``, with ``cfg.continuous_lr`` as the learning rate over the continuous prior."""
    if model.quantizer is None and cfg.continuous_lr is not None:
        return replace(cfg.ppo, lr=cfg.continuous_lr)
    return cfg.ppo


def resolve_codebooks(cfg: TaskTrainConfig, run, model: LatentPrior, resume: bool) -> None:
    """Put the active codebooks in ``cfg`` before the run saves it: a resumed run's own (its saved
    config's; None there, from before defaults were resolved, meant all), else the task's paper
    default when the recipe leaves them out (:func:`task_codebooks`)."""
    saved = runs.resumed_meta(run, KIND, resume)
    if saved is not None:
        if cfg.codebooks is None:
            cfg.codebooks = saved["config"].get("codebooks")
        return
    cfg.codebooks = task_codebooks(model, cfg.task, cfg.codebooks)


def train(cfg: TaskTrainConfig, run, prior_run, lib: ReferenceLibrary, *, resume: bool = False,
          until: int | None = None, data=None, command: str | None = None) -> dict:
    """Train (or resume) a high-level policy for ``cfg.task`` over the prior in ``prior_run``."""
    pcfg, hum, model, _ = load_prior(prior_run)
    cfg.check()
    resolve_codebooks(cfg, run, model, resume)
    cfg.env.same_world(pcfg.env, f"the prior {prior_run}", hum.control_hz)

    def eval_hook(tr: TaskTrainer) -> dict:
        res = evaluate_policy(cfg, hum, lib, model, pcfg.action.scale, tr.ac, cfg.eval_episodes, cfg.seed + 12345)
        return {f"eval_{k}": float(v) for k, v in res.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}

    return runner.train(lambda d: TaskTrainer(cfg, hum, lib, pcfg, model, d), cfg, run, hum, kind=KIND,
                        resume=resume, until=until, data=data, command=command,
                        extra=runs.link_record("prior", prior_run, PRIOR_KIND), evaluate=eval_hook,
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
        checked(cfg)  # the option's range is the field's: task learning chooses codes in at least one codebook
    cfg.check()  # a task named in the recipe or --set is known before anything is loaded
    prior_run, run = Path(prior_run), Path(run)
    saved = runs.resumed_meta(run, KIND, resume)
    if saved is not None and saved["extra"]["task"] != cfg.task:
        raise UserError(f"{run} holds a {saved['extra']['task']!r} policy; cannot resume it as {cfg.task!r}")
    pmeta, _, hum = runs.load_run(prior_run, PRIOR_KIND)
    # The prior's world (control rate, target filter) unless the recipe sets it, another refused
    # before the library is built at that rate; train() holds it again for callers from Python.
    cfg.env.same_world(from_dict(SimConfig, pmeta["config"]["env"]), f"the prior {prior_run}", hum.control_hz)
    src, lib = runs.run_library(prior_run, pmeta, hum, cfg.env.control_hz, data, clips, split)
    return train(cfg, run, prior_run, lib, resume=resume, until=until, data=src)
