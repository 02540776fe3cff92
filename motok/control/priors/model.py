"""The latent motion priors of the hybrid-latent paper (Bae et al. 2025, sections 3-4): one
posterior-prior-decoder shape, five bottlenecks.

* posterior ``f_phi(s, s~) -> z`` (Eq. 7 observation and Eq. 9 goal, normalised);
* prior ``f_theta(s) -> z_p`` (the observation only: what task learning keeps);
* low-level decoder ``pi_low(s, z_bar) -> a``, the residual PD offsets on the current pose.

Kinds (the capability rows of ``motok.control.priors.kinds.KINDS``):

* ``continuous`` (PULSE-style, Eq. 1-2): Gaussian posterior and prior (mean and clamped log-std
  heads), ``z ~ q(z | s, s~)`` by reparameterisation, ``z_bar = z``, ``L_kl = KL(q || p)``.
* ``discrete`` (NCP-style, Eq. 3-4): ``z_bar = VQ(z)``, one codebook, straight-through; no prior
  network (task learning picks codes).
* ``discrete+``: ``z_bar = RVQ(z)``, residual codebooks with quantizer dropout; no prior network.
* ``hybrid`` (section 4.1, Algorithm 1): the margin ``y = z - sg(z_p)`` is quantized,
  ``y_bar = RVQ(y)`` (EMA codebooks, dead-code reset, quantizer dropout: section 4.2),
  ``z_bar = sg(z_p) + y_bar``, and ``L_mm = ||z_bar - z_p||^2`` pulls prior and posterior together.
* ``hybrid-vq`` (appendix A.1): the hybrid with one VQ codebook instead of RVQ.
* ``hybrid-fsq``, ``hybrid-grvq`` (the paper's future work): the margin by grouped FSQ or group RVQ
  (:mod:`motok.quantize.grouped`); FSQ has no commitment loss, so Eq. 6 keeps ``L_mm``, not ``L_commit``.
* ``hybrid-parts``: group RVQ with two groups, the lower and the upper body; each half of the
  posterior's ``z`` is computed from ``s`` and its own part's entries of the goal only
  (:mod:`motok.control.priors.parts`), ``z_p`` shared.

Where the gradients go (Algorithm 1): the decoder reads ``z_bar``, whose only path back is the
straight-through estimator to ``z`` (the posterior); ``z_p`` enters it behind a stop-gradient, so
the prior learns from ``L_mm`` (and ``L_reg``) only, never from the action loss. Quantizers come
from :mod:`motok.quantize` (EMA updates and code resets happen inside their training-mode forward).

Conventions, the authors' released code's (their loss weights were tuned with them): squared
norms are summed over latent dimensions and averaged over rows; the Gaussian KL is averaged over
latent dimensions; the commitment loss is the quantizer's per-element mean (``motok.quantize``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from motok.checkpoint import register_kind
from motok.control import runs
from motok.control.mdp.actions import ActionConfig
from motok.control.priors.kinds import KINDS, Kind
from motok.control.rl.networks import RunningNorm, mlp
from motok.control.tasks.imitation import ImitationTaskConfig
from motok.errors import UserError
from motok.control.priors.parts import PART_NAMES
from motok.quantize.base import QuantizerConfig
from motok.quantize.grouped import GroupedFSQ, GroupedRVQ
from motok.quantize.registry import build_quantizer
from motok.ranges import In
from motok.sim.env import SimConfig
from motok.sim.humanoid import Humanoid

KIND = "control-prior"
register_kind(KIND, (1,))



@dataclass
class PriorConfig:
    kind: str = ""  # one of KINDS; `motok control distill --prior` sets it
    latent_dim: In[int, ">= 1"] = 64  # D: the latent z's size, and the codebooks' code dimension
    # hidden sizes of f_phi(s, s~) -> z
    posterior_hidden: In[list[int], ">= 1"] = field(default_factory=lambda: [256, 256])
    prior_hidden: In[list[int], ">= 1"] = field(default_factory=lambda: [256, 256])  # hidden sizes of f_theta(s) -> z_p
    # hidden sizes of pi_low(s, z_bar) -> a
    decoder_hidden: In[list[int], ">= 1"] = field(default_factory=lambda: [256, 256])
    activation: str = "elu"  # relu | elu | tanh | silu
    log_std_min: In[float, "any"] = -5.0  # continuous: log-std heads clamped to [min, max] (PHC's bounds)
    log_std_max: In[float, "any"] = 1.0  # the upper bound of that clamp (PHC's)
    num_codebooks: In[int, ">= 1"] = 8  # discrete+ and hybrid: residual codebooks
    codebook_size: In[int, ">= 1"] = 128  # codes per residual codebook
    vq_codebook_size: In[int, ">= 1"] = 1024  # discrete and hybrid-vq: the single codebook
    quantizer: str = "ema_reset"  # how each codebook learns (motok.quantize.vq.VQ_KINDS)
    decay: In[float, "[0, 1]"] = 0.99  # EMA decay
    reset_threshold: In[float, ">= 0"] = 2.0  # EMA usage below which a code is reset (the authors' code: 2)
    quantizer_dropout: In[float, "[0, 1]"] = 1.0  # share of training batches that use only M ~ U{1..N} codebooks
    kmeans_init: bool = True  # codebooks from k-means on the first training batch
    # hybrid-grvq: the margin's dimensions split into this many groups, each with num_codebooks residual
    # codebooks of codebook_size codes (hybrid-parts: always two, the lower and the upper body)
    groups: In[int, ">= 1"] = 2
    fsq_channels: In[int, ">= 1"] = 3  # hybrid-fsq: channels per group, num_codebooks groups (M counts groups)
    fsq_levels: In[int, ">= 3"] = 5  # hybrid-fsq: levels per channel, odd (a group not in use sits at level zero)

    def check(self) -> None:
        if self.kind not in KINDS:
            raise UserError(f"prior kind must be one of {', '.join(KINDS)}, not {self.kind!r}")
        if self.log_std_min > self.log_std_max:
            raise UserError("prior.log_std_min must not exceed prior.log_std_max")


@dataclass
class Latents:
    """What one forward pass computed, for rows ``(B, .)``."""

    action: Tensor  # pi_low(s, z_bar): residual PD offsets on the current pose
    z: Tensor  # posterior latent (continuous: the sample, or the mean when not sampling)
    z_bar: Tensor  # what the decoder read
    z_p: Tensor | None  # prior latent (continuous: the prior mean); None without a prior network
    reg: list[Tensor]  # latents whose change between neighbouring steps L_reg penalises
    losses: dict[str, Tensor]  # "commit", "codebook", "mm", "kl", "part": zero-dim, unweighted
    indices: Tensor | None = None  # (B, N) code indices, -1 for codebooks a batch did not use
    stats: dict = field(default_factory=dict)  # the quantizer's: usage, perplexity, dead, num_active


def gaussian_kl(mu_q: Tensor, log_std_q: Tensor, mu_p: Tensor, log_std_p: Tensor) -> Tensor:
    """Eq. 2's ``KL(q || p)`` per dimension for diagonal Gaussians, in closed form:
    ``log(s_p / s_q) + (s_q^2 + (mu_q - mu_p)^2) / (2 s_p^2) - 1/2``."""
    var_q, var_p = torch.exp(2 * log_std_q), torch.exp(2 * log_std_p)
    return log_std_p - log_std_q + (var_q + (mu_q - mu_p) ** 2) / (2 * var_p) - 0.5


def squared_norm(x: Tensor) -> Tensor:
    """``||x||^2`` per row (summed over the last axis)."""
    return (x * x).sum(-1)


def quantizer_config(c: PriorConfig, residual: bool) -> QuantizerConfig:
    """The :mod:`motok.quantize` config of a prior's codebooks (one book, or ``num_codebooks``)."""
    return QuantizerConfig(kind="rvq" if residual else c.quantizer, rvq_base=c.quantizer,
                           codebook_size=c.codebook_size if residual else c.vq_codebook_size,
                           num_codebooks=c.num_codebooks if residual else 1, dim=c.latent_dim, decay=c.decay,
                           reset_threshold=c.reset_threshold, quantizer_dropout=c.quantizer_dropout,
                           kmeans_init=c.kmeans_init)


