"""Thrown balls: a pool of free sphere bodies added to a motok humanoid, for the perturbation test
of the hybrid-latent paper (Bae et al. 2025, section 6.3.3: spheres of 10 cm radius and 4.2 kg
thrown every 0.3 s at 10-20 m/s from a random point 1 m from the character).

MuJoCo cannot add bodies to a compiled model, so :func:`build_ball_model` writes a variant of a
humanoid's MJCF with ``count`` balls appended *after* the humanoid in ``<worldbody>``: the
humanoid's state stays the prefix ``qpos[:, :hum.nq]`` / ``qvel[:, :hum.nv]`` (checked by
:func:`motok.sim.humanoid.load_humanoid`) and :class:`motok.sim.env.HumanoidEnv` observes, drives
and resets the humanoid exactly as on the plain model. Each ball is a free joint and a sphere geom
with ``contype 0, conaffinity 1``: MuJoCo lets two geoms touch when ``(contype1 & conaffinity2) |
(contype2 & conaffinity1)`` is non-zero, and every humanoid geom and the floor carry bit 0 in
``contype`` (:data:`motok.sim.mjcf.FLOOR`), so a ball hits the humanoid and the floor but never
another ball. An idle ball rests on the floor far from the character (:func:`park_positions`).

Balls are moved through the stepper (:func:`set_balls`, ``Stepper.set_columns``), which keeps the
humanoid's solver warm start; :func:`launch_balls` is the throw's geometry, a pure function, and
:func:`detect_hits` tells ball-humanoid contacts apart from ball-floor ones (docstring there).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from motok.atomic import atomic_path
from motok.errors import UserError
from motok.rotations import quat_to_matrix
from motok.sim.humanoid import Humanoid, load_humanoid
from motok.sim.obs import Bodies

META_NAME = "motok_balls"
PREFIX = "motok_ball_"  # body, joint and geom names: "motok_ball_3"
PARK_XY = (1000.0, 1000.0)  # m: idle balls lie here, 1 m apart, far beyond any episode's walk
RGBA = ".25 .45 .85 1"


# ----------------------------------------------------------------------------- the model

def park_positions(count: int, radius: float) -> np.ndarray:
    """``(count, 3)``: where idle balls rest, on the floor. Resting rather than floating: a ball
    parked in the air falls, and one parked under the floor is inside its half-space and is
    thrown out; a resting ball costs one floor contact and stays where it is."""
    k = np.arange(count, dtype=np.float64)
    return np.stack([PARK_XY[0] + k, np.full(count, PARK_XY[1]), np.full(count, float(radius))], -1)


def build_ball_model(humanoid: Humanoid | str | Path, out, count: int, radius: float = 0.1,
                     mass: float = 4.2) -> Path:
    """Write ``humanoid``'s MJCF (a :class:`Humanoid` loaded from a file, or a path) with ``count``
    balls (sphere ``radius`` m, ``mass`` kg) after it, parked; returns ``out``. Load it with
    :func:`motok.sim.humanoid.load_humanoid`; the balls' layout is :func:`find_balls`."""
    src = humanoid.path if isinstance(humanoid, Humanoid) else Path(humanoid)
    if src is None:
        raise UserError("build_ball_model needs a humanoid loaded from a file (Humanoid.path is None)")
    if int(count) < 1 or not radius > 0 or not mass > 0:
        raise UserError(f"balls: need count >= 1, radius > 0 and mass > 0, got {count}, {radius}, {mass}")
    hum = load_humanoid(src)  # one-line errors for anything that is not a motok humanoid
    import mujoco

    if mujoco.mj_name2id(hum.model, mujoco.mjtObj.mjOBJ_TEXT, META_NAME) >= 0:
        raise UserError(f"{src}: already has balls; build from the plain humanoid")
    root = ET.fromstring(Path(src).read_text())
    ET.SubElement(root.find("asset"), "material", name=PREFIX + "material", rgba=RGBA)
    world = root.find("worldbody")
    for k, p in enumerate(park_positions(count, radius)):
        b = ET.SubElement(world, "body", name=f"{PREFIX}{k}", pos=" ".join(f"{x:.9g}" for x in p))
        ET.SubElement(b, "freejoint", name=f"{PREFIX}{k}")  # a freejoint takes no defaults: no armature
        ET.SubElement(b, "geom", name=f"{PREFIX}{k}", type="sphere", size=f"{radius:.9g}", mass=f"{mass:.9g}",
                      material=PREFIX + "material", contype="0", conaffinity="1")
    meta = {"version": 1, "count": int(count), "radius": float(radius), "mass": float(mass)}
    ET.SubElement(root.find("custom"), "text", name=META_NAME, data=json.dumps(meta))
    # The humanoid's own scale for the renderer: from the parked balls MuJoCo would derive an extent
    # of about 1 km, and with it a near clipping plane 10 m from the camera (z_near = 0.01 extent).
    if root.find("statistic") is None:
        ET.SubElement(root, "statistic", extent=f"{hum.model.stat.extent:.9g}",
                      center=" ".join(f"{x:.9g}" for x in hum.model.stat.center))
    ET.indent(root)
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.write_text(ET.tostring(root, encoding="unicode"))
    built = load_humanoid(out)
    _check_filter(built, find_balls(built.model))
    return out


