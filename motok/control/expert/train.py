"""The physics expert of the hybrid-latent paper (appendix B.2): PPO on the imitation task with
``r = w_im r_im + w_style r_style`` (0.5 each in the paper).

* ``r_im``, Eq. 10, the product form of ``motok.control.mdp.rewards`` (the imitation task's
  reward, ``motok.control.tasks.imitation``);
* ``r_style``, Eq. 11: the AMP discriminator of ``motok.control.rl.amp``, a reward hook of the
  rollout collector (with ``amp.feet`` it also sees the soles);
* with ``w_action_rate > 0`` (not in the paper; 0 by default) the additive smoothness term
  ``w_action_rate r_action_rate`` (``motok.control.mdp.rewards.action_rate``).

The trainer only composes parts: physics (``HumanoidEnv``), the imitation task, the action map
(residual PD targets), the encoder-decoder policy (``motok.control.expert.model``), the collector
and PPO; the runner (``motok.control.rl.runner``) does the rest. Training saves a bundle (kind ``control-expert``)
every ``save_every`` iterations with the MJCF (``RUN/humanoid.xml``) and its hash, the
observation/action spec, the normaliser statistics, and everything needed to resume exactly:
optimisers, replay buffer, torch/numpy/task RNG states.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch

from motok.control import runs
from motok.control.expert.model import KIND, ExpertConfig, build_actor_critic
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.task_env import TaskEnv
from motok.control.rl import runner
from motok.control.rl.amp import AMP, AMPHook, SoleObservation, reference_observations
from motok.control.rl.ppo import PPO
from motok.control.rl.rollout import Collector
from motok.control.rl.sampling import DifficultySampler, failures
from motok.control.tasks.imitation import (ImitationTask, ImitationTaskConfig, eval_metrics, evaluate, subset,
                                          summarise)
from motok.config import from_dict
from motok.data.dataset import select_clips
from motok.distributed import Dist, gather
from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import Humanoid, HumanoidConfig, config_difference, load_humanoid
from motok.sim.reference import ReferenceLibrary


def imitation_mdp(hum: Humanoid, lib: ReferenceLibrary, sim: SimConfig, task: ImitationTaskConfig,
                  action: ActionConfig, seed: int) -> TaskEnv:
    """The imitation MDP; with ``sim.on_device`` its library, episode state and start draws (a
    seeded ``torch.Generator``) live on the physics device too."""
    env = HumanoidEnv(hum, sim)
    if env.on_device:
        lib = lib.to(env.torch_device)
        rng = torch.Generator(device=env.torch_device).manual_seed(seed)
    else:
        rng = np.random.default_rng(seed)
    return TaskEnv(env, ImitationTask(task, env, lib, rng), partial(pd_targets, action))


class ExpertTrainer:
    """PPO + AMP on the imitation task; one ``step`` is one collect-and-update iteration."""

    def __init__(self, cfg: ExpertConfig, hum: Humanoid, lib: ReferenceLibrary, d: Dist | None = None):
        d = d or Dist()
        self.cfg = cfg
        torch.manual_seed(cfg.seed)  # the same initial weights on every rank (the runner reseeds ranks > 0 after)
        seed = runner.rank_seed(cfg.seed, d.rank)
        self.amp_rng = np.random.default_rng(seed + 1)
        self.hum, self.lib = hum, lib
        G = cfg.env.groups
        if G < 1 or cfg.env.num_envs % G:
            raise UserError(f"env.groups must divide env.num_envs ({cfg.env.num_envs}), not {G}")
        part = replace(cfg.env, num_envs=cfg.env.num_envs // G)
        # Group 0 keeps the single-group streams, so groups: 1 is the plain sequential rollout.
        self.mdps = [imitation_mdp(hum, lib, part, cfg.task, cfg.action, seed + 7919 * g) for g in range(G)]
        self.mdp = m = self.mdps[0]
        device = m.env.torch_device if m.env.on_device else None  # networks and buffers where the rollout is
        self.ac = build_actor_critic(cfg.net, m.obs_dim, m.goal_dim, m.action_dim).to(device)
        self.ppo = PPO(self.ac, cfg.ppo, cfg.iterations)
        use_amp = cfg.amp.enabled and cfg.w_style != 0
        sole = SoleObservation(hum) if use_amp and cfg.amp.feet else None  # the discriminator sees the soles
        self.amp = AMP(cfg.amp, reference_observations(lib, m.env.end_effectors, sole), lib.starts, device) \
            if use_amp else None
        hooks = (AMPHook(self.amp, cfg.w_style, self.amp_rng),) if self.amp else ()
        self.collector = Collector(self.mdps, self.ac, cfg.ppo.horizon, cfg.w_im, hooks,
                                   action_rate=cfg.w_action_rate, hook_obs=sole)
        self.samples_per_iteration = cfg.ppo.horizon * self.collector.num_envs * d.world
        self.iteration, self.samples, self.wall = 0, 0, 0.0
        self.dist = d
        self.sampler = DifficultySampler(cfg.sampling, np.maximum(lib.lengths - (cfg.task.goal_frames + 1), 0))

    # ------------------------------------------------------------------ state
    def model_state(self) -> dict[str, torch.Tensor]:
        st = {f"ac.{k}": v for k, v in self.ac.state_dict().items()}
        if self.amp is not None:
            st.update({f"disc.{k}": v for k, v in self.amp.disc.state_dict().items()})
        return st

    def train_state(self) -> dict:
        ts = {**runner.counters(self), "ppo_opt": self.ppo.opt.state_dict(), "sampler": self.sampler.state()}
        if self.amp is not None:
            ts["amp_opt"] = self.amp.opt.state_dict()
        return ts

    def rank_state(self) -> dict:
        rs = {**runner.task_rng_state(self.mdp), "amp_rng": runner.generator_state(self.amp_rng),
              "group_task_rngs": [runner.generator_state(m.task.rng) for m in self.mdps[1:]]}
        if self.amp is not None:
            rs["replay"] = self.amp.replay.state()
        return rs

    def load(self, model: dict, shared: dict | None, rank: dict | None) -> None:
        self.ac.load_state_dict(runs.split_state(model, "ac."))
        if self.amp is not None:
            self.amp.disc.load_state_dict(runs.split_state(model, "disc."))
        if shared is None:
            return
        runner.load_counters(self, shared)
        self.ppo.opt.load_state_dict(shared["ppo_opt"])
        self.sampler.load(shared["sampler"])
        self._set_clip_p()
        runner.load_task_rng(self.mdp, rank)
        for m, st in zip(self.mdps[1:], rank.get("group_task_rngs", [])):
            runner.load_generator(m.task.rng, st)
        runner.load_generator(self.amp_rng, rank["amp_rng"])
        if self.amp is not None:
            self.amp.opt.load_state_dict(shared["amp_opt"])
            self.amp.replay.load(rank["replay"])

    def start_segment(self) -> None:
        self.collector.start()

    # ------------------------------------------------------------------ one iteration
    def step(self) -> dict:
        stats = runner.timed_step(self, self.collector.collect, lambda ro, last_value: {
            **self.collector.update_hooks(), **self.ppo.update(ro, last_value, self.iteration)})
        if self.sampler.due(self.iteration):
            t2 = time.perf_counter()
            stats.update(self.measure_difficulty())
            self.wall += time.perf_counter() - t2
            stats.update(wall_s=round(self.wall, 2), difficulty_s=time.perf_counter() - t2)
        return stats

    def _set_clip_p(self) -> None:
        for m in self.mdps:
            m.task.clip_p = self.sampler.probabilities()

    def measure_difficulty(self) -> dict:
        """Every training clip from frame 0 (each rank a share), then new start-clip probabilities."""
        c, d, lib = self.cfg, self.dist, self.lib
        mine = np.arange(d.rank, len(lib), d.world)
        res = evaluate(self.hum, self.ac, lib, c.env, c.task, c.action, batch=c.sampling.eval_batch, clips=mine)
        per = {k: v for part in gather(res["clips"], d) for k, v in part.items()}
        stats = self.sampler.update(failures(per, lib.names), self.iteration)
        self._set_clip_p()
        o = summarise(per)
        stats.update(train_mpjpe_mm=o["mpjpe_mm"], train_seconds=o["seconds_played"] / len(per))
        return stats

    def spec(self) -> dict:
        e, hum = self.mdp.env, self.hum
        m = hum.model
        return {"obs_dim": e.obs_dim, "goal_dim": self.mdp.goal_dim, "action_dim": e.action_dim,
                "action": {"kind": "residual PD target offsets (rad): q_hat = base + scale * a",
                           "base": self.cfg.action.base, "scale": self.cfg.action.scale,
                           "actuators": list(hum.layout.hinge_names), "ctrl_range": m.actuator_ctrlrange.tolist()},
                "observation": "Eq. 7 s (heading frame) then Eq. 9 goal, normalised by ac.norm.{mean,var,count}",
                "normaliser": ["ac.norm.mean", "ac.norm.var", "ac.norm.count"], "control_hz": e.control_hz,
                # the discriminator's input per state: Eq. 7, plus 4 with amp.feet (0: no discriminator)
                "amp_obs_dim": int(self.amp.ref.shape[1]) if self.amp is not None else 0,
                "clips": list(self.lib.names)}


def train(cfg: ExpertConfig, run, hum: Humanoid, lib: ReferenceLibrary, *, resume: bool = False,
          until: int | None = None, data=None, command: str | None = None, init=None) -> dict:
    """Train (or resume) an expert into ``run``; stops after ``until`` iterations if given.
    ``init``: an expert run whose weights (policy, critic, normaliser, discriminator) a new run
    starts from, with fresh optimisers, counters and schedules (a warm start, e.g. from an expert
    of a subset of the clips); recorded in the bundle. A resumed run ignores it."""
    names = subset(lib.names, cfg.eval_per_group) if cfg.eval_per_group else list(lib.names)
    ids = np.array([lib.index(n) for n in names])

    def eval_hook(tr: ExpertTrainer) -> dict:
        return eval_metrics(evaluate(hum, tr.ac, lib, cfg.env, cfg.task, cfg.action, clips=ids,
                                     batch=cfg.sampling.eval_batch, feet=True))

    start, extra = None, {}
    if init is not None:
        meta, start, ihum = runs.load_run(init, KIND)
        if runs.mjcf_hash(ihum) != runs.mjcf_hash(hum):
            raise UserError(f"--init {init}: that expert was trained on another humanoid (MJCF hash differs)")
        saw = bool(meta["config"].get("amp", {}).get("feet", False))
        # only a discriminator carried over must see what it saw; a run without one loads none
        if "disc.mean" in start and cfg.amp.enabled and cfg.w_style != 0 and saw != cfg.amp.feet:
            raise UserError(f"--init {init}: its discriminator was trained with amp.feet={str(saw).lower()}, this "
                            f"recipe has amp.feet={str(cfg.amp.feet).lower()} (another input size); set it to match")
        extra = runs.link_record("init", init, KIND)

    def make(d: Dist) -> ExpertTrainer:
        tr = ExpertTrainer(cfg, hum, lib, d)
        if start is not None:
            try:
                tr.load(start, None, None)
            except RuntimeError as e:  # shapes: other networks or observation sizes
                raise UserError(f"--init {init}: its networks do not fit this recipe ({str(e).splitlines()[0]})")
        return tr

    return runner.train(make, cfg, run, hum, kind=KIND, resume=resume, until=until, data=data, command=command,
                        evaluate=eval_hook, label="expert", extra=extra)


def train_from_data(cfg: ExpertConfig, data, run, *, clips: str | None = None, split: str | None = None,
                    humanoid=None, resume: bool = False, until: int | None = None, init=None) -> dict:
    """``motok control expert train``: the humanoid (the run's own on resume, else ``humanoid`` or
    the one built from ``data``, cached), the reference library of the chosen clips, then :func:`train`."""
    from motok.sim.reference import humanoid_for, load_library

    run = Path(run)
    if resume and (run / "humanoid.xml").exists():
        hum = load_humanoid(run / "humanoid.xml")
        built = hum.meta.get("config", {})
        # as the MJCF's metadata stores it (JSON: tuples are lists); older builds lack newer fields
        wanted = {k: v for k, v in json.loads(json.dumps(asdict(cfg.humanoid))).items() if k in built}
        if humanoid is None and wanted != {k: built[k] for k in wanted}:
            what = ", ".join(f"{k}: {built[k]} -> {v}" for k, v in wanted.items() if built[k] != v)
            raise UserError(f"{run} was trained on another humanoid than the recipe's humanoid section asks "
                            f"for ({what}); resume with the recipe it was trained with, or train a new run")
        if humanoid is not None:  # a resume continues in the run's world, never silently in another
            other = load_humanoid(humanoid)
            if runner.mjcf_hash(other) != runner.mjcf_hash(hum):
                what = config_difference(hum, other) or "its geometry or gains"
                raise UserError(f"--humanoid {humanoid}: {run} was trained on another humanoid ({what}); "
                                "resume without --humanoid, or train a new run on it")
    elif init is not None:  # the warm start's humanoid, so its weights mean the same joints
        hum = load_humanoid(Path(init) / "humanoid.xml")
    else:
        hum = load_humanoid(humanoid) if humanoid else humanoid_for(data, cfg=cfg.humanoid)
    if humanoid is not None or init is not None:  # the bundle records the world the run really has
        cfg.humanoid = from_dict(HumanoidConfig, {k: v for k, v in hum.meta.get("config", {}).items()
                                                  if k in HumanoidConfig.__dataclass_fields__})
    lib = load_library(hum, data, control_hz=cfg.env.control_hz, clips=select_clips(data, clips, split))
    return train(cfg, run, hum, lib, resume=resume, until=until, data=data, init=init)
