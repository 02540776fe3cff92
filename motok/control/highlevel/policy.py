"""The high-level policy of task learning over a frozen latent prior (hybrid-latent paper section
5 / 6.3, appendix C, Tables 6-8).

The prior's decoder ``pi_low(s, z_bar)`` is frozen; a new policy ``pi_high(s, g)`` reads the
proprioception ``s`` (Eq. 7) and the task goal ``g`` and chooses the latent:

* ``discrete``, ``hybrid-vq``: one categorical over the codebook;
* ``discrete+``, ``hybrid``: one categorical per active codebook (the first ``M``: the task's
  paper default, Tables 6-8, unless the run gives ``codebooks``), independent given the input;
  ``z_bar`` is the sum of the chosen codes, plus ``z_p(s)`` for the hybrid (section 4.1: the codes
  are codes of the margin to the prior);
* ``continuous``: a Gaussian offset ``u`` with a fixed exploration std (``net.std``, 0.04 as the
  authors' code fixes it; the paper's Fig. 4 right shows the result depends on it),
  ``z = mu_p(s) + u`` (Eq. 2's prior mean);
* ``hybrid-grvq``: one categorical per (group, active codebook): ``G * M`` heads;
* ``hybrid-fsq``: one categorical per channel of the first M channel groups, its levels as
  classes (``M * C`` heads of L classes); the chosen levels are the margin's code;
* ``hybrid-parts``: one network per body part (:mod:`motok.control.highlevel.heads`), each with a
  categorical per active codebook of its part, so a later task can drive the parts with two goals.

Every head is a column of the prior's code indices (``LatentPrior.columns``), in its order.

The environment sees the decoder's action: :class:`LatentActionMap` is the action map of
``motok.control.mdp.task_env.TaskEnv`` that turns the high-level action into PD targets on the
current pose (``q_hat = q + scale pi_low(s, z_bar)``, how the prior was distilled). PPO optimises
the high-level policy only; the prior's weights never receive a gradient (they are not in the
optimiser, and the map runs under ``no_grad``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from motok.checkpoint import register_kind
from motok.control import runs
from motok.control.highlevel.heads import PartCategoricalPolicy
from motok.control.mdp.actions import residual_targets
from motok.control.mdp.task_env import TaskEnv
from motok.control.priors.load import check_codebooks
from motok.control.priors.model import LatentPrior, load_prior
from motok.control.priors.parts import PART_NAMES
from motok.control.rl.networks import ActorCritic, RunningNorm, ValueNet
from motok.control.rl.policies import MLPPolicy, MultiCategoricalPolicy
from motok.control.rl.ppo import PPOConfig
from motok.control.tasks import registry
from motok.errors import UserError
from motok.ranges import In
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import Humanoid
from motok.sim.reference import ReferenceLibrary

KIND = "control-task"
register_kind(KIND, (1,))


@dataclass
class HighLevelNetConfig:
    # hidden sizes of the high-level policy's MLP
    policy: In[list[int], ">= 1"] = field(default_factory=lambda: [256, 256])
    value: In[list[int], ">= 1"] = field(default_factory=lambda: [256, 256])  # hidden sizes of the critic's MLP
    activation: str = "elu"  # relu | elu | tanh | silu
    # Continuous prior: the fixed exploration std of the offset u. 0.04, the value the authors' released
    # continuous task recipe fixes (log std -3.2) after the sensitivity Fig. 4 (right) shows; 0.2 and
    # 0.1 are what motok measured before (docs/history.md): --set net.std=0.2
    std: In[float, "> 0"] = 0.04


class LatentActionMap:
    """``(actions, env, task) -> PD targets``: high-level actions decoded by the frozen prior.

    ``actions`` are code indices ``(N, M)`` (int) for the quantized kinds or offsets ``(N, D)``
    for the continuous prior. ``scale`` is the prior's action scale (its distillation recipe's
    ``action.scale``)."""

    def __init__(self, model: LatentPrior, codebooks: int, scale: float):
        self.model, self.codebooks, self.scale = model.eval().requires_grad_(False), codebooks, float(scale)

    @torch.no_grad()
    def latent(self, sn: torch.Tensor, actions) -> torch.Tensor:
        """``z_bar`` for normalised observations ``sn`` and high-level actions."""
        m = self.model
        if m.quantizer is None:
            return m.offset_to_latent(sn, torch.as_tensor(actions, dtype=torch.float32, device=sn.device))
        return m.codes_to_latent(sn, torch.as_tensor(actions, dtype=torch.int64, device=sn.device), self.codebooks)

    @torch.no_grad()
    def __call__(self, actions, env, task):
        m = self.model
        device = next(m.parameters()).device  # the prior's; the environment's arrays may be host or device
        sn = m.norm_obs(torch.as_tensor(env.observation(), dtype=torch.float32, device=device))
        a = m.decode(sn, self.latent(sn, actions))
        return residual_targets(a if env.on_device else a.cpu().numpy(), env.qpos[:, env.hinge_adr], self.scale)


def action_space(model: LatentPrior, codebooks: int | None) -> dict:
    """What the high-level policy chooses: ``{"kind", "codebooks", "heads", "codes"[, "parts"]}``
    (``heads`` categoricals of ``codes`` classes each; ``parts``: heads per body part) or
    ``{"kind", "codebooks", "latent_dim"}`` for the continuous prior."""
    m = check_codebooks(model, codebooks)
    if model.quantizer is None:
        return {"kind": "gaussian offset u, z = mu_p(s) + u", "codebooks": 0, "latent_dim": model.cfg.latent_dim}
    space = {"kind": "code indices, one categorical per index column", "codebooks": m, "heads": model.columns(m),
             "codes": model.quantizer.codebook_size}
    if model.caps.parts:
        groups = model.quantizer.column_groups(m)
        space["parts"] = {n: int((groups == g).sum()) for g, n in enumerate(PART_NAMES)}
    return space


def build_high_level(net: HighLevelNetConfig, model: LatentPrior, obs_dim: int, goal_dim: int,
                     codebooks: int | None) -> ActorCritic:
    """Normaliser + policy + value on ``[s, g]``; the policy's action space follows the prior."""
    if goal_dim < 1:
        raise UserError("a task for the high-level policy needs a goal (goal_dim >= 1)")
    if model.obs_dim != obs_dim:
        raise UserError(f"the prior reads {model.obs_dim} observation entries, the task's humanoid gives {obs_dim}")
    space = action_space(model, codebooks)
    d = obs_dim + goal_dim
    if model.quantizer is None:
        if net.std <= 0:
            raise UserError(f"net.std must be positive, not {net.std}")
        pol = MLPPolicy(d, model.cfg.latent_dim, tuple(net.policy), net.activation, math.log(net.std), False)
    elif "parts" in space:
        pol = PartCategoricalPolicy(d, model.quantizer.column_groups(space["codebooks"]), space["codes"], PART_NAMES,
                                    tuple(net.policy), net.activation)
    else:
        pol = MultiCategoricalPolicy(d, space["heads"], space["codes"], tuple(net.policy), net.activation)
    return ActorCritic(RunningNorm(d), pol, ValueNet(d, tuple(net.value), net.activation))


