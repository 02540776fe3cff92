"""The MuJoCo humanoid, generated from a motion dataset's skeleton (``motok sim build-humanoid``).

One body per skeleton joint, named after it, so the body positions *are* the dataset's joint
positions and no retargeting is needed. MuJoCo is Z-up and the datasets are Y-up facing +Z
with the left on +X; the map ``(x, y, z)_data -> (z, x, y)_mujoco`` is a proper rotation that
puts the character's forward on +X, its left on +Y and up on +Z (MuJoCo's own convention).

The rest geometry comes from the data (``motok.sim.reference.rest_geometry``): the dataset's bone
lengths, the mocap's own sibling geometry at the hips and chest, feet pitched to lie flat at rest.

Joints: a free root; three hinges per ball joint, ordered so the middle hinge is the twist
about the child bone (twist is small because the data has none, so the Euler decomposition
stays far from gimbal lock); one hinge for knees and elbows (the parents of feet and hands).
Leaves (head, hands, toes) are jointless bodies welded to their parents. Ranges are the data's
range of motion plus a margin; PD gains are proportional to the mass each joint moves.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from motok.data.skeleton import Skeleton

# MuJoCo picks its GL backend at import; every motok.sim module imports this one first, so a
# headless machine renders through EGL unless the user chose (render.py falls back to sticks).
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

META_NAME = "motok_humanoid"
META_VERSION = 1
AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
FORWARD, UP = AXES["x"], AXES["z"]


class HumanoidError(ValueError):
    pass


def to_mj(v: np.ndarray) -> np.ndarray:
    """Dataset coordinates (Y up, facing +Z, left +X) to MuJoCo's (Z up, facing +X, left +Y)."""
    return np.asarray(v)[..., [2, 0, 1]]


@dataclass
class HumanoidConfig:
    total_mass: float = 65.0  # kg; densities are scaled to reach it
    timestep: float = 1.0 / 120.0  # 4 substeps per 30 Hz control step; docs/sim.md has the stability/speed measurements
    control_hz: float = 30.0
    range_margin_deg: float = 20.0
    stiffness_per_kg: float = 15.0  # Nm/rad per kg moved: the ankle then holds ~1000 Nm/rad, > m g l
    min_stiffness: float = 40.0  # Nm/rad; keeps light distal joints (elbows, neck) from being floppy
    derivative_time: float = 0.1  # kv = derivative_time * kp (PHC's kp/kd ratio of 10)
    armature: float = 0.02
    friction: float = 1.0
    solver_iterations: int = 20
    self_collision: bool = True
    max_frames: int = 20000  # frames sampled from the dataset for geometry and ranges


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


def _moved_mass(model, layout: Layout, skeleton: Skeleton, body_ids: np.ndarray) -> dict[str, float]:
    """Mass each hinge moves: its subtree, or for leg joints the larger side (a stance leg carries the body)."""
    total = float(model.body_subtreemass[body_ids[0]])
    legs = set(joint_chain(layout, skeleton.feet_left[0])) | set(joint_chain(layout, skeleton.feet_right[0]))
    out = {}
    for j, name in enumerate(layout.names):
        sub = float(model.body_subtreemass[body_ids[j]])
        out.update({f"{name}_{a[-1]}": max(sub, total - sub) if j in legs else sub for a in layout.axes[j]})
    return out


