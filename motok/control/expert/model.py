"""The physics expert's recipe and networks (hybrid-latent paper appendix B.2), and the loader
that rebuilds a trained expert from its bundle (kind ``control-expert``) for the readers that
drive it: distillation's teacher, tracking, evaluation."""

from __future__ import annotations

from dataclasses import dataclass, field

from motok.checkpoint import register_kind
from motok.control import runs
from motok.control.mdp.actions import ActionConfig
from motok.control.rl.amp import AMPConfig
from motok.control.rl.networks import ActorCritic, RunningNorm, ValueNet
from motok.control.rl.policies import EncoderDecoderPolicy
from motok.control.rl.ppo import PPOConfig
from motok.control.rl.sampling import SamplingConfig
from motok.control.tasks.imitation import ImitationTaskConfig
from motok.ranges import In
from motok.sim.env import SimConfig
from motok.sim.humanoid import Humanoid, HumanoidConfig

KIND = "control-expert"
register_kind(KIND, (1,))


@dataclass
class NetConfig:
    latent_dim: In[int, ">= 1"] = 64  # the encoder's latent z (no bottleneck: a plain vector)
    encoder: In[list[int], ">= 1"] = field(default_factory=lambda: [512, 256])  # hidden sizes of E(s, s~) -> z
    decoder: In[list[int], ">= 1"] = field(default_factory=lambda: [512, 256])  # hidden sizes of D(s, z) -> a
    value: In[list[int], ">= 1"] = field(default_factory=lambda: [512, 256])  # hidden sizes of the critic
    activation: str = "elu"  # relu | elu | tanh | silu
    log_std: In[float, "any"] = -1.6  # the Gaussian's state-independent log std (rad)
    learn_log_std: bool = False  # a parameter (learned) rather than a buffer (fixed, PHC's choice)


@dataclass
class ExpertConfig:
    seed: In[int, ">= 0"] = 0  # networks, task draws, minibatches
    # PPO iterations (each: ppo.horizon steps of every environment, then the updates)
    iterations: In[int, ">= 1"] = 1000
    w_im: In[float, ">= 0"] = 0.5  # weight of the imitation reward r_im (Eq. 10)
    w_style: In[float, ">= 0"] = 0.5  # weight of AMP's style reward r_style (Eq. 11); 0 also turns AMP off
    # weight of the action-rate term r_action_rate = -mean_j (a_t - a_(t-1))^2, added to the reward
    # (docs/sim.md "Feet"); 0, the paper's reward, leaves it out
    w_action_rate: In[float, ">= 0"] = 0.0
    save_every: In[int, ">= 1"] = 50  # iterations between checkpoints (every one resumes exactly)
    eval_every: In[int, ">= 0"] = 0  # iterations between `evaluate` passes logged as eval_* metrics (0: never)
    eval_per_group: In[int, ">= 0"] = 0  # eval_* on this many clips per content x style (0: every training clip)
    torch_threads: In[int, ">= 1"] = 1  # during rollouts: 2 fights MuJoCo's worker threads on a 2-core machine
    update_threads: In[int, ">= 0"] = 0  # during the PPO and discriminator updates (0: torch_threads)
    env: SimConfig = field(default_factory=lambda: SimConfig(num_envs=64))  # the batched physics it trains in
    task: ImitationTaskConfig = field(default_factory=ImitationTaskConfig)  # the imitation task
    action: ActionConfig = field(default_factory=ActionConfig)  # the action map (residual PD targets)
    ppo: PPOConfig = field(default_factory=PPOConfig)  # the PPO update
    net: NetConfig = field(default_factory=NetConfig)  # the encoder-decoder policy and critic
    amp: AMPConfig = field(default_factory=AMPConfig)  # the style discriminator
    sampling: SamplingConfig = field(default_factory=SamplingConfig)  # difficulty-weighted start clips
    # The world a new run builds from --data (contact model, PD gains; docs/sim.md): its MJCF goes
    # into the run, and a resume keeps it (a different one here is refused, not applied).
    humanoid: HumanoidConfig = field(default_factory=HumanoidConfig)

    def resume_may_change(self) -> set[str]:
        """What ``--resume`` may change (motok.resume): the run's length, unless the learning-rate
        schedule spans it; anything else would make the run differ from an uninterrupted one."""
        return {"iterations"} if self.ppo.lr_schedule == "constant" else set()


def build_actor_critic(n: NetConfig, obs_dim: int, goal_dim: int, action_dim: int) -> ActorCritic:
    pol = EncoderDecoderPolicy(obs_dim, goal_dim, action_dim, n.latent_dim, tuple(n.encoder), tuple(n.decoder),
                               n.activation, n.log_std, n.learn_log_std)
    return ActorCritic(RunningNorm(obs_dim + goal_dim), pol, ValueNet(obs_dim + goal_dim, tuple(n.value), n.activation))


def load_expert(run) -> tuple[ExpertConfig, Humanoid, ActorCritic, dict]:
    """A trained expert's recipe, humanoid (hash checked), actor-critic and bundle metadata."""
    return runs.load_run_model(run, KIND, ExpertConfig, "ac.", lambda cfg, meta: build_actor_critic(
        cfg.net, *(meta["extra"][k] for k in ("obs_dim", "goal_dim", "action_dim"))))
