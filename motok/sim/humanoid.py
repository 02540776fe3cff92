"""The MuJoCo humanoid motok builds from a motion dataset's skeleton: its types and its loading.

One body per skeleton joint, named after it, so the body positions *are* the dataset's joint
positions and no retargeting is needed. MuJoCo is Z-up and the datasets are Y-up facing +Z
with the left on +X; the map ``(x, y, z)_data -> (z, x, y)_mujoco`` is a proper rotation that
puts the character's forward on +X, its left on +Y and up on +Z (MuJoCo's own convention).

Joints (:func:`make_layout`): a free root; three hinges per ball joint, ordered so the middle
hinge is the twist about the child bone (twist is small because the data has none, so the Euler
decomposition stays far from gimbal lock); one hinge for knees and elbows (the parents of feet
and hands). Leaves (head, hands, toes) are jointless bodies welded to their parents.

The builder is :func:`motok.sim.mjcf.build_humanoid` (rest geometry from the data, ranges from
its range of motion plus a margin, PD gains proportional to the mass each joint moves);
:func:`load_humanoid` reads back any file it wrote and checks what the rest of motok relies on.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from motok.errors import MotokError
from motok.ranges import In
from motok.skeleton import Skeleton

META_NAME = "motok_humanoid"
META_VERSION = 1
AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
FORWARD, UP = AXES["x"], AXES["z"]


class HumanoidError(MotokError, ValueError):
    pass


def to_mj(v: np.ndarray) -> np.ndarray:
    """Dataset coordinates (Y up, facing +Z, left +X) to MuJoCo's (Z up, facing +X, left +Y)."""
    return np.asarray(v)[..., [2, 0, 1]]


def from_mj(v: np.ndarray) -> np.ndarray:
    """MuJoCo (Z up, X forward) -> data frame (Y up): the inverse of :func:`to_mj`."""
    return np.asarray(v)[..., [1, 2, 0]]