@dataclass
class BallPool:
    """Where the balls of a model live: body, geom and first qpos/qvel address of each, ``(K,)``."""

    count: int
    radius: float
    mass: float
    body: np.ndarray
    geom: np.ndarray
    qadr: np.ndarray
    vadr: np.ndarray

    @property
    def qcols(self) -> np.ndarray:
        """``(K, 7)`` qpos columns of each ball's free joint: position, then quaternion."""
        return self.qadr[:, None] + np.arange(7)

    @property
    def vcols(self) -> np.ndarray:
        """``(K, 6)`` qvel columns: world linear velocity, then body-frame angular velocity."""
        return self.vadr[:, None] + np.arange(6)

    @property
    def park(self) -> np.ndarray:
        return park_positions(self.count, self.radius)

    def first(self, k: int) -> "BallPool":
        """The pool of the first ``k`` balls (the others stay wherever they are)."""
        if not 1 <= k <= self.count:
            raise UserError(f"balls: the model has {self.count} balls per environment, not {k}")
        return replace(self, count=int(k), body=self.body[:k], geom=self.geom[:k], qadr=self.qadr[:k],
                       vadr=self.vadr[:k])


def find_balls(model) -> BallPool:
    """The balls :func:`build_ball_model` added to ``model`` (an MjModel); ``UserError`` if none."""
    import mujoco

    obj = mujoco.mjtObj
    tid = mujoco.mj_name2id(model, obj.mjOBJ_TEXT, META_NAME)
    if tid < 0:
        raise UserError("this humanoid has no thrown balls: build one with motok.sim.balls.build_ball_model")
    raw = bytes(model.text_data[model.text_adr[tid]:model.text_adr[tid] + model.text_size[tid]]).split(b"\0")[0]
    meta = json.loads(raw.decode())
    K = int(meta["count"])
    body = np.array([mujoco.mj_name2id(model, obj.mjOBJ_BODY, f"{PREFIX}{k}") for k in range(K)])
    geom = np.array([mujoco.mj_name2id(model, obj.mjOBJ_GEOM, f"{PREFIX}{k}") for k in range(K)])
    jnt = np.array([mujoco.mj_name2id(model, obj.mjOBJ_JOINT, f"{PREFIX}{k}") for k in range(K)])
    if (body < 0).any() or (geom < 0).any() or (jnt < 0).any():
        raise UserError(f"the model's ball metadata lists {K} balls but not every {PREFIX}<k> body exists")
    return BallPool(K, float(meta["radius"]), float(meta["mass"]), body, geom,
                    model.jnt_qposadr[jnt].astype(np.int64), model.jnt_dofadr[jnt].astype(np.int64))


def _check_filter(hum: Humanoid, pool: BallPool) -> None:
    """Every ball must touch every humanoid geom and the floor, and no other ball."""
    m = hum.model
    ours = np.isin(m.geom_bodyid, hum.body_ids)
    floor = np.flatnonzero(m.geom_bodyid == 0)
    ct, ca = m.geom_contype, m.geom_conaffinity

    def touch(a, b):
        return ((ct[a][:, None] & ca[b][None]) | (ct[b][None] & ca[a][:, None])) != 0

    if not (touch(pool.geom, np.flatnonzero(ours)).all() and touch(pool.geom, floor).all()) \
            or touch(pool.geom, pool.geom).any():
        raise UserError("balls: the humanoid's contact bits do not let balls hit every body geom "
                        "(each humanoid geom needs bit 0 in contype, as motok.sim.mjcf writes)")


# ----------------------------------------------------------------------------- moving balls

def ball_states(env, pool: BallPool) -> tuple[np.ndarray, np.ndarray]:
    """``(pos, vel)``, each ``(N, K, 3)``: ball centres and linear velocities (world), copies."""
    q, v = env.stepper.qpos, env.stepper.qvel
    return q[:, pool.qcols[:, :3]], v[:, pool.vcols[:, :3]]


