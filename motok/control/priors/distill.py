"""Online distillation of a latent prior from the frozen expert (hybrid-latent paper section
4.3.1, Eq. 6): ``motok control distill``.

Per iteration the student (:class:`motok.control.priors.model.LatentPrior`) acts in the batched
imitation MDP with its own actions on the current-pose base, the expert labels every visited
state (:mod:`motok.control.priors.dagger`: DAgger, with the label conversion), and a supervised update
over minibatches minimises Eq. 6,

    L = 10 ||a - a_label||^2 + alpha L_reg + beta L_commit + gamma L_mm  (+ w_kl KL(q || p))

(``hybrid-fsq``: no ``L_commit``, FSQ has none; ``hybrid-parts`` adds ``w_part L_part``, not the
paper's: ``LatentPrior.cross_part_change``)

with ``L_reg`` the change of the latents between neighbouring steps of one episode (continuous:
the posterior mean; discrete, discrete+: ``z_bar``; hybrid: ``||y_bar - y_bar'||^2 + ||z_p -
z_p'||^2``), ``alpha`` 0.005 (continuous) or 0.05 (the others), ``beta`` 1, and ``gamma`` (L_mm,
hybrids) and ``w_kl`` (continuous) ramped linearly from 0.1 to 1.0 and 0.05 to 0.5 over the first
12.5 % of the iterations (the authors' schedule). Minibatches are sets of whole environment
columns, so both steps of every neighbouring pair are in the same forward pass.

The runner (:mod:`motok.control.rl.runner`) does seeding, checkpoints and exact resume, metrics,
provenance, the MJCF copy and hash, and torchrun. The bundle (kind ``control-prior``) records the
expert it was distilled from (path relative to the bundle and absolute), the prior's kind, sizes
and codebooks.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from motok.checkpoint import read_meta
from motok.config import from_dict
from motok.control import runs
from motok.control.expert.model import KIND as EXPERT_KIND
from motok.control.expert.model import load_expert
from motok.control.expert.train import imitation_mdp
from motok.control.priors.dagger import DaggerBatch, DaggerCollector
from motok.control.priors.load import StudentPolicy
from motok.control.priors.kinds import KINDS
from motok.control.priors.model import KIND, DistillConfig, LatentPrior, Latents, squared_norm
from motok.control.priors.parts import body_layout
from motok.control.rl import runner
from motok.control.rl.networks import ActorCritic
from motok.control.tasks.imitation import eval_metrics, evaluate, subset
from motok.distributed import Dist, average_gradients, world_size
from motok.errors import UserError
from motok.sim.env import SimConfig
from motok.sim.humanoid import Humanoid, load_humanoid
from motok.sim.reference import ReferenceLibrary

BAR = (("act", "action_loss", "{:.3g}"), ("commit", "commit_loss", "{:.3g}"), ("usage", "code_usage", "{:.2f}"),
       ("len", "episode_seconds", "{:.2f}s"), ("succ", "success", "{:.2f}"))
SUMMARY = ("action_loss", "rollout_action_err", "commit_loss", "mm_loss", "reg_loss", "kl_loss", "part_loss", "code_usage",
           "episode_seconds", "success", "r_im", "samples_per_s")


def latent_change(latents: list[torch.Tensor], horizon: int, done: torch.Tensor) -> torch.Tensor:
    """``L_reg``: for each latent ``(T * n, d)`` (rows step-major), the mean over neighbouring
    steps of one episode (pairs ``(t, t + 1)`` with ``done[t]`` false) of ``||l_{t+1} - l_t||^2``,
    summed over the latents."""
    keep = ~done[:-1]
    total = latents[0].new_zeros(())
    if not keep.any():
        return total
    for lat in latents:
        v = lat.view(horizon, -1, lat.shape[-1])
        total = total + squared_norm(v[1:] - v[:-1])[keep].mean()
    return total


def distill_loss(out: Latents, labels: torch.Tensor, horizon: int, done: torch.Tensor,
                 w: dict[str, float]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 6 for one minibatch of whole environment columns (rows step-major, ``done`` ``(T, n)``):
    the weighted sum and its unweighted terms. A gradient-learned codebook's own loss (zero for
    the EMA kinds) joins with weight 1, VQ-VAE's."""
    L = out.losses
    part = L.get("part", L["mm"].new_zeros(()))  # hybrid-parts' L_part (beyond the paper); zero elsewhere
    terms = {"action_loss": squared_norm(out.action - labels).mean(), "reg_loss": latent_change(out.reg, horizon, done),
             "commit_loss": L["commit"], "mm_loss": L["mm"], "kl_loss": L["kl"], "part_loss": part}
    total = (w["action"] * terms["action_loss"] + w["reg"] * terms["reg_loss"] + w["commit"] * L["commit"]
             + L["codebook"] + w["mm"] * L["mm"] + w["kl"] * L["kl"] + w.get("part", 0.0) * part)
    return total, terms


