"""How far the soles slide: the foot geometry's own skating, for simulated and reference bodies alike.

The kinematic skating measure (``motok.eval.physical``) follows a joint, the toe, and counts it as
in contact while it is within 1 cm of its resting height. A simulated foot that rocks on its sole
keeps its toe joint a few centimetres up through the stance, so that measure sees little contact
and cannot say whether the part of the foot that does touch the floor holds still. This one follows
the material points that touch: the bottom corners of every box geom (the humanoid's feet and toes,
``motok.sim.mjcf``). A corner is in contact while it is at most ``tolerance`` above the floor (at or
below it counts too: reference poses reach into the floor); between two consecutive states where
it is in contact at both, its slip is its horizontal displacement over the time step. A planted
foot, or one rolling over an edge, moves its touching corners by nothing; a sliding one by its speed.

Everything is computed on whole ``(N, T, J, .)`` arrays of body positions and rotations (no MuJoCo
call, no loop over frames), from the bodies a rollout already has (``HumanoidEnv.bodies``) or a
reference library holds (``body_pos``, ``body_quat``), so simulation and reference are measured by
the same code at the same rate.

:func:`sole_state` is the per-state form the AMP discriminator can see (``amp.feet``): per foot,
the height of its lowest corner and that corner's horizontal speed, from one state's body
positions, rotations and velocities, for a simulated state and a reference frame alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.arrays import like, take_along, xp
from motok.rotations import quat_to_matrix
from motok.sim.obs import cross3

BOX = 6  # mujoco.mjtGeom.mjGEOM_BOX
TOLERANCE = 0.01  # m above the floor that still counts as touching (the kinematic measure's 1 cm)
SLIP_SPEED = 0.05  # m/s: a corner step faster than this counts as sliding (the kinematic measure's threshold)


@dataclass(frozen=True)
class Soles:
    """The bottom corners of the humanoid's box geoms: ``joint`` ``(K,)`` the skeleton index of each
    corner's body and ``offset`` ``(K, 3)`` the corner in that body's frame."""

    joint: np.ndarray
    offset: np.ndarray

    def world(self, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """Corner positions ``(..., K, 3)`` from body positions ``(..., J, 3)`` and rotations
        ``(..., J, 3, 3)`` (body to world)."""
        return pos[..., self.joint, :] + np.einsum("...kij,kj->...ki", rot[..., self.joint, :, :], self.offset)


def soles(hum) -> Soles:
    """The four lowest corners (in the body frame's -z, MuJoCo's up) of each box geom of ``hum``."""
    m = hum.model
    skeleton_of = {int(b): j for j, b in enumerate(hum.body_ids)}
    joints, offsets = [], []
    for g in np.flatnonzero(m.geom_type == BOX):
        body = int(m.geom_bodyid[g])
        if body not in skeleton_of:
            continue
        sx, sy, sz = m.geom_size[g]
        corners = np.array([[x, y, -sz] for x in (-sx, sx) for y in (-sy, sy)])
        r = quat_to_matrix(np.asarray(m.geom_quat[g], np.float64))
        offsets.append(m.geom_pos[g] + corners @ r.T)
        joints += [skeleton_of[body]] * 4
    if not joints:
        raise ValueError("the humanoid has no box geoms: nothing to measure sole slip on")
    return Soles(np.asarray(joints), np.concatenate(offsets))


def foot_corners(sole: Soles, skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Indices of ``sole``'s corners on the left and on the right foot (the corners of the bodies
    ``skeleton.feet_left`` / ``feet_right``: ankle and toes)."""
    out = tuple(np.flatnonzero(np.isin(sole.joint, list(f))) for f in (skeleton.feet_left, skeleton.feet_right))
    if not all(len(f) for f in out):
        raise ValueError("a foot of the humanoid has no box geom: no sole to describe")
    return out


def sole_state(sole: Soles, feet, pos, rot, vel, angvel):
    """``(..., 2 len(feet))``: for each foot (corner indices ``feet``, :func:`foot_corners`), the
    height above the floor (m, MuJoCo's z) of its lowest corner, then that corner's horizontal speed
    (m/s), from body positions ``(..., J, 3)``, rotations ``(..., J, 3, 3)``, linear and angular
    velocities (world frame; numpy or torch). A corner's velocity is its body's linear velocity plus
    ``angvel x (R offset)``: a state's own quantities, so a transition's two states each carry
    theirs, and the corner that touches while a foot rolls over an edge moves at nothing."""
    x = xp(pos)
    j = like(pos, sole.joint) if x is not np else sole.joint
    r = x.einsum("...kij,kj->...ki", rot[..., j, :, :], like(pos, sole.offset))
    height = pos[..., j, 2] + r[..., 2]
    v = vel[..., j, :] + cross3(angvel[..., j, :], r)
    speed = x.hypot(v[..., 0], v[..., 1])
    out = []
    for f in feet:
        f = like(pos, f) if x is not np else f
        low = height[..., f].argmin(-1)[..., None]  # the foot's lowest corner
        out += [take_along(height[..., f], low, -1)[..., 0], take_along(speed[..., f], low, -1)[..., 0]]
    return x.stack(out, -1)