@dataclass
class HumanoidConfig:
    total_mass: In[float, "> 0"] = 65.0  # kg; densities are scaled to reach it
    # 4 substeps per 30 Hz control step; docs/sim.md has the stability/speed measurements
    timestep: In[float, "> 0"] = 1.0 / 120.0
    control_hz: In[float, "> 0"] = 30.0  # PD targets per second, round(1 / (control_hz timestep)) substeps each
    range_margin_deg: In[float, "[0, 180]"] = 20.0  # joint limits: the data's angle range widened by this each side
    stiffness_per_kg: In[float, ">= 0"] = 15.0  # Nm/rad per kg moved: the ankle then holds ~1000 Nm/rad, > m g l
    min_stiffness: In[float, ">= 0"] = 40.0  # Nm/rad; keeps light distal joints (elbows, neck) from being floppy
    derivative_time: In[float, ">= 0"] = 0.1  # kv = derivative_time * kp (PHC's kp/kd ratio of 10)
    # The ankles' stiffness (and so damping) as a share of the mass rule's: a compliant ankle lets
    # the sole settle flat on the floor instead of holding the reference's foot angle against it.
    ankle_stiffness_scale: In[float, "> 0"] = 1.0
    armature: In[float, ">= 0"] = 0.02  # kg m^2, MuJoCo's joint armature: inertia added to every joint's own
    friction: In[float, ">= 0"] = 1.0  # sliding friction coefficient of every geom, the floor's too
    # Physics cost: benchmarks/physics.py steps states recorded from PD tracking of walk, run, turn
    # and arm clips, falls included, under each option (table in docs/sim.md). Together the
    # defaults below are 1.19-1.22x the raw mj_step rate of the previous build (every pair
    # colliding, 20/10 iterations, automatic Jacobian, islands), same trajectories to 0.1 mm.
    # Newton takes 2.8 iterations on average and at most 9 on those states: 10 never binds (6 binds
    # on 2 % of the steps), so the cap bounds the worst step without changing the physics.
    solver_iterations: In[int, ">= 1"] = 10
    ls_iterations: In[int, ">= 1"] = 5  # the most line-search iterations per solver iteration (MuJoCo's option)
    # "data": the floor plus only the part pairs that touch in the data (arms vs trunk, arms vs
    # thighs, arm vs arm, leg vs leg; mjcf.contact_bits). What it drops (head, neck and clavicles vs
    # anything, arms vs shins and feet, trunk vs legs) touches in 0.01 % of 190k reference frames
    # (head vs upper arm) and in none of 63k recorded tracking steps: the contacts are those of
    # "all", from 91 candidate geom pairs instead of 249 (what a GPU broadphase tests). Same cost on
    # the CPU, where the arms-on-torso contact it keeps (0.7 per step) is what costs. "legs" (leg vs
    # leg) and "none" (floor only) are another 1.10-1.17x but let the arms into the torso, which
    # changes the arms by 3-4 cm within 10 steps of tracking: the reference itself puts the upper
    # arms inside the torso capsules in 40 % of its frames (the capsules are wider than the actors).
    self_collision: str = "data"  # "all" | "data" | "legs" | "none"; true/false mean all/none
    # MuJoCo's "auto" means dense below nv = 60; for this nv = 43 tree the sparse Jacobian and
    # Hessian make the Newton solve about 30 % cheaper (1.12-1.16x the whole step), same result.
    jacobian: str = "sparse"  # "auto" | "dense" | "sparse"
    islands: bool = False  # one humanoid is one island: finding it every step only costs (1.02-1.05x)
    max_frames: In[int, ">= 1"] = 20000  # frames sampled from the dataset for geometry and ranges
    # The contact model (docs/sim.md "Feet"): part of the MJCF and of its metadata, so a controller
    # trained on one is never resumed or evaluated on another by mistake. The defaults are MuJoCo's.
    cone: str = "pyramidal"  # friction cone: "pyramidal" | "elliptic"
    # frictional-to-normal impedance ratio; > 1 makes friction harder (elliptic cones)
    impratio: In[float, ">= 1"] = 1.0
    noslip_iterations: In[int, ">= 0"] = 0  # MuJoCo's no-slip post-solve on the friction rows (0: off)
    contact_solref: In[tuple[float, float], "> 0"] = (0.02, 1.0)  # (time constant s, damping ratio) of every contact
    contact_solimp: In[tuple[float, float, float], "> 0"] = (0.9, 0.95, 0.001)  # (dmin, dmax, width m) of every contact

    def __post_init__(self):
        legacy = {"true": "all", "false": "none"}  # the option used to be a boolean
        self.self_collision = legacy.get(str(self.self_collision).lower(), str(self.self_collision))
        if self.self_collision not in SELF_COLLISION:
            raise HumanoidError(f"self_collision must be one of {', '.join(SELF_COLLISION)}, "
                                f"not {self.self_collision!r}")
        if self.jacobian not in ("auto", "dense", "sparse"):
            raise HumanoidError(f"jacobian must be auto, dense or sparse, not {self.jacobian!r}")
        if self.solver_iterations < 1 or self.ls_iterations < 1:
            raise HumanoidError("solver_iterations and ls_iterations must be at least 1")
        if not (np.isfinite(self.ankle_stiffness_scale) and self.ankle_stiffness_scale > 0):
            raise HumanoidError(f"ankle_stiffness_scale must be a finite number > 0, not {self.ankle_stiffness_scale!r}")
        if self.cone not in ("pyramidal", "elliptic"):
            raise HumanoidError(f"cone must be pyramidal or elliptic, not {self.cone!r}")
        if not (np.isfinite(self.impratio) and self.impratio >= 1):
            raise HumanoidError(f"impratio must be a finite number >= 1, not {self.impratio!r}")
        if self.noslip_iterations < 0:
            raise HumanoidError(f"noslip_iterations must be >= 0, not {self.noslip_iterations!r}")
        self.contact_solref = tuple(float(v) for v in self.contact_solref)
        self.contact_solimp = tuple(float(v) for v in self.contact_solimp)
        tc, dr = self.contact_solref if len(self.contact_solref) == 2 else (float("nan"),) * 2
        if not (np.isfinite(tc) and np.isfinite(dr) and tc > 0 and dr > 0):
            raise HumanoidError(f"contact_solref must be [time constant > 0, damping ratio > 0], not "
                                f"{list(self.contact_solref)}")
        lo, hi, width = self.contact_solimp if len(self.contact_solimp) == 3 else (float("nan"),) * 3
        if not (0 < lo <= hi < 1 and width > 0):
            raise HumanoidError(f"contact_solimp must be [dmin, dmax, width] with 0 < dmin <= dmax < 1 and "
                                f"width > 0, not {list(self.contact_solimp)}")

    def contact_model(self) -> dict:
        """The fields that define the contact model, by name (what a resume on another humanoid compares)."""
        return {k: getattr(self, k) for k in CONTACT_FIELDS}


SELF_COLLISION = ("all", "data", "legs", "none")
CONTACT_FIELDS = ("cone", "impratio", "noslip_iterations", "contact_solref", "contact_solimp", "friction",
                  "self_collision", "timestep")


