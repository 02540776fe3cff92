"""Action maps: a policy's output -> PD targets ``(N, nu)`` for ``HumanoidEnv.step``.

* ``current``: ``q_hat = q + scale a``, residual on the current hinge angles (the hybrid-latent
  paper's code, and the only choice for a policy with no reference motion);
* ``reference``: ``q_hat = q_ref' + (kv / kp) qd_ref' + scale a``, residual on the next reference
  frame with a velocity lead, so a zero action is PD tracking of the reference's angles *and*
  velocities (the usual residual form for imitation experts; exploration noise does not
  accumulate). The reference comes from the task (:meth:`next_reference`).

A frozen latent decoder (the priors' low-level policy) is one more map of the same shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.arrays import is_tensor
from motok.errors import UserError
from motok.ranges import In

BASES = ("current", "reference")


@dataclass
class ActionConfig:
    base: str = "current"  # what the action is a residual on: current | reference
    scale: In[float, "> 0"] = 1.0  # PD target offset (rad) per unit of action

    def __post_init__(self):
        if self.base not in BASES:
            raise UserError(f"action base must be 'current' or 'reference', not {self.base!r}")


def residual_targets(a, base, scale: float):
    """``base + scale a``: host actions in float64 (C MuJoCo's precision), device ones as they are."""
    return base + scale * (a if is_tensor(a) else np.asarray(a, dtype=np.float64))


def reference_base(env, ref_qpos, ref_qvel):
    """``(N, nu)`` reference hinge angles plus the velocity lead ``(kv / kp) qd_ref``."""
    return ref_qpos[:, env.hinge_adr] + env.velocity_lead * ref_qvel[:, env.hinge_dof]


def pd_targets(cfg: ActionConfig, a, env, task):
    """The map named by ``cfg.base``; ``task.next_reference()`` gives ``(qpos, qvel)`` for ``reference``."""
    if cfg.base == "current":
        return residual_targets(a, env.qpos[:, env.hinge_adr], cfg.scale)
    return residual_targets(a, reference_base(env, *task.next_reference()), cfg.scale)
