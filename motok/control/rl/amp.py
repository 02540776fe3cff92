"""Adversarial motion prior (Peng et al. 2021, AMP) for the expert's style reward, hybrid-latent
paper Eq. 11.

A discriminator ``D(s, s') = sigmoid(f(s, s'))`` sees state transitions: reference transitions
(consecutive frames of the motion library, observed with the same Eq. 7 observation the policy
gets) labelled **1** and policy transitions labelled **0**. It is trained with binary cross
entropy plus a gradient penalty ``w_gp E_ref[||grad_x f(x)||^2]`` on the reference samples
(AMP's zero-centred penalty, which keeps ``f`` flat on the data manifold so the reward gives the
policy a usable gradient), and sees policy transitions drawn half from the current rollout and
half from a replay buffer of older ones (so it does not forget what earlier policies did).

The style reward is ``r_style = -scale log(1 - D(s, s'))`` (``scale`` 5 in the paper): large when
the discriminator takes the policy's transition for reference data. **Convention note.** The
paper's text says the discriminator outputs 1 for the *agent*, but with that labelling
``-log(1 - D)`` would reward looking *unlike* the data; the formula only makes sense with 1 for
reference data, which is AMP's (and ASE's) convention and the one implemented here.

**The feet** (``AMPConfig.feet``, off by default: the paper's discriminator sees Eq. 7 alone).
Eq. 7 holds no foot height and no world-frame speed, so a sole sliding along the floor looks
like a planted one to the discriminator. With ``feet`` each state of a transition, simulated
and reference alike, is Eq. 7 followed by :class:`SoleObservation`: per foot, the lowest sole
corner's height above the floor and its horizontal speed (``motok.sim.soles.sole_state``, one
function for both). The discriminator's input grows by 4 per state (2 per foot), recorded in
the run's spec (``amp_obs_dim``); a resume with the other setting is refused like any change.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from motok.arrays import xp
from motok.control.rl.networks import mlp
from motok.distributed import average_gradients, world_size
from motok.ranges import In
from motok.rotations import quat_to_matrix
from motok.sim.obs import Bodies, observation
from motok.sim.soles import foot_corners, sole_state, soles


@dataclass
class AMPConfig:
    enabled: bool = True  # false: no discriminator and no style reward
    hidden: In[list[int], ">= 1"] = field(default_factory=lambda: [256, 256])  # the discriminator's hidden sizes
    activation: str = "relu"  # relu | elu | tanh | silu
    lr: In[float, "> 0"] = 1e-4  # the discriminator's Adam learning rate
    weight_decay: In[float, ">= 0"] = 1e-4  # L2 on the discriminator's weights
    grad_penalty: In[float, ">= 0"] = 5.0  # w_gp of the zero-centred gradient penalty on reference inputs
    logit_reg: In[float, ">= 0"] = 0.01  # L2 on the last layer's weights: keeps logits from saturating
    batch_size: In[int, ">= 1"] = 512  # reference and policy transitions per minibatch (policy: half replayed)
    updates: In[int, ">= 0"] = 8  # discriminator minibatches per PPO iteration
    replay_size: In[int, ">= 1"] = 100_000  # older policy transitions kept, so the discriminator does not forget
    style_scale: In[float, ">= 0"] = 5.0  # r_style = -style_scale log(1 - D)
    # true: each state the discriminator sees is Eq. 7 and, per foot, the lowest sole corner's height
    # and horizontal speed (SoleObservation; docs/sim.md "Feet"); false: Eq. 7 alone, the paper's
    feet: bool = False


def gradient_penalty(logit_fn, x_ref: torch.Tensor) -> torch.Tensor:
    """``E[||d logit / d x||^2]`` at the reference inputs ``x_ref``."""
    x = x_ref.detach().requires_grad_(True)
    (g,) = torch.autograd.grad(logit_fn(x).sum(), x, create_graph=True)
    return (g**2).sum(-1).mean()


def style_reward(logits: torch.Tensor, scale: float) -> torch.Tensor:
    """``-scale log(1 - D)`` with ``D = sigmoid(logit)``; ``1 - D`` floored at 1e-4 so a confident
    discriminator cannot produce an unbounded reward. ``log(1 - sigmoid(l)) = -softplus(l)``."""
    return scale * torch.clamp(F.softplus(logits), max=-float(np.log(1e-4)))


class Discriminator(nn.Module):
    """``f([s, s'])`` on inputs normalised by fixed reference statistics (stored as buffers)."""

    def __init__(self, obs_dim: int, hidden=(256, 256), activation="relu"):
        super().__init__()
        self.register_buffer("mean", torch.zeros(obs_dim))
        self.register_buffer("std", torch.ones(obs_dim))
        self.net = mlp([2 * obs_dim, *hidden, 1], activation, out_gain=0.1)

    def normalise(self, s: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
        # Clipped: a fallen policy's states lie many reference deviations away and would saturate D.
        return torch.cat([(s - self.mean) / self.std, (s2 - self.mean) / self.std], -1).clamp(-5.0, 5.0)

    def logit_of(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x).squeeze(-1)

    def forward(self, s, s2):
        return self.logit_of(self.normalise(s, s2))


class ReplayBuffer:
    """Fixed-size ring of policy transitions ``(s, s')``; state saved for exact resume."""

    def __init__(self, capacity: int, obs_dim: int, device=None):
        self.data = torch.zeros(capacity, 2, obs_dim, device=device)
        self.pos, self.size = 0, 0

    def add(self, s: torch.Tensor, s2: torch.Tensor) -> None:
        cap, n = len(self.data), len(s)
        keep = slice(max(n - cap, 0), n)  # more than fits: only the newest survive, in ring order
        rows = (self.pos + torch.arange(n, device=self.data.device)[keep]) % cap
        self.data[rows] = torch.stack([s[keep], s2[keep]], 1)
        self.pos = int((self.pos + n) % cap)
        self.size = min(self.size + n, cap)

    def sample(self, n: int, rng: np.random.Generator) -> torch.Tensor:
        return self.data[_rows(rng.integers(0, self.size, n), self.data)]

    def state(self) -> dict:
        return {"data": self.data[:self.size].to("cpu", copy=True), "pos": torch.tensor(self.pos)}  # host: a checkpoint loads anywhere

    def load(self, st: dict) -> None:
        n = len(st["data"])
        self.data[:n] = st["data"].to(self.data.device)
        self.pos, self.size = int(st["pos"]), n


def _rows(idx: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """Host-drawn row indices (the seeded numpy generator decides the minibatches) on ``like``'s device."""
    return torch.from_numpy(idx).to(like.device)


class AMP:
    """Discriminator, its optimiser, the replay buffer and the reference transitions."""

    def __init__(self, cfg: AMPConfig, ref_obs: np.ndarray, clip_starts: np.ndarray, device=None):
        """``ref_obs (F, D)``: Eq. 7 observations of every library frame; ``clip_starts (C+1,)``
        so that a transition never spans two clips; ``device``: where the rollout's transitions are."""
        self.cfg = cfg
        self.ref = torch.as_tensor(ref_obs, dtype=torch.float32, device=device)
        last = np.zeros(len(ref_obs), dtype=bool)
        last[np.asarray(clip_starts[1:]) - 1] = True
        self.ref_idx = np.flatnonzero(~last)  # frames with a successor in the same clip
        self.disc = Discriminator(ref_obs.shape[1], tuple(cfg.hidden), cfg.activation).to(device)
        self.disc.mean.copy_(self.ref.mean(0))
        self.disc.std.copy_(self.ref.std(0).clamp_min(0.05))  # near-constant reference features must not blow up
        self.opt = torch.optim.Adam(self.disc.parameters(), lr=cfg.lr)
        self.replay = ReplayBuffer(cfg.replay_size, ref_obs.shape[1], device)

    def reference_batch(self, n: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        g = _rows(self.ref_idx[rng.integers(0, len(self.ref_idx), n)], self.ref)
        return self.ref[g], self.ref[g + 1]

    @torch.no_grad()
    def reward(self, s: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
        return style_reward(self.disc(s, s2), self.cfg.style_scale)

    def loss(self, ref: tuple[torch.Tensor, torch.Tensor], pol: tuple[torch.Tensor, torch.Tensor]):
        d, c = self.disc, self.cfg
        x_ref, x_pol = d.normalise(*ref), d.normalise(*pol)
        l_ref, l_pol = d.logit_of(x_ref), d.logit_of(x_pol)
        bce = 0.5 * (F.binary_cross_entropy_with_logits(l_ref, torch.ones_like(l_ref))
                     + F.binary_cross_entropy_with_logits(l_pol, torch.zeros_like(l_pol)))
        gp = gradient_penalty(d.logit_of, x_ref)
        last = d.net[-1].weight
        loss = bce + c.grad_penalty * gp + c.logit_reg * (last**2).sum()
        with torch.no_grad():
            stats = {"disc_loss": float(bce), "disc_gp": float(gp), "disc_ref": float(torch.sigmoid(l_ref).mean()),
                     "disc_pol": float(torch.sigmoid(l_pol).mean())}
        return loss, stats

    def update(self, s: torch.Tensor, s2: torch.Tensor, rng: np.random.Generator) -> dict[str, float]:
        """Train on this rollout's policy transitions ``(M, D)`` (mixed with replay), then store them."""
        c = self.cfg
        stats: dict[str, float] = {}
        for _ in range(c.updates):
            n = c.batch_size
            cur = _rows(rng.integers(0, len(s), n), s)
            if self.replay.size:
                k = n // 2
                old = self.replay.sample(n - k, rng)
                pol = (torch.cat([s[cur[:k]], old[:, 0]]), torch.cat([s2[cur[:k]], old[:, 1]]))
            else:
                pol = (s[cur], s2[cur])
            loss, st = self.loss(self.reference_batch(n, rng), pol)
            if c.weight_decay:
                loss = loss + c.weight_decay * sum((p**2).sum() for n_, p in self.disc.named_parameters()
                                                   if n_.endswith("weight"))
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            if world_size() > 1:
                average_gradients(list(self.disc.parameters()))
            self.opt.step()
            for k_, v in st.items():
                stats[k_] = stats.get(k_, 0.0) + v / c.updates
        self.replay.add(s, s2)
        return stats


class SoleObservation:
    """The soles as the discriminator sees them with ``AMPConfig.feet``: :meth:`of` appends to Eq. 7
    observations ``(N, D)`` the :func:`~motok.sim.soles.sole_state` of the same states; called as
    ``(mdp, obs)`` it is the collector's ``hook_obs`` (the simulated bodies of ``mdp.env``)."""

    def __init__(self, hum):
        self.sole = soles(hum)
        self.feet = foot_corners(self.sole, hum.skeleton)

    def of(self, obs, bodies: Bodies):
        f = sole_state(self.sole, self.feet, bodies.pos, bodies.rot, bodies.vel, bodies.angvel)
        return xp(obs).concatenate([obs, f], -1)

    def __call__(self, mdp, obs):
        return self.of(obs, mdp.env.bodies)

    def reference(self, lib, chunk: int = 65536) -> np.ndarray:
        """``(F, 2 x feet)`` of every library frame, in chunks: the rotation matrices of a whole
        dataset's bodies would not fit in memory at once."""
        out = []
        for a in range(0, len(lib.body_pos), chunk):
            sl = slice(a, a + chunk)
            out.append(sole_state(self.sole, self.feet, lib.body_pos[sl], quat_to_matrix(lib.body_quat[sl]),
                                  lib.body_vel[sl], lib.body_angvel[sl]))
        return np.concatenate(out) if out else np.zeros((0, 2 * len(self.feet)))


def reference_observations(lib, end_effectors, sole: SoleObservation | None = None) -> np.ndarray:
    """Eq. 7 observation of every frame of a reference library: the discriminator's reference
    samples; with ``sole`` followed by the frame's soles (``AMPConfig.feet``)."""
    bodies = Bodies(lib.body_pos, lib.body_vel, lib.body_angvel, quat=lib.body_quat)
    obs = observation(lib.qpos, lib.qvel, bodies, end_effectors)
    return obs if sole is None else np.concatenate([obs, sole.reference(lib)], -1)


class AMPHook:
    """AMP as a reward hook of the rollout collector: ``r_style`` on the rollout's transitions,
    then a discriminator update on them, with its own seeded generator for minibatches."""

    name = "r_style"

    def __init__(self, amp: AMP, weight: float, rng: np.random.Generator):
        self.amp, self.weight, self.rng = amp, weight, rng

    def reward(self, s: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
        return self.amp.reward(s, s2)

    def update(self, s: torch.Tensor, s2: torch.Tensor) -> dict[str, float]:
        return self.amp.update(s, s2, self.rng)