@dataclass
class Layout:
    """The kinematic structure both the MJCF and the inverse kinematics are derived from.

    ``kinds[j]``: ``free`` (root), ``ball`` (three hinges), ``hinge`` (one) or ``fixed`` (leaf).
    ``axes[j]``: hinge axes in the body frame, in composition order; ``rest[j]``: body position in
    its parent's frame (MuJoCo coordinates; every body frame is world-aligned at qpos0).
    """

    names: list[str]
    parents: np.ndarray
    rest: np.ndarray
    kinds: list[str]
    axes: list[list[str]]
    children: list[list[int]] = field(default_factory=list)

    def __post_init__(self):
        self.parents = np.asarray(self.parents)
        self.rest = np.asarray(self.rest, dtype=np.float64)
        self.children = [list(np.flatnonzero(self.parents == j)) for j in range(len(self.names))]

    @property
    def hinge_names(self) -> list[str]:
        return [f"{n}_{a[-1]}" for n, ax in zip(self.names, self.axes) for a in ax]

    def axis_vectors(self, j: int) -> np.ndarray:
        return np.array([AXES[a] if a in AXES else -AXES[a[1]] for a in self.axes[j]]).reshape(-1, 3)


def _dominant(v: np.ndarray) -> str:
    return "xyz"[int(np.argmax(np.abs(v)))]


def make_layout(skeleton: Skeleton, rest_mj: np.ndarray) -> Layout:
    """The joint layout of ``skeleton`` with rest offsets ``rest_mj (J, 3)`` (MuJoCo coordinates).

    Knees and elbows are found as the parents of the feet and hands (no names assumed); their
    hinge axis is ``bone x flex direction`` snapped to a body axis, so positive angles flex them.
    """
    J, parents = skeleton.num_joints, skeleton.parents
    children = [np.flatnonzero(parents == j) for j in range(J)]
    feet = {skeleton.feet_left[0], skeleton.feet_right[0]}
    hands = [e for e in skeleton.end_effectors if e not in feet and e != skeleton.head]
    hinge_dir = {int(parents[f]): -FORWARD for f in feet}  # knees: the shin swings backwards
    hinge_dir.update({int(parents[h]): FORWARD for h in hands})  # elbows: the forearm swings forwards
    kinds, axes = [], []
    for j in range(J):
        kids = children[j]
        if j == 0:
            kinds.append("free"), axes.append([])
        elif len(kids) == 0:
            kinds.append("fixed"), axes.append([])
        elif j in hinge_dir and len(kids) == 1:
            a = np.cross(rest_mj[kids[0]], hinge_dir[j])
            name = _dominant(a)
            if abs(a[np.argmax(np.abs(a))]) < 0.5 * np.linalg.norm(a):
                raise HumanoidError(f"joint {skeleton.joints[j]}: hinge axis {a} is not near a body axis")
            kinds.append("hinge"), axes.append([name if a["xyz".index(name)] > 0 else "-" + name])
        else:
            bone = rest_mj[kids].sum(0) if len(kids) > 1 else rest_mj[kids[0]]
            twist = "z" if len(kids) > 1 else _dominant(bone)
            others = [a for a in "xyz" if a != twist]
            kinds.append("ball"), axes.append([others[0], twist, others[1]])
    return Layout(list(skeleton.joints), parents, rest_mj, kinds, axes)


def joint_chain(layout: Layout, j: int) -> list[int]:
    """Joint ``j`` and its ancestors up to, not including, the root."""
    out = []
    while j > 0:
        out.append(j)
        j = layout.parents[j]
    return out


# ----------------------------------------------------------------------------- loading

@dataclass
class Humanoid:
    """A loaded motok humanoid: the MjModel, its skeleton and the layout the IK works in."""

    model: object
    skeleton: Skeleton
    layout: Layout
    body_ids: np.ndarray  # (J,) MuJoCo body id of each skeleton joint
    qpos_adr: list[np.ndarray]  # per joint: qpos addresses of its hinges
    meta: dict
    path: Path | None = None

    @property
    def control_hz(self) -> float:
        return float(self.meta["control_hz"])

    @property
    def substeps(self) -> int:
        return max(1, int(round(1.0 / (self.control_hz * self.model.opt.timestep))))

    @property
    def hinge_qpos_adr(self) -> np.ndarray:
        return np.concatenate([a for a in self.qpos_adr if len(a)]).astype(np.int64)

    # The humanoid's own state is the prefix qpos[:nq], qvel[:nv] of the model's (the loader checks
    # it): a model may append other free bodies after it (motok.sim.balls), whose coordinates follow.
    @property
    def nq(self) -> int:
        return 7 + len(self.hinge_qpos_adr)

    @property
    def nv(self) -> int:
        return 6 + len(self.hinge_qpos_adr)


def config_difference(a: "Humanoid", b: "Humanoid") -> str:
    """What differs between the build configs of two humanoids, contact model first, e.g.
    ``"cone: pyramidal -> elliptic, impratio: 1 -> 10"``; empty when the configs agree."""
    ca, cb = a.meta.get("config", {}), b.meta.get("config", {})
    keys = [*CONTACT_FIELDS, *sorted(k for k in {*ca, *cb} if k not in CONTACT_FIELDS)]
    fmt = lambda v: "unset" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))  # noqa: E731
    return ", ".join(f"{k}: {fmt(ca.get(k))} -> {fmt(cb.get(k))}" for k in keys if ca.get(k) != cb.get(k))