@dataclass
class SlipSums:
    """Additive sums over clips: corner steps in contact, their summed slip (m/s) and those above
    :data:`SLIP_SPEED`, and the corner steps looked at."""

    slip: float = 0.0
    contact: int = 0
    fast: int = 0
    steps: int = 0
    depth: float = 0.0  # summed depth (m) below the floor of the lowest corner, over the states looked at
    states: int = 0

    def add(self, other: "SlipSums") -> "SlipSums":
        for k in self.__dataclass_fields__:
            setattr(self, k, getattr(self, k) + getattr(other, k))
        return self

    def result(self) -> dict:
        c = self.contact
        return {"sole_slip_cm_s": 100 * self.slip / c if c else float("nan"),
                "sole_slip_ratio": self.fast / c if c else float("nan"),
                "sole_contact_fraction": c / self.steps if self.steps else float("nan"),
                "sole_penetration_mm": 1000 * self.depth / self.states if self.states else float("nan")}


def slip_sums(corners: np.ndarray, dt: float, valid: np.ndarray | None = None,
              tolerance: float = TOLERANCE) -> SlipSums:
    """Sums of one or many clips of corner positions ``(..., T, K, 3)`` (MuJoCo frame, z up) sampled
    every ``dt`` seconds; ``valid`` ``(..., T)`` marks the states that belong to a clip (a step counts
    when both its states do). Penetration: how deep the lowest corner is below the floor, per state
    (0 when above it), the geometry's measure, since a simulated body's joints never reach the floor."""
    c = np.asarray(corners, np.float64)
    touch = c[..., 2] <= tolerance  # (..., T, K)
    pair = touch[..., :-1, :] & touch[..., 1:, :]
    valid = np.ones(c.shape[:-2], bool) if valid is None else np.asarray(valid, bool)
    both = (valid[..., :-1] & valid[..., 1:])[..., None]
    pair &= both
    speed = np.linalg.norm(np.diff(c[..., :2], axis=-3), axis=-1) / dt
    depth = np.maximum(-c[..., 2].min(-1), 0.0)  # (..., T)
    return SlipSums(slip=float(speed[pair].sum()), contact=int(pair.sum()), fast=int((speed[pair] > SLIP_SPEED).sum()),
                    steps=int(np.broadcast_to(both, pair.shape).sum()), depth=float(depth[valid].sum()),
                    states=int(valid.sum()))


def reference_corners(sole: Soles, body_pos: np.ndarray, body_quat: np.ndarray) -> np.ndarray:
    """Corners of reference frames from a library's ``body_pos`` and ``body_quat`` (w, x, y, z)."""
    return sole.world(np.asarray(body_pos, np.float64), quat_to_matrix(np.asarray(body_quat, np.float64)))


def floor_contacts(m, d, feet: np.ndarray) -> np.ndarray:
    """The contacts between the geoms marked in ``feet`` ``(ngeom,)`` and the world's (the floor), at
    ``d``'s state after ``mj_forward`` (or ``mj_step``, whose contacts and velocities are those of the
    state it started from): rows ``(normal force N, friction force N, slip speed m/s, distance m,
    geom)``. The slip is the horizontal velocity of the foot's material point at the contact
    (``mj_objectVelocity`` of the geom, moved to the contact point), the floor being static."""
    import mujoco

    rows, f6, v6 = [], np.zeros(6), np.zeros(6)
    for i in range(d.ncon):
        c = d.contact[i]
        g1, g2 = int(c.geom1), int(c.geom2)
        g = g1 if m.geom_bodyid[g2] == 0 and feet[g1] else g2 if m.geom_bodyid[g1] == 0 and feet[g2] else -1
        if g < 0 or c.efc_address < 0:  # not a foot on the floor, or excluded from the constraints
            continue
        mujoco.mj_contactForce(m, d, i, f6)
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_GEOM, g, v6, 0)  # [angular, linear], world axes
        v = v6[3:] + np.cross(v6[:3], c.pos - d.geom_xpos[g])
        rows.append((f6[0], np.hypot(f6[1], f6[2]), np.hypot(v[0], v[1]), c.dist, g))
    return np.asarray(rows, np.float64).reshape(-1, 5)


def contact_runs(flags: np.ndarray) -> np.ndarray:
    """Lengths (in samples) of the uninterrupted contacts in each column of ``flags`` ``(T, G)``
    (whether geom ``g`` touches at sample ``t``), column after column."""
    f = np.pad(np.asarray(flags, np.int8), ((1, 1), (0, 0)))
    edges = np.diff(f, axis=0).T  # (G, T + 1): +1 where a contact starts, -1 after it ends
    starts, ends = np.nonzero(edges == 1), np.nonzero(edges == -1)
    return ends[1] - starts[1]


HOLD, SLIDE = (0.1, 0.8, 0.2, 0.9), (0.95, 0.1, 0.1, 0.9)  # marker colours: green holds, red slides


def contact_markers(corners: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a video draws of sole corners ``(T, K, 3)`` (MuJoCo world, z up): marker positions
    ``(T, K, 3)`` (NaN where a corner is off the floor: not drawn), colours ``(T, K, 4)`` (:data:`SLIDE`
    where the corner touched at the last state too and moved faster than :data:`SLIP_SPEED` since,
    else :data:`HOLD`)
    and the running sole slip in cm/s: over the steps so far where the corner touched at both
    ends, as :func:`slip_sums` counts it."""
    down = corners[..., 2] <= TOLERANCE
    step = np.zeros(down.shape)
    step[1:] = np.linalg.norm(corners[1:, :, :2] - corners[:-1, :, :2], axis=-1) / dt
    both = down.copy()
    both[1:] &= down[:-1]
    both[0] = False
    rgba = np.where(((step > SLIP_SPEED) & both)[..., None], SLIDE, HOLD).astype(np.float32)
    pos = np.where(down[..., None], corners, np.nan)
    n = np.cumsum(both.sum(1))
    running = 100 * np.cumsum((step * both).sum(1)) / np.maximum(n, 1)
    return pos, rgba, running