def task_codebooks(model: LatentPrior, task: str, codebooks: int | None) -> int | None:
    """The ``codebooks`` a new run of ``task`` over ``model`` uses: ``codebooks`` when given, else
    the task's paper default (``TaskSpec.codebooks``, at most the prior's; all where the task has
    none); None for the continuous prior, which has no codebooks."""
    if codebooks is not None or model.quantizer is None:
        return codebooks
    default = registry.spec(task).codebooks
    return model.num_codebooks if default is None else min(default, model.num_codebooks)


def paper_ppo() -> PPOConfig:
    """Tables 6-8: clip 0.1, lr 5e-5, horizon 16, gamma 0.99, lambda 0.95."""
    return PPOConfig(horizon=16, epochs=6, minibatch_size=1024, gamma=0.99, lam=0.95, clip=0.1, lr=5e-5,
                     entropy_coef=0.01, max_grad_norm=1.0)


@dataclass
class TaskTrainConfig:
    seed: In[int, ">= 0"] = 0  # networks, task draws and minibatches
    iterations: In[int, ">= 1"] = 2000  # PPO iterations (each: ppo.horizon steps of every environment, then the update)
    task: str = "navigation"  # one of motok.control.tasks.registry.names()
    # Active codebooks M of a residual prior. None: the task's paper default (its TaskSpec.codebooks,
    # Tables 6-8: in-betweening 1, head tracking 2, navigation 1; at most the prior's), saved resolved
    # when a run starts. Runs saved before that resolution held None for all of them, and still do.
    codebooks: In[int | None, ">= 1"] = None
    save_every: In[int, ">= 1"] = 50  # iterations between checkpoints
    eval_every: In[int, ">= 0"] = 0  # iterations between task evaluations logged as eval_* (0: never)
    eval_episodes: In[int, ">= 1"] = 64  # episodes of each of those evaluations
    deterministic_eval: bool = True  # evaluate with the most likely action (argmax codes, the mean offset)
    torch_threads: In[int, ">= 1"] = 1  # during rollouts: MuJoCo has the cores
    update_threads: In[int, ">= 0"] = 0  # during the PPO update (0: torch_threads)
    env: SimConfig = field(default_factory=lambda: SimConfig(num_envs=128))  # the batched physics of the rollouts
    tasks: registry.TaskConfigs = field(default_factory=registry.TaskConfigs)  # every task's settings: tasks.NAME.FIELD
    ppo: PPOConfig = field(default_factory=paper_ppo)  # the update (Tables 6-8's values by default)
    net: HighLevelNetConfig = field(default_factory=HighLevelNetConfig)  # the high-level policy and critic
    # The continuous prior's learning rate, in place of ppo.lr (None: ppo.lr). Its fixed-std Gaussian
    # moves far more per step than the categorical heads at the same lr (docs/history.md): the 2-core
    # recipes raise ppo.lr for the categorical policies and keep this at Tables 6-8's 5e-5.
    continuous_lr: In[float | None, "> 0"] = None

    # What a config saved before a key existed did (motok.config.from_dict): ppo.lr for every prior.
    KEYS_ADDED = {"continuous_lr": None}
    # Taken from the prior when a run starts and saved resolved: a resume's recipe may leave them out.
    RESUME_DERIVED = ("env.control_hz", "env.target_filter", "codebooks")

    def check(self) -> None:
        registry.check(self.task)

    def resume_may_change(self) -> set[str]:
        """What ``--resume`` may change (motok.resume): the run's length, unless the learning-rate
        schedule spans it."""
        return {"iterations"} if self.ppo.lr_schedule == "constant" else set()


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


def load_task_run(run) -> tuple[TaskTrainConfig, Humanoid, ActorCritic, LatentPrior, float, dict]:
    """``(cfg, humanoid, high-level actor-critic, frozen prior, prior action scale, meta)``."""
    run = Path(run)
    prior = {}

    def build(cfg: TaskTrainConfig, meta: dict) -> ActorCritic:
        # The policy's heads are the linked prior's codebooks: the prior is loaded first, and kept.
        pcfg, phum, model, _ = load_prior(runs.linked_path(run, meta, "prior"))
        ex = meta["extra"]
        if runs.mjcf_hash(phum) != ex["mjcf_sha256"]:
            raise UserError(f"{run}: its prior now has another humanoid than the one the policy was trained on")
        prior.update(model=model, scale=pcfg.action.scale)
        return build_high_level(cfg.net, model, ex["obs_dim"], ex["goal_dim"], cfg.codebooks)

    cfg, hum, ac, meta = runs.load_run_model(run, KIND, TaskTrainConfig, "ac.", build)
    return cfg, hum, ac, prior["model"], prior["scale"], meta