def load_humanoid(path) -> Humanoid:
    """Load and check a humanoid MJCF written by :func:`motok.sim.mjcf.build_humanoid`, with one-line errors."""
    import mujoco

    path = Path(path)
    if not path.exists():
        raise HumanoidError(f"{path}: no such file (build one with `motok sim build-humanoid`)")
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else "unknown error"
        raise HumanoidError(f"{path}: MuJoCo cannot load this MJCF: {first}") from None
    return humanoid_from_model(model, path)


def humanoid_from_model(model, path=None) -> Humanoid:
    import mujoco

    where, obj = path or "<model>", mujoco.mjtObj
    tid = mujoco.mj_name2id(model, obj.mjOBJ_TEXT, META_NAME)
    if tid < 0:
        raise HumanoidError(f"{where}: not a motok humanoid (no <custom><text name='{META_NAME}'>); "
                            "build one with `motok sim build-humanoid`")
    raw = bytes(model.text_data[model.text_adr[tid]:model.text_adr[tid] + model.text_size[tid]]).split(b"\0")[0]
    try:
        meta = json.loads(raw.decode())
    except json.JSONDecodeError as e:
        raise HumanoidError(f"{where}: corrupt motok metadata ({e})") from None
    if meta.get("version") != META_VERSION:
        raise HumanoidError(f"{where}: humanoid format version {meta.get('version')} is not {META_VERSION}; rebuild it")
    skeleton = Skeleton.from_dict(meta["skeleton"], source=f"{where}:{META_NAME}")
    ids, kinds, axes, qadr = [], [], [], []
    for j, name in enumerate(skeleton.joints):
        b, p = mujoco.mj_name2id(model, obj.mjOBJ_BODY, name), skeleton.parents[j]
        if b < 0:
            raise HumanoidError(f"{where}: the skeleton's joint {name!r} has no body of that name")
        if (p >= 0 and model.body_parentid[b] != ids[p]) or not np.allclose(model.body_quat[b], [1, 0, 0, 0]):
            raise HumanoidError(f"{where}: body {name!r} must be an unrotated child of {skeleton.joints[p]!r}")
        ids.append(b)
        jn = list(range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]))
        types = [int(model.jnt_type[k]) for k in jn]
        want = [int(mujoco.mjtJoint.mjJNT_FREE)] if p < 0 else [int(mujoco.mjtJoint.mjJNT_HINGE)] * len(types)
        ax = model.jnt_axis[jn]
        if types != want or len(types) not in ((1,) if p < 0 else (0, 1, 3)) or \
                (p >= 0 and len(jn) and not np.allclose(np.abs(ax).max(-1), 1.0)):
            raise HumanoidError(f"{where}: body {name!r} needs a free joint (root) or 0, 1 or 3 body-axis hinges")
        kinds.append("free" if p < 0 else {0: "fixed", 1: "hinge", 3: "ball"}[len(jn)])
        axes.append([] if p < 0 else [("" if a.max() > 0.5 else "-") + "xyz"[int(np.abs(a).argmax())] for a in ax])
        qadr.append(np.array([] if p < 0 else model.jnt_qposadr[jn], dtype=np.int64))
    hinges = np.concatenate([q for q in qadr if len(q)])
    driven = model.jnt_qposadr[model.actuator_trnid[:, 0]] if model.nu else np.zeros(0, dtype=int)
    if model.nu != len(hinges) or not np.array_equal(driven, hinges):
        raise HumanoidError(f"{where}: expected one position actuator per hinge, in skeleton order")
    root_jnt = model.body_jntadr[ids[0]]
    dofs = model.jnt_dofadr[model.actuator_trnid[:, 0]] if model.nu else np.zeros(0, dtype=int)
    if model.jnt_qposadr[root_jnt] != 0 or model.jnt_dofadr[root_jnt] != 0 or \
            not np.array_equal(np.sort(hinges), 7 + np.arange(len(hinges))) or \
            not np.array_equal(np.sort(dofs), 6 + np.arange(len(hinges))):
        raise HumanoidError(f"{where}: the humanoid's joints must come first in qpos and qvel "
                            "(other bodies, such as motok.sim.balls', go after it in <worldbody>)")
    rest = model.body_pos[ids].copy()
    layout = Layout(list(skeleton.joints), skeleton.parents, rest, kinds, axes)
    return Humanoid(model, skeleton, layout, np.array(ids), qadr, meta, Path(path) if path else None)