def build_humanoid(data_path, out, cfg: HumanoidConfig | None = None) -> dict:
    """Write the MJCF for a ``motion-dataset`` artifact; returns a summary (mass, DoF, ranges...)."""
    import mujoco

    from motok.artifacts import command_line, hash_inputs
    from motok.atomic import atomic_path
    from motok.data.dataset import MotionFile
    from motok.sim.mjcf import body_geoms, geom_volume, mjcf_text
    from motok.sim.reference import rest_geometry, solve_pose

    cfg = cfg or HumanoidConfig()
    with MotionFile(data_path, "motion-dataset") as mf:
        skeleton, offsets = mf.skeleton, np.asarray(mf.offsets, dtype=np.float64)
        step = max(1, int(np.ceil(mf.frame_offsets[-1] / cfg.max_frames)))
        clips = [np.asarray(mf.frames("joints", i), dtype=np.float64)[::step] for i in range(len(mf))]
    frames = np.concatenate(clips)
    rest_d, foot = rest_geometry(frames, skeleton, offsets)
    layout = make_layout(skeleton, to_mj(rest_d))
    angles = np.concatenate([solve_pose(to_mj(c), layout)[2] for c in clips if len(c) > 0])
    margin = np.deg2rad(cfg.range_margin_deg)
    # Ranges always contain 0 so the rest pose (qpos0, what a viewer opens) is a legal configuration.
    lo = np.clip(np.minimum(angles.min(0) - margin, 0.0), -np.pi + 1e-3, 0.0)
    hi = np.clip(np.maximum(angles.max(0) + margin, 0.0), 0.0, np.pi - 1e-3)
    ranges = {n: (lo[i], hi[i]) for i, n in enumerate(layout.hinge_names)}
    height = float(np.quantile(frames[:, skeleton.head, 1], 0.5)) + 0.18
    scale = height / 1.70
    geoms = body_geoms(layout, skeleton, foot, scale)
    volume = sum(geom_volume(g) for gs in geoms.values() for g in gs)
    density = cfg.total_mass / volume
    # qpos0 stands the rest pose on the floor: root height = leg drop to the ankle + stance ankle height.
    drop = -sum(layout.rest[k][2] for k in joint_chain(layout, skeleton.feet_left[0]))
    meta = dict(version=META_VERSION, skeleton=skeleton.to_dict(), control_hz=cfg.control_hz, config=asdict(cfg),
                foot=foot, root_height=float(drop + foot["ankle_height"] + 1e-3),
                source=str(data_path), inputs=hash_inputs([data_path]), command=command_line())
    xml = mjcf_text(layout, geoms, cfg, density, ranges, {n: 1.0 for n in layout.hinge_names}, [], meta)
    model = mujoco.MjModel.from_xml_string(xml)
    body_ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in layout.names])
    gains = {n: max(cfg.stiffness_per_kg * m, cfg.min_stiffness)
             for n, m in _moved_mass(model, layout, skeleton, body_ids).items()}
    excludes = _rest_contacts(model, layout) if cfg.self_collision else []
    xml = mjcf_text(layout, geoms, cfg, density, ranges, gains, excludes, meta)
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.write_text(xml)
    hum = load_humanoid(out)
    m = hum.model
    return {"output": str(out), "bodies": m.nbody - 1, "hinges": m.nu, "nq": m.nq, "nv": m.nv,
            "mass_kg": round(float(m.body_subtreemass[1]), 2), "height_m": round(height, 3),
            "timestep_s": m.opt.timestep, "substeps": hum.substeps, "control_hz": cfg.control_hz,
            "excluded_pairs": len(excludes), "frames_used": len(frames)}


def joint_chain(layout: Layout, j: int) -> list[int]:
    """Joint ``j`` and its ancestors up to, not including, the root."""
    out = []
    while j > 0:
        out.append(j)
        j = layout.parents[j]
    return out


def _rest_contacts(model, layout: Layout) -> list[tuple[str, str]]:
    """Body pairs that touch at qpos0: structural overlaps (pelvis vs spine children, ...), excluded."""
    import mujoco

    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    pairs = set()
    for c in d.contact[: d.ncon]:
        b1, b2 = model.geom_bodyid[c.geom[0]], model.geom_bodyid[c.geom[1]]
        if b1 and b2:
            pairs.add(tuple(sorted((mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b1),
                                    mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b2)))))
    return sorted(pairs)


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


def load_humanoid(path) -> Humanoid:
    """Load and check a humanoid MJCF written by :func:`build_humanoid`, with one-line errors."""
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
    rest = model.body_pos[ids].copy()
    layout = Layout(list(skeleton.joints), skeleton.parents, rest, kinds, axes)
    return Humanoid(model, skeleton, layout, np.array(ids), qadr, meta, Path(path) if path else None)