# A capability row's quantizer name -> its builder (PriorConfig, Kind) -> Quantizer.
QUANTIZERS = {
    "vq": lambda c, k: build_quantizer(quantizer_config(c, False)),
    "rvq": lambda c, k: build_quantizer(quantizer_config(c, True)),
    "fsq": lambda c, k: GroupedFSQ(quantizer_config(c, True), c.num_codebooks, c.fsq_channels, c.fsq_levels),
    "grvq": lambda c, k: GroupedRVQ(quantizer_config(c, True), len(PART_NAMES) if k.parts else c.groups),
}


class LatentPrior(nn.Module):
    """Normaliser + posterior + prior + quantizer + decoder of one kind (:attr:`caps`, its row of ``KINDS``).

    Inputs of :meth:`forward` are ``[s, s~]`` rows already normalised by :attr:`norm` (the
    student's own :class:`~motok.control.rl.networks.RunningNorm`, saved with the weights).

    ``parts`` (``hybrid-parts``): ``(goal, action)``, the body part of every goal entry and of every
    actuator (:func:`motok.control.priors.parts.body_layout`). They are buffers, saved with the
    weights, so a loaded prior needs none; without them every half of ``z`` reads the whole goal
    and ``L_part`` is zero."""

    def __init__(self, cfg: PriorConfig, obs_dim: int, goal_dim: int, action_dim: int, parts=None):
        super().__init__()
        cfg.check()
        self.cfg, self.kind = cfg, cfg.kind
        self.caps: Kind = KINDS[cfg.kind]
        self.obs_dim, self.goal_dim, self.action_dim = obs_dim, goal_dim, action_dim
        D, act = cfg.latent_dim, cfg.activation
        gaussian = self.caps.gaussian
        self.norm = RunningNorm(obs_dim + goal_dim)
        # A Gaussian head is one layer giving [mean, log-std]; the others give z itself.
        self.posterior = mlp([obs_dim + goal_dim, *cfg.posterior_hidden, D * (2 if gaussian else 1)], act)
        self.prior = mlp([obs_dim, *cfg.prior_hidden, D * (2 if gaussian else 1)], act) \
            if self.caps.prior_network else None
        self.quantizer = QUANTIZERS[self.caps.quantizer](cfg, self.caps) if not gaussian else None
        if self.caps.parts:  # row g: which posterior inputs the margin's group g reads (s always, its part's goal)
            keep, actuators = torch.ones(len(PART_NAMES), obs_dim + goal_dim), torch.full((action_dim,), -1)
            if parts is not None:
                keep[:, obs_dim:] = torch.as_tensor(parts[0])[None] == torch.arange(len(PART_NAMES))[:, None]
                actuators = torch.as_tensor(parts[1])
            self.register_buffer("part_inputs", keep)
            self.register_buffer("action_parts", actuators)  # -1: unknown, no actuator is another part's
        # out_gain 0.01: the student starts near zero offsets, i.e. holding its pose.
        self.decoder = mlp([obs_dim + D, *cfg.decoder_hidden, action_dim], act, out_gain=0.01)

    # ------------------------------------------------------------------ parts
    def norm_obs(self, s_raw: Tensor) -> Tensor:
        """The observation ``s`` alone normalised by the student's statistics (task learning has no goal)."""
        n, d = self.norm, s_raw.shape[-1]
        y = (s_raw - n.mean[:d].to(s_raw.dtype)) / torch.sqrt(n.var[:d].to(s_raw.dtype) + n.eps)
        return y.clamp(-n.clip, n.clip)

    def _gaussian(self, head: Tensor) -> tuple[Tensor, Tensor]:
        mu, log_std = head.chunk(2, -1)
        return mu, log_std.clamp(self.cfg.log_std_min, self.cfg.log_std_max)

    def prior_latent(self, s: Tensor) -> tuple[Tensor, Tensor | None]:
        """``z_p = f_theta(s)`` (continuous: ``(mean, log-std)``; else ``(z_p, None)``)."""
        if self.prior is None:
            raise UserError(f"the {self.kind} prior has no prior network")
        head = self.prior(s)
        return self._gaussian(head) if self.caps.gaussian else (head, None)

    def decode(self, s: Tensor, z_bar: Tensor) -> Tensor:
        """``a = pi_low(s, z_bar)``: the low-level policy, from normalised ``s`` and a latent."""
        return self.decoder(torch.cat([s, z_bar], -1))

    @property
    def num_codebooks(self) -> int:
        return 0 if self.quantizer is None else self.quantizer.num_codebooks

    def columns(self, m: int | None = None) -> int:
        """Code-index columns of the first M codebooks (all by default): M for one or residual
        codebooks, M * G for group RVQ, M * channels for FSQ (each column a channel's level)."""
        return 0 if self.quantizer is None else self.quantizer.columns(self.num_codebooks if m is None else m)

    def posterior_latent(self, xn: Tensor) -> Tensor:
        """``f_phi(s, s~)``; for ``hybrid-parts`` the margin group g's dimensions come from a pass
        that reads ``s`` and only part g's goal entries (the others at their running mean, 0)."""
        if not self.caps.parts:
            return self.posterior(xn)
        w = self.cfg.latent_dim // len(PART_NAMES)  # group g of the margin is dimensions g w .. (g + 1) w
        return torch.cat([self.posterior(xn * keep)[..., g * w:(g + 1) * w]
                          for g, keep in enumerate(self.part_inputs)], -1)

    def codebooks(self) -> Tensor:
        """Every code, ``(N, K, D)`` (detached); the hybrid's are codes of the margin ``y``."""
        if self.quantizer is None:
            raise UserError("the continuous prior has no codebooks")
        return self.quantizer.codebooks()

    # ------------------------------------------------------------------ the forward pass
    def forward(self, xn: Tensor, num_codebooks: int | None = None, sample: bool = True) -> Latents:
        """All of Algorithm 1 for normalised ``[s, s~]`` rows: posterior, prior, bottleneck,
        decoder. In training mode the quantizer also updates its codebooks (EMA, resets) and,
        for residual kinds, drops all but the first M ~ U{1..N} codebooks (quantizer dropout);
        ``num_codebooks`` fixes M instead. ``sample`` (continuous): ``z`` drawn from the
        posterior rather than its mean."""
        s = xn[..., :self.obs_dim]
        zero = xn.new_zeros(())
        losses = {"commit": zero, "codebook": zero, "mm": zero, "kl": zero, "part": zero}
        head = self.posterior_latent(xn)
        if self.caps.gaussian:
            mu_q, log_std_q = self._gaussian(head)
            mu_p, log_std_p = self.prior_latent(s)
            z = mu_q + torch.exp(log_std_q) * torch.randn_like(mu_q) if sample else mu_q  # Eq. 1, reparameterised
            losses["kl"] = gaussian_kl(mu_q, log_std_q, mu_p, log_std_p).mean(-1).mean()  # Eq. 2
            return Latents(self.decode(s, z), z, z, mu_p, [mu_q], losses)
        z = head
        z_p = self.prior_latent(s)[0] if self.prior is not None else None
        # Hybrid (Algorithm 1): quantize the margin to the prior, which is held fixed here.
        target = z - z_p.detach() if z_p is not None else z
        q = self.quantizer(target, num_codebooks)
        losses["commit"], losses["codebook"] = q.losses["commit"], q.losses["codebook"]
        if z_p is None:  # discrete (Eq. 3-4) and discrete+: z_bar = VQ(z) or RVQ(z)
            return Latents(self.decode(s, q.z_q), z, q.z_q, None, [q.z_q], losses, q.indices, q.stats)
        z_bar = z_p.detach() + q.z_q  # z_bar = sg(z_p) + y_bar: the action loss never reaches the prior
        losses["mm"] = squared_norm(z_bar - z_p).mean()  # L_mm, section 4.1
        action = self.decode(s, z_bar)
        if self.caps.parts and self.training:
            losses["part"] = self.cross_part_change(s, z_p.detach(), q.z_q, action.detach())
        return Latents(action, z, z_bar, z_p, [q.z_q, z_p], losses, q.indices, q.stats)

    def cross_part_change(self, s: Tensor, z_p: Tensor, y_bar: Tensor, action: Tensor) -> Tensor:
        """``L_part`` (``hybrid-parts``, not the paper's): for each part g, the margin's group g
        replaced by the previous row's (another state's codes), ``||a' - sg(a)||^2`` over the actuators
        of the *other* parts, summed over g, mean over rows: the decoder learns that a part's codes
        leave the other parts' actuators alone."""
        w = self.cfg.latent_dim // len(PART_NAMES)
        group = torch.arange(self.cfg.latent_dim, device=s.device) // w
        total = action.new_zeros(())
        for g in range(len(PART_NAMES)):
            mine = (group == g).to(y_bar.dtype)
            swapped = self.decode(s, z_p + y_bar * (1 - mine) + y_bar.roll(1, 0) * mine)
            others = ((self.action_parts != g) & (self.action_parts >= 0)).to(action.dtype)
            total = total + squared_norm((swapped - action) * others).mean()
        return total

    # ------------------------------------------------------------------ what task learning drives
    @torch.no_grad()
    def codes_to_latent(self, s: Tensor, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        """``z_bar`` from code indices of the first M codebooks (at least :meth:`columns` ``(M)``
        columns; -1 entries skip a codebook): ``z_p(s) + the decoded margin`` for the hybrids (the
        sum of the selected codes; FSQ: the output projection of the chosen levels), the sum of
        the codes for ``discrete+``, the code for ``discrete``."""
        if self.quantizer is None:
            raise UserError("the continuous prior has no codes: use offset_to_latent")
        q = self.quantizer
        m = num_codebooks if num_codebooks is not None else \
            max(m for m in range(self.num_codebooks + 1) if q.columns(m) <= indices.shape[-1])
        codes = q.decode(indices[..., :q.columns(m)], m)
        return codes + self.prior_latent(s)[0] if self.prior is not None else codes

    @torch.no_grad()
    def offset_to_latent(self, s: Tensor, u: Tensor) -> Tensor:
        """Continuous task learning: ``z = mu_p(s) + u``, an offset from the prior's mean."""
        if not self.caps.gaussian:
            raise UserError(f"offset_to_latent is for the continuous prior, not {self.kind!r}")
        return self.prior_latent(s)[0] + u

    def spec(self) -> dict:
        """What a bundle records of the model (the sizes a reader needs to rebuild it)."""
        q = self.quantizer
        return {"kind": self.kind, "latent_dim": self.cfg.latent_dim, "has_prior": self.prior is not None,
                "num_codebooks": self.num_codebooks, "codebook_size": q.codebook_size if q is not None else 0,
                "quantizer": self.caps.quantizer if q is not None else None, "index_columns": self.columns(),
                "posterior_hidden": list(self.cfg.posterior_hidden), "prior_hidden": list(self.cfg.prior_hidden),
                "decoder_hidden": list(self.cfg.decoder_hidden)}


@dataclass
class WeightSchedule:
    start: In[float, ">= 0"] = 0.0  # the weight at iteration 0
    end: In[float, ">= 0"] = 0.0  # the weight once the ramp is over
    ramp: In[float, "[0, 1]"] = 0.125  # share of the iterations over which the weight moves linearly from start to end

    def at(self, iteration: int, total: int) -> float:
        n = self.ramp * total
        return self.end if n <= 0 else self.start + (self.end - self.start) * min(iteration / n, 1.0)


@dataclass
class LossConfig:
    action: In[float, ">= 0"] = 10.0  # weight of ||a - a_label||^2
    commit: In[float, ">= 0"] = 1.0  # beta
    reg: In[float | None, ">= 0"] = None  # alpha; None: 0.005 for continuous, 0.05 for the others (the paper's)
    mm: WeightSchedule = field(default_factory=lambda: WeightSchedule(0.1, 1.0))  # gamma (hybrids)
    # hybrid-parts: weight of L_part, a part's codes must not move the other parts' actuators (beyond the
    # paper); 10, the action term's: at 1 the short check measured no tie at all (docs/control/priors.md)
    part: In[float, ">= 0"] = 10.0
    kl: WeightSchedule = field(default_factory=lambda: WeightSchedule(0.05, 0.5))  # continuous


@dataclass
class DistillConfig:
    seed: In[int, ">= 0"] = 0  # the student's weights, task draws, minibatches
    # DAgger iterations (each: horizon steps of every environment, then epochs of Eq. 6)
    iterations: In[int, ">= 1"] = 3000
    save_every: In[int, ">= 1"] = 50  # iterations between checkpoints (every one resumes exactly)
    eval_every: In[int, ">= 0"] = 0  # iterations between imitation evaluations of the student, logged as eval_*
    eval_per_group: In[int, ">= 0"] = 0  # eval_* on this many clips per content x style (0: every clip)
    eval_batch: In[int, ">= 1"] = 256  # clips played side by side in an imitation evaluation (speed only)
    torch_threads: In[int, ">= 1"] = 1  # during rollouts: 2 fights MuJoCo's worker threads on a 2-core machine
    update_threads: In[int, ">= 0"] = 0  # during the supervised update, while the physics is idle (0: torch_threads)
    horizon: In[int, ">= 1"] = 32  # steps per environment per iteration
    epochs: In[int, ">= 1"] = 4  # passes over each iteration's data
    minibatch_size: In[int, ">= 1"] = 1024  # samples; rounded down to whole environment columns of `horizon` steps
    lr: In[float, "> 0"] = 2e-4  # the authors' distillation learning rate
    max_grad_norm: In[float, "> 0"] = 1.0  # global gradient-norm clip of the student's update
    action_noise: In[float, ">= 0"] = 0.055  # std of the noise on the student's actions while collecting (rad)
    env: SimConfig = field(default_factory=lambda: SimConfig(num_envs=128))  # the batched physics of the rollouts
    # the imitation task; goal_frames must be the expert's
    task: ImitationTaskConfig = field(default_factory=lambda: ImitationTaskConfig(termination="mean"))
    # the student's action map: residual on the current pose
    action: ActionConfig = field(default_factory=lambda: ActionConfig("current"))
    prior: PriorConfig = field(default_factory=PriorConfig)  # the prior's kind and sizes
    loss: LossConfig = field(default_factory=LossConfig)  # Eq. 6's weights

    # Set when a run starts (--prior, the expert's filter) and saved resolved: a resume's recipe may leave them out.
    RESUME_DERIVED = ("prior.kind", "env.target_filter")

    def resume_may_change(self) -> set[str]:
        """What ``--resume`` may change (motok.resume): the run's length, unless a loss weight
        ramps over a share of it."""
        ramps = [w for w in (self.loss.mm, self.loss.kl) if w.start != w.end and w.ramp > 0]
        return set() if ramps else {"iterations"}


def load_prior(run) -> tuple[DistillConfig, Humanoid, LatentPrior, dict]:
    """A distilled prior in eval mode, with its config, humanoid (hash checked) and metadata."""
    cfg, hum, model, meta = runs.load_run_model(run, KIND, DistillConfig, "model.", lambda cfg, meta: LatentPrior(
        cfg.prior, *(meta["extra"][k] for k in ("obs_dim", "goal_dim", "action_dim"))))
    return cfg, hum, model.eval(), meta
