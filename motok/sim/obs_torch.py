"""Eq. 7 in torch: the observation of :mod:`motok.sim.obs`, formula for formula, on tensors of any
device, so a GPU rollout computes it where MuJoCo Warp keeps the state (``WarpStepper.qpos_t``,
``qvel_t`` and ``bodies_tensor()``) without a host copy. tests/test_warp.py checks it against the
numpy version. The first piece of the on-device path docs/sim.md describes; goals, rewards and
resets are still numpy.
"""

from __future__ import annotations

import torch

from motok.sim.obs import Bodies


def heading(root_rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosine and sine of the yaw of the root's forward (+X) axis (as ``obs.heading``)."""
    fx, fy = root_rot[..., 0, 0], root_rot[..., 1, 0]
    n = torch.clamp(torch.hypot(fx, fy), min=1e-9)  # the forward axis pointing straight up has no heading
    return fx / n, fy / n


def unyaw(c: torch.Tensor, s: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``(..., 3)`` by minus the heading (as ``obs.unyaw``)."""
    x, y = v[..., 0], v[..., 1]
    return torch.stack([c * x + s * y, c * y - s * x, v[..., 2]], -1)


def observation(qpos: torch.Tensor, qvel: torch.Tensor, bodies: Bodies, end_effectors) -> torch.Tensor:
    """Eq. 7, ``(N, 1 + 6 + 3 + 3 + 2H + 3E)``, from tensor body states (``bodies.rot`` given)."""
    N = len(qpos)
    root = bodies.rot[:, 0]
    c, s = heading(root)
    c, s = c[:, None], s[:, None]
    six = unyaw(c, s, torch.stack([root[..., 0], root[..., 1]], 1)).reshape(N, 6)
    ee = list(end_effectors)
    vecs = torch.cat([bodies.vel[:, :1], bodies.angvel[:, :1], bodies.pos[:, ee] - bodies.pos[:, :1]], 1)
    vecs = unyaw(c, s, vecs).reshape(N, -1)
    return torch.cat([bodies.pos[:, 0, 2:3], six, vecs[:, :6], qpos[:, 7:], qvel[:, 6:], vecs[:, 6:]], -1)
