"""Trained controllers for inference: what tracking, evaluation and text to physics drive.

A :class:`Controller` is an expert run or a distilled prior, named by its parts rather than read
by position: the recipe it was trained with (its ``env``, ``task`` and ``action`` sections say how
it acts), the humanoid, the policy (``act(x_raw, deterministic) -> (xn, a, logp, v)``, as an
actor-critic), the bundle's metadata, and for a prior its model. A prior acts through its
posterior and decoder (:class:`StudentPolicy`), optionally with its first ``M`` codebooks only;
:func:`check_codebooks` is the one place that says which ``M`` a prior takes."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from motok.control.expert.model import load_expert
from motok.control.priors.model import LatentPrior, load_prior
from motok.errors import UserError
from motok.sim.humanoid import Humanoid


@dataclass(repr=False)
class Controller:
    """A trained policy ready to drive the humanoid."""

    cfg: object  # the recipe it was trained with (ExpertConfig or DistillConfig): env, task, action
    humanoid: Humanoid
    policy: object  # act(x_raw, deterministic) -> (xn, a, logp, v), as an actor-critic
    meta: dict  # the bundle's metadata (kind, weights hash, extra)
    prior: LatentPrior | None = None  # the distilled prior the policy decodes with (None for an expert)

    def __repr__(self) -> str:  # the fields hold whole networks and recipes
        what = f"a {self.prior.kind} prior" if self.prior is not None else "an expert"
        return (f"Controller({what}, {self.humanoid.skeleton.num_joints} joints, "
                f"iteration {self.meta.get('extra', {}).get('iteration')})")


class StudentPolicy:
    """The student as :func:`motok.control.tasks.imitation.evaluate` expects an actor-critic:
    ``act(x_raw, deterministic) -> (xn, a, logp, v)`` (``logp`` and ``v`` are zeros). Evaluation
    runs the model in eval mode, so no codebook changes and, deterministic, no random draws;
    ``num_codebooks`` decodes with the first M codebooks only."""

    def __init__(self, model: LatentPrior, num_codebooks: int | None = None):
        self.model, self.num_codebooks = model, num_codebooks

    def parameters(self):
        return self.model.parameters()

    @torch.no_grad()
    def act(self, x: torch.Tensor, deterministic: bool = True):
        m = self.model
        m.eval()
        xn = m.norm(x)
        a = m(xn, self.num_codebooks, sample=not deterministic).action
        zero = torch.zeros(len(x), device=x.device)
        return xn, a, zero, zero


def check_codebooks(model: LatentPrior, codebooks: int | None, prior_alone: bool = True) -> int:
    """M, the codebooks to use (all by default); 0 for the continuous prior. ``prior_alone``: M = 0
    is allowed where there is a prior network (``z_bar = z_p(s)``, for generation and task
    learning); decoding a posterior's codes needs at least one codebook."""
    n = model.num_codebooks
    if model.quantizer is None:
        if codebooks is not None:
            raise UserError("the continuous prior has no codebooks: leave out --codebooks")
        return 0
    if codebooks is None:
        return n
    if codebooks == 0 and prior_alone and model.prior is not None:
        return 0
    if not 1 <= codebooks <= n:
        alone = " (or 0: the prior's z_p alone)" if prior_alone and model.prior is not None else ""
        raise UserError(f"--codebooks must be in 1..{n}{alone} for this {model.kind} prior")
    return codebooks


def load_controller(expert=None, prior=None, codebooks: int | None = None) -> Controller:
    """The :class:`Controller` of an expert run, or of a distilled prior's posterior and decoder
    (acting on the current pose; the first ``codebooks`` only)."""
    if (expert is None) == (prior is None):
        raise UserError("track with one controller: --expert RUN or --prior PRIOR")
    if expert is not None:
        if codebooks is not None:  # an expert's action has no codebooks: taking it would change nothing
            raise UserError(f"--codebooks {codebooks}: selects a prior's codebooks; the expert {expert} has none")
        cfg, hum, ac, meta = load_expert(expert)
        return Controller(cfg, hum, ac, meta)
    cfg, hum, model, meta = load_prior(prior)
    if codebooks is not None:
        check_codebooks(model, codebooks, prior_alone=False)
    return Controller(cfg, hum, StudentPolicy(model, codebooks), meta, model)