def set_balls(env, pool: BallPool, ids, slots, pos, vel) -> None:
    """Put ball ``slots[i]`` of environment ``ids[i]`` at ``pos[i]`` with linear velocity ``vel[i]``
    (no spin, identity orientation), through the stepper: the humanoid's state and solver warm
    start are untouched. ``slots`` may be one int for every row."""
    ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
    slots = np.broadcast_to(np.asarray(slots, dtype=np.int64), ids.shape)
    if len(ids) == 0:
        return
    if slots.min() < 0 or slots.max() >= pool.count:
        raise IndexError(f"ball slots must be in 0..{pool.count - 1}, got {slots.tolist()}")
    n = len(ids)
    q = np.zeros((n, 7))
    q[:, :3], q[:, 3] = np.broadcast_to(pos, (n, 3)), 1.0
    v = np.zeros((n, 6))
    v[:, :3] = np.broadcast_to(vel, (n, 3))
    env.stepper.set_columns(ids, pool.qcols[slots], q, pool.vcols[slots], v)


def park_balls(env, pool: BallPool, ids) -> None:
    """Every ball of environments ``ids`` back to its resting place, still."""
    ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
    K = pool.count
    set_balls(env, pool, np.repeat(ids, K), np.tile(np.arange(K), len(ids)), np.tile(pool.park, (len(ids), 1)), 0.0)


def launch_balls(root_pos, rng: np.random.Generator, distance: float = 1.0, speed=(10.0, 20.0),
                 height_range=(0.5, 1.5), target=None, gravity: float = 9.81) -> tuple[np.ndarray, np.ndarray]:
    """Throws at ``(N, 3)`` characters: ``(start, velocity)``, each ``(N, 3)``.

    Section 6.3.3: a start ``distance`` m from ``root_pos`` *horizontally*, in a uniformly random
    direction, at a height uniform in ``height_range`` (m above the floor); a speed uniform in
    ``speed`` (m/s), aimed at ``target`` (default: the root itself). With ``gravity > 0`` the aim
    is the low ballistic arc through the target at exactly that speed (the drop over 1 m at
    10 m/s is 5 cm); ``gravity=0`` aims in a straight line. Draws, in order: directions,
    heights, speeds.
    """
    root = np.asarray(root_pos, dtype=np.float64).reshape(-1, 3)
    n = len(root)
    aim = root if target is None else np.asarray(target, dtype=np.float64).reshape(n, 3)
    lo, hi = (float(x) for x in speed)
    if not (distance > 0 and 0 < lo <= hi and height_range[0] <= height_range[1] and gravity >= 0):
        raise UserError(f"balls: need distance > 0, 0 < speed[0] <= speed[1], height_range[0] <= "
                        f"height_range[1] and gravity >= 0; got {distance}, {speed}, {height_range}, {gravity}")
    phi = rng.uniform(0.0, 2 * np.pi, n)
    start = np.empty((n, 3))
    start[:, 0], start[:, 1] = root[:, 0] + distance * np.cos(phi), root[:, 1] + distance * np.sin(phi)
    start[:, 2] = rng.uniform(height_range[0], height_range[1], n)
    s = rng.uniform(lo, hi, n)
    d = aim - start
    D = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    H = d[:, 2]
    if gravity > 0:
        disc = s ** 4 - gravity * (gravity * D ** 2 + 2 * H * s ** 2)
        if (disc < 0).any():
            raise UserError(f"balls: a target {D[disc < 0].max():.2f} m away is out of reach at {s[disc < 0].min():.1f} m/s")
        elevation = np.arctan((s ** 2 - np.sqrt(disc)) / (gravity * D))
    else:
        elevation = np.arctan2(H, D)
    vel = np.empty((n, 3))
    vel[:, :2] = (s * np.cos(elevation) / D)[:, None] * d[:, :2]
    vel[:, 2] = s * np.sin(elevation)
    return start, vel


# ----------------------------------------------------------------------------- hits

@dataclass
class Capsules:
    """The humanoid's collision geometry as capsules in body frames: ``body`` (skeleton index),
    segment ends ``a``, ``b`` ``(G, 3)``, ``radius`` ``(G,)``. Spheres are zero-length capsules;
    boxes (feet, toes) the capsule around them along their longest axis, a few mm generous."""

    body: np.ndarray
    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray


