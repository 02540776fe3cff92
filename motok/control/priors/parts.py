"""Body parts of the part-wise hybrid prior (``hybrid-parts``): which bodies, goal entries and
actuators belong to the lower body and which to the upper body, read from the humanoid's skeleton
(its tree and its declared feet), never from joint indices or names written here.

The lower body is the root and every subtree of the root that holds a foot (the legs); the upper
body is every other subtree of the root (spine, chest, neck, head, arms). The root goes with the
legs: its motion is what the legs produce.
"""

from __future__ import annotations

import numpy as np

from motok.errors import UserError
from motok.skeleton import Skeleton

PART_NAMES = ("lower", "upper")  # group g of the margin is PART_NAMES[g]
GOAL_PER_BODY = 15  # Eq. 9 per body and goal frame: position 3, rotation 6 (two columns), velocity 3, angular velocity 3


def body_parts(skeleton: Skeleton) -> np.ndarray:
    """``(J,)`` part index of every body: 0 lower (root and the subtrees holding a foot), 1 upper."""
    parents = np.asarray(skeleton.parents)
    root = int(np.flatnonzero(parents < 0)[0])

    def branch(j: int) -> int:  # the child of the root whose subtree holds j
        while parents[j] != root:
            j = int(parents[j])
        return j

    legs = {branch(f) for f in (*skeleton.feet_left, *skeleton.feet_right)}
    part = np.array([0 if j == root or branch(j) in legs else 1 for j in range(len(parents))])
    if part.min() == part.max():
        raise UserError(f"skeleton {skeleton.name!r}: no upper body apart from the legs' subtrees")
    return part


def goal_parts(skeleton: Skeleton, goal_dim: int) -> np.ndarray:
    """``(goal_dim,)`` part of every entry of the imitation goal, laid out ``(K, J, 15)`` (Eq. 9)."""
    J = skeleton.num_joints
    if goal_dim % (J * GOAL_PER_BODY):
        raise UserError(f"a goal of {goal_dim} entries is not Eq. 9's {GOAL_PER_BODY} per body of {J} bodies")
    return np.tile(np.repeat(body_parts(skeleton), GOAL_PER_BODY), goal_dim // (J * GOAL_PER_BODY))


def body_layout(hum, goal_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """``(goal_parts, action_parts)``: what ``LatentPrior(..., parts=)`` takes."""
    return goal_parts(hum.skeleton, goal_dim), action_parts(hum)


def action_parts(hum) -> np.ndarray:
    """``(action_dim,)`` part of every actuator: its joint's (hinges in joint order, as the actions)."""
    part = body_parts(hum.skeleton)
    return np.repeat(part, [len(a) for a in hum.qpos_adr])


def part_selectivity(model, s, indices, actuator_parts, draws: int = 8, seed: int = 0):
    """How much each group's codes move each body part's actuators: ``S[g, p]``, the mean squared
    change of the decoder's action per actuator of part p when the codes of group g are redrawn
    uniformly (every other column kept), from ``z_bar`` decoded from ``indices`` (all codebooks) at
    normalised states ``s``. A part-wise prior wants a large diagonal: lower-body codes move the
    legs, upper-body codes the arms and head. Any grouped prior can be measured (``hybrid-grvq``:
    the same groups with no tie to the parts, the control)."""
    import torch

    q, m = model.quantizer, model.num_codebooks
    groups, act = q.column_groups(m), torch.as_tensor(actuator_parts)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        a0 = model.decode(s, model.codes_to_latent(s, indices, m))
        out = torch.zeros(int(groups.max()) + 1, int(act.max()) + 1)
        for g in range(len(out)):
            for _ in range(draws):
                idx = indices.clone()
                cols = torch.nonzero(groups == g).flatten()
                idx[:, cols] = torch.randint(q.codebook_size, (len(idx), len(cols)), generator=gen)
                change = (model.decode(s, model.codes_to_latent(s, idx, m)) - a0) ** 2
                out[g] += torch.stack([change[:, act == p].mean() for p in range(out.shape[1])]) / draws
    return out.numpy()