class DistillTrainer:
    """DAgger collection + Eq. 6 update; one ``step`` is one iteration (the runner's Trainer)."""

    def __init__(self, cfg: DistillConfig, hum: Humanoid, lib: ReferenceLibrary, expert_cfg, expert: ActorCritic,
                 d: Dist | None = None):
        d = d or Dist()
        cfg.prior.check()
        if cfg.action.base != "current":
            raise UserError("a latent prior acts without a reference: action.base must be 'current'")
        if cfg.task.goal_frames != expert_cfg.task.goal_frames:
            raise UserError(f"task.goal_frames={cfg.task.goal_frames} but the expert was trained with "
                            f"{expert_cfg.task.goal_frames}: the goal must be the one the expert reads")
        if getattr(cfg.env, "groups", 1) != 1:
            raise UserError("distillation steps its environments as one group: env.groups must be 1")
        self.cfg, self.hum, self.lib = cfg, hum, lib
        torch.manual_seed(cfg.seed)  # the same initial weights on every rank (the runner reseeds ranks > 0 after)
        self.mdp = m = imitation_mdp(hum, lib, cfg.env, cfg.task, cfg.action, runner.rank_seed(cfg.seed, d.rank))
        device = m.env.torch_device if m.env.on_device else None  # the student and teacher where the rollout is
        parts = body_layout(hum, m.goal_dim) if KINDS[cfg.prior.kind].parts else None
        self.model = LatentPrior(cfg.prior, m.obs_dim, m.goal_dim, m.action_dim, parts).to(device)
        self.expert = expert.eval().requires_grad_(False).to(device)
        if expert.norm.mean.shape[0] != m.obs_dim + m.goal_dim:
            raise UserError(f"the expert reads {expert.norm.mean.shape[0]} inputs, the task gives "
                            f"{m.obs_dim + m.goal_dim}: another humanoid or goal?")
        self.params = list(self.model.parameters())  # the normaliser and EMA codebooks are buffers
        self.opt = torch.optim.Adam(self.params, lr=cfg.lr)
        self.collector = DaggerCollector(m, self.model, self.expert, expert_cfg.action, cfg.horizon,
                                         cfg.action_noise, cfg.action.scale)
        self.alpha = cfg.loss.reg if cfg.loss.reg is not None else KINDS[cfg.prior.kind].reg
        self.samples_per_iteration = cfg.horizon * m.num_envs * d.world
        self.iteration, self.samples, self.wall = 0, 0, 0.0

    # ------------------------------------------------------------------ state
    def model_state(self) -> dict[str, torch.Tensor]:
        return {f"model.{k}": v for k, v in self.model.state_dict().items()}

    def train_state(self) -> dict:
        return {**runner.counters(self), "opt": self.opt.state_dict()}

    def rank_state(self) -> dict:
        return runner.task_rng_state(self.mdp)

    def load(self, model: dict, shared: dict | None, rank: dict | None) -> None:
        self.model.load_state_dict(runs.split_state(model, "model."))
        if shared is not None:
            runner.load_shared(self, shared, rank, opt=self.opt)

    def start_segment(self) -> None:
        self.collector.start()

    def spec(self) -> dict:
        e, m = self.mdp.env, self.hum.model
        return {"obs_dim": e.obs_dim, "goal_dim": self.mdp.goal_dim, "action_dim": e.action_dim,
                "action": {"kind": "residual PD target offsets (rad): q_hat = q + scale * a", "base": "current",
                           "scale": self.cfg.action.scale, "actuators": list(self.hum.layout.hinge_names),
                           "ctrl_range": m.actuator_ctrlrange.tolist()},
                "observation": "posterior: Eq. 7 s then Eq. 9 goal; prior and decoder: s; normalised by "
                               "model.norm.{mean,var,count} (the first obs_dim entries for s)",
                "normaliser": ["model.norm.mean", "model.norm.var", "model.norm.count"],
                "control_hz": e.control_hz, "prior": self.model.spec(), "clips": list(self.lib.names)}

    # ------------------------------------------------------------------ one iteration
    def weights(self) -> dict[str, float]:
        c, it = self.cfg, self.iteration
        return {"action": c.loss.action, "reg": self.alpha, "commit": c.loss.commit,
                "mm": c.loss.mm.at(it, c.iterations), "kl": c.loss.kl.at(it, c.iterations), "part": c.loss.part}

    def update(self, b: DaggerBatch) -> dict:
        c, model = self.cfg, self.model
        model.train()
        T, N = b.labels.shape[:2]
        n = max(1, min(N, c.minibatch_size // T))
        w = self.weights()
        done, synced = b.done, world_size() > 1
        sums: dict[str, float] = {}
        steps, reset, active = 0, 0, 0
        for _ in range(c.epochs):
            perm = torch.randperm(N).to(b.x.device)
            for i in range(0, N - n + 1, n):  # a ragged last minibatch would be noisier: dropped
                cols = perm[i:i + n]
                out = model(model.norm(b.x[:, cols].flatten(0, 1)))
                loss, terms = distill_loss(out, b.labels[:, cols].flatten(0, 1), T, done[:, cols], w)
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                if synced:
                    average_gradients(self.params)
                gn = torch.nn.utils.clip_grad_norm_(self.params, c.max_grad_norm)
                self.opt.step()
                for k, v in {**terms, "loss": loss, "grad_norm": gn}.items():
                    sums[k] = sums.get(k, 0.0) + float(v.detach())
                reset += sum(out.stats.get("dead", []))
                active += out.stats.get("num_active_codebooks", 0)
                steps += 1
        caps = model.caps
        out = {k: v / max(steps, 1) for k, v in sums.items()
               if k in ("action_loss", "reg_loss", "loss", "grad_norm") or k in caps.losses}
        if caps.schedule is not None:
            out[f"w_{caps.schedule}"] = w[caps.schedule]
        if model.quantizer is not None:
            out.update(codes_reset=reset, active_codebooks=active / max(steps, 1))
        return out

    def step(self) -> dict:
        return runner.timed_step(self, self.collector.collect, self.update)


# ---------------------------------------------------------------------- entry points

def expert_record(expert_run) -> dict:
    """The expert a prior was distilled from, for the bundle's metadata (:func:`runs.link_record`),
    with its action map (what the label conversion needs)."""
    rec = runs.link_record("expert", expert_run, EXPERT_KIND)
    cfg = read_meta(expert_run, EXPERT_KIND)["config"]["action"]
    rec["expert_info"]["action"] = {"base": cfg["base"], "scale": cfg["scale"]}
    return rec


def expert_path(run, meta: dict) -> Path:
    """Where the prior bundle ``run``'s expert is: relative to the bundle first, then absolute."""
    return runs.linked_path(run, meta, "expert")


def train(cfg: DistillConfig, run, expert_run, lib: ReferenceLibrary, *, resume: bool = False,
          until: int | None = None, data=None, command: str | None = None) -> dict:
    """Distil the expert in ``expert_run`` into a ``cfg.prior.kind`` prior in ``run`` on the clips of ``lib``."""
    ecfg, hum, expert, _ = load_expert(expert_run)
    cfg.env.same_world(ecfg.env, f"the expert {expert_run}", hum.control_hz)
    names = subset(lib.names, cfg.eval_per_group) if cfg.eval_per_group else list(lib.names)
    ids = np.array([lib.index(x) for x in names])

    def eval_hook(tr: DistillTrainer) -> dict:
        return eval_metrics(evaluate(hum, StudentPolicy(tr.model), lib, cfg.env, cfg.task, cfg.action, clips=ids,
                                     batch=cfg.eval_batch, feet=True))

    return runner.train(lambda d: DistillTrainer(cfg, hum, lib, ecfg, expert, d), cfg, run, hum, kind=KIND,
                        resume=resume, until=until, data=data, command=command,
                        extra=expert_record(expert_run), evaluate=eval_hook,
                        label=f"distill {cfg.prior.kind}", fields=BAR, summary_keys=SUMMARY)


def train_from_expert(cfg: DistillConfig, expert_run, run, *, prior: str | None = None, data=None,
                      clips: str | None = None, split: str | None = None, resume: bool = False,
                      until: int | None = None) -> dict:
    """``motok control distill``: the prior kind (``prior``, which must agree with the recipe's
    if it names one), the expert's humanoid and clips (or the clips of ``data`` matching
    ``clips``/``split``), then :func:`train`."""
    if prior is not None and prior not in KINDS:
        raise UserError(f"--kind must be one of {', '.join(KINDS)}, not {prior!r}")
    expert_run, run = Path(expert_run), Path(run)
    saved = runs.resumed_meta(run, KIND, resume)  # before the recipe's kind: a resume's config is the run's
    if saved is not None and saved["extra"]["prior"]["kind"] != (prior or cfg.prior.kind):
        raise UserError(f"{run} holds a {saved['extra']['prior']['kind']!r} prior; cannot resume it as "
                        f"{prior or cfg.prior.kind!r}")
    if prior and cfg.prior.kind and cfg.prior.kind != prior:
        raise UserError(f"the recipe is for a {cfg.prior.kind!r} prior, not {prior!r}")
    cfg.prior.kind = prior or cfg.prior.kind
    cfg.prior.check()
    hum = load_humanoid(expert_run / "humanoid.xml")
    emeta = read_meta(expert_run, EXPERT_KIND)
    # The expert's world (control rate, target filter) unless the recipe sets it, another refused
    # before the library is built at that rate; train() holds it again for callers from Python.
    cfg.env.same_world(from_dict(SimConfig, emeta["config"].get("env", {})), f"the expert {expert_run}",
                       hum.control_hz)
    src, lib = runs.run_library(expert_run, emeta, hum, cfg.env.control_hz, data, clips, split)
    return train(cfg, run, expert_run, lib, resume=resume, until=until, data=src)