def humanoid_capsules(hum: Humanoid) -> Capsules:
    import mujoco

    m = hum.model
    index = {int(b): j for j, b in enumerate(hum.body_ids)}
    gt = mujoco.mjtGeom
    body, a, b, r = [], [], [], []
    for g in np.flatnonzero(np.isin(m.geom_bodyid, hum.body_ids)):
        rot, size, pos = quat_to_matrix(m.geom_quat[g]), m.geom_size[g], m.geom_pos[g]
        t = int(m.geom_type[g])
        if t == gt.mjGEOM_CAPSULE:
            half, rad = rot[:, 2] * size[1], size[0]
        elif t == gt.mjGEOM_BOX:
            order = np.argsort(size)
            half, rad = rot[:, order[2]] * size[order[2]], np.hypot(size[order[0]], size[order[1]])
        else:  # sphere; anything else by its bounding sphere
            half, rad = np.zeros(3), (size[0] if t == gt.mjGEOM_SPHERE else m.geom_rbound[g])
        body.append(index[int(m.geom_bodyid[g])]), a.append(pos - half), b.append(pos + half), r.append(rad)
    return Capsules(np.array(body), np.array(a), np.array(b), np.array(r))


def segment_distance(p0, p1, q0, q1) -> np.ndarray:
    """Shortest distance between segments ``p0-p1`` and ``q0-q1`` (broadcast ``(..., 3)``),
    degenerate (point) segments included (Ericson, Real-Time Collision Detection, 5.1.9)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e = (d1 * d1).sum(-1), (d2 * d2).sum(-1)
    b, c, f = (d1 * d2).sum(-1), (d1 * r).sum(-1), (d2 * r).sum(-1)
    eps = 1e-12
    safe = lambda x: np.where(x > eps, x, 1.0)  # noqa: E731  (the masked-out lanes divide by 1)
    denom = a * e - b * b
    s = np.where(denom > eps, np.clip((b * f - c * e) / safe(denom), 0.0, 1.0), 0.0)  # parallel: any s, take 0
    t = (b * s + f) / safe(e)
    s_end = np.clip(-c / safe(a), 0.0, 1.0)  # closest point of p's segment to q0 (t clamped to 0)
    s = np.where(e > eps, np.where(t < 0, s_end, np.where(t > 1, np.clip((b - c) / safe(a), 0.0, 1.0), s)), s_end)
    t = np.where(e > eps, np.clip(t, 0.0, 1.0), 0.0)
    s, t = np.where(a > eps, s, 0.0), np.where(a > eps, t, np.where(e > eps, np.clip(f / safe(e), 0.0, 1.0), 0.0))
    return np.linalg.norm(p0 + d1 * s[..., None] - q0 - d2 * t[..., None], axis=-1)


def world_capsules(caps: Capsules, bodies: Bodies) -> tuple[np.ndarray, np.ndarray]:
    """Segment ends ``(N, G, 3)`` of the capsules at the body states ``bodies``."""
    rot, pos = bodies.rot[:, caps.body], bodies.pos[:, caps.body]
    return pos + np.einsum("ngij,gj->ngi", rot, caps.a), pos + np.einsum("ngij,gj->ngi", rot, caps.b)


def detect_hits(pool: BallPool, caps: Capsules, before: tuple, after: tuple, bodies_before: Bodies,
                bodies_after: Bodies, gravity: np.ndarray, dt: float, min_dv: float = 0.05,
                slack: float = 0.05) -> np.ndarray:
    """``(N, K)``: which balls touched the humanoid during the control step from ``before`` to
    ``after`` (``(pos, vel)`` of :func:`ball_states`).

    Neither stepper can say: ``mujoco.batch`` cannot bind MjData's contact list (an arena array),
    and contacts read at the end of a control step would miss a hit that begins and ends within
    its 4 substeps. A ball in flight has nothing but gravity acting on it, so its velocity changes
    by exactly ``g dt``: a change that differs by more than ``min_dv`` (m/s) means a contact
    somewhere in the step, with the floor or the humanoid. It is the humanoid's if the ball's path
    over the step (the segment between its two positions) came within ``slack`` (m) of a humanoid
    capsule, at the body states before or after the step. Misses: a contact below ``min_dv`` (a
    0.2 N s graze). False hits: a floor bounce within ``slack`` of a foot.
    """
    (p0, v0), (p1, v1) = before, after
    kick = np.linalg.norm(v1 - v0 - np.asarray(gravity) * dt, axis=-1) > min_dv
    out = np.zeros(kick.shape, dtype=bool)
    e, k = np.nonzero(kick)
    if len(e) == 0:
        return out
    near = np.zeros(len(e), dtype=bool)
    for bodies in (bodies_before, bodies_after):
        qa, qb = world_capsules(caps, bodies.take(e))  # (M, G, 3)
        dist = segment_distance(p0[e, k][:, None], p1[e, k][:, None], qa, qb) - caps.radius - pool.radius
        near |= dist.min(-1) < slack
    out[e, k] = near
    return out
