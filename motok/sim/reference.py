"""From the dataset to the humanoid: rest geometry, inverse kinematics, and the reference library
(dataset clips as qpos/qvel and body states at the control rate).

Rest geometry (:func:`rest_geometry`, used by the MJCF builder): bone lengths from the dataset's
uniform skeleton; directions from the T-pose, except at branching joints (hips, chest), where the
children keep the mocap's own sibling geometry (a Procrustes mean over sampled frames), and at the
ankles, whose toe bones are pitched down to the median stance angle so the sole is flat at rest.

Inverse kinematics (:func:`solve_locals`): the dataset stores HumanML3D per-bone rotations
(siblings rotate independently, no twist), which a body tree cannot use, so per-joint rotations
are re-derived from the canonical joint positions, top-down, in the spirit of
``motok.data.export.bvh_pose`` but against the humanoid's *fixed* rest geometry:

* branching joints (root, chest): Kabsch fit of the children's rest offsets onto their bones;
* limb roots (hip, shoulder), whose child is a one-hinge knee or elbow: the bone direction is
  matched exactly and the hinge axis is turned onto the normal of the limb's bend plane, so the
  knee can reproduce the foot with its single hinge (a plain swing would leave the bend plane
  wherever the twist-free swing puts it). Near a straight limb the normal is undefined; it is
  blended with the swing solution's axis, which keeps the twist continuous;
* hinges: the signed angle between rest and target child bone about the hinge axis;
* other single-child joints: the shortest-arc swing relative to the parent (no twist, smooth).

Resampling to the control rate (default 30 Hz) slerps the local rotations and interpolates the
root position linearly (``motok.features.resample``); qvel is the central difference of qpos
(``mj_differentiatePos``); body positions, rotations, linear and angular velocities come from
MuJoCo's forward kinematics. The library is cached in one ``.npz`` keyed by the dataset's hash,
the MJCF text and the rate, so it is built once.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from motok.atomic import atomic_path
from motok.data.skeleton import Skeleton
from motok.features.resample import resample_positions, resample_quats
from motok.rotations import matrix_to_quat, qbetween, qfix, qinv, qmul, qrot, quat_to_euler
from motok.sim.humanoid import Humanoid, Layout, to_mj

LIB_VERSION = 1
BEND_BLEND = 0.02  # |thigh x shin| (sine of the bend) below which the swing axis takes over


class ReferenceError(KeyError):
    pass


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rotations ``R (F,3,3)`` minimising ``sum_k |R src_k - dst_k|^2``; src ``(K,3)``, dst ``(F,K,3)``."""
    h = np.einsum("ki,fkj->fij", src, dst)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", vt, u)))
    fix = np.ones(u.shape[:-1])
    fix[:, -1] = d
    return np.einsum("fji,fj,fkj->fik", vt, fix, u)


def rest_geometry(joints: np.ndarray, skeleton: Skeleton, offsets: np.ndarray) -> tuple[np.ndarray, dict]:
    """Rest offsets ``(J,3)`` in dataset coordinates and foot measurements, from sampled frames."""
    parents = skeleton.parents
    lengths = np.linalg.norm(offsets, axis=-1)
    rest = skeleton.directions * lengths[:, None]
    bones = joints - joints[:, np.maximum(parents, 0)]
    for j in range(skeleton.num_joints):
        kids = np.flatnonzero(parents == j)
        if len(kids) < 2:
            continue
        template = rest[kids]
        for _ in range(3):  # generalised Procrustes: align every frame to the mean, re-average
            r = _kabsch(template, bones[:, kids])
            mean = np.einsum("fkj,fji->fki", bones[:, kids], r).mean(0)
            mean *= (lengths[kids] / np.linalg.norm(mean, axis=-1))[:, None]
            fit = _kabsch(rest[kids], mean[None])[0]  # express it in the best-fit T-pose frame
            template = mean @ fit
        rest[kids] = template
    ankles = [skeleton.feet_left[0], skeleton.feet_right[0]]
    toes = [skeleton.feet_left[1], skeleton.feet_right[1]]
    a_y, t_y = joints[:, ankles, 1].ravel(), joints[:, toes, 1].ravel()
    # Stance: both the toe and the ankle near their lowest; the foot's pitch there is its flat pose.
    stance = (t_y < np.quantile(t_y, 0.3) + 0.01) & (a_y < np.quantile(a_y, 0.3) + 0.01)
    if stance.sum() < 10:
        stance = np.ones_like(t_y, dtype=bool)
    toe_len = np.tile(lengths[toes], len(joints))
    pitch = float(np.median(np.arcsin(np.clip((a_y - t_y)[stance] / toe_len[stance], -1, 1))))
    up = np.array([0.0, 1.0, 0.0])
    for t in toes:
        h = rest[t] - up * rest[t][1]
        h /= np.linalg.norm(h)
        rest[t] = lengths[t] * (np.cos(pitch) * h - np.sin(pitch) * up)
    foot = {"pitch": pitch, "ankle_height": float(np.median(a_y[stance])), "toe_height": float(np.median(t_y[stance]))}
    return rest, foot


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    h = 0.5 * np.asarray(angle)[..., None]
    return np.concatenate([np.cos(h), np.sin(h) * axis], -1)


def _frame(u: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Orthonormal frames ``(..., 3, 3)`` with columns ``u``, ``n`` made orthogonal to ``u``, ``u x n``."""
    e1 = _unit(u)
    e2 = _unit(n - (n * e1).sum(-1, keepdims=True) * e1)
    return np.stack([e1, e2, np.cross(e1, e2)], -1)


def solve_locals(x: np.ndarray, layout: Layout) -> np.ndarray:
    """Joint positions ``(T, J, 3)`` (MuJoCo coordinates) -> local rotations ``(T, J, 4)``.

    Slot 0 holds the root's global rotation; a leaf's slot is the identity.
    """
    x = np.asarray(x, dtype=np.float64)
    T, J = x.shape[:2]
    par, rest, kids = layout.parents, layout.rest, layout.children
    bone = x - x[:, np.maximum(par, 0)]
    glob = np.zeros((T, J, 4))
    glob[..., 0] = 1.0
    for j in range(J):  # parents precede children (a Skeleton invariant)
        gp = glob[:, par[j]] if j > 0 else glob[:, 0].copy()
        ks, kind = kids[j], layout.kinds[j]
        if kind == "fixed":
            glob[:, j] = gp
        elif len(ks) > 1:
            glob[:, j] = matrix_to_quat(_kabsch(rest[ks], bone[:, ks]))
        elif kind == "hinge":
            a, c = layout.axis_vectors(j)[0], ks[0]
            t = qrot(qinv(gp), bone[:, c])
            t, r = t - (t @ a)[:, None] * a, rest[c] - (rest[c] @ a) * a
            theta = np.arctan2(np.cross(r, t) @ a, t @ r)
            glob[:, j] = qmul(gp, _axis_angle(a, theta))
        else:
            c = ks[0]
            swing = qmul(gp, qbetween(np.broadcast_to(rest[c], (T, 3)), qrot(qinv(gp), bone[:, c])))
            if layout.kinds[c] == "hinge" and kids[c]:
                a = layout.axis_vectors(c)[0]
                u_t, w = _unit(bone[:, c]), _unit(bone[:, kids[c][0]])
                bend = np.cross(u_t, w)
                n = bend + BEND_BLEND * qrot(swing, np.broadcast_to(a, (T, 3)))
                m = _frame(u_t, n) @ _frame(rest[c], a).T
                glob[:, j] = matrix_to_quat(m)
            else:
                glob[:, j] = swing
    local = glob.copy()
    local[:, 1:] = qmul(qinv(glob[:, par[1:]]), glob[:, 1:])
    return qfix(local)


def locals_to_angles(local: np.ndarray, layout: Layout) -> np.ndarray:
    """Local rotations ``(T, J, 4)`` -> hinge angles ``(T, H)`` in ``layout.hinge_names`` order.

    A ball joint's three hinges compose as intrinsic Euler angles in their listed order, which is
    exactly how MuJoCo chains several hinges in one body. Angles are unwrapped along time.
    """
    cols = []
    for j, kind in enumerate(layout.kinds):
        if kind == "ball":
            order = "".join(a.upper() for a in layout.axes[j])
            cols.append(quat_to_euler(local[:, j], order, degrees=False))
        elif kind == "hinge":
            a = layout.axis_vectors(j)[0]
            q = local[:, j]
            cols.append((2 * np.arctan2(q[:, 1:] @ a, q[:, 0]))[:, None])
    ang = np.concatenate(cols, -1) if cols else np.zeros((len(local), 0))
    return np.unwrap(ang, axis=0)


class Pose(NamedTuple):
    root_pos: np.ndarray
    root_quat: np.ndarray
    angles: np.ndarray
    local: np.ndarray


def solve_pose(x: np.ndarray, layout: Layout) -> Pose:
    local = solve_locals(x, layout)
    return Pose(np.asarray(x[:, 0], dtype=np.float64), local[:, 0], locals_to_angles(local, layout), local)


def clip_qpos(joints_data: np.ndarray, hum: Humanoid, src_fps: float, dst_fps: float) -> np.ndarray:
    """A clip's canonical joints (dataset coordinates) -> qpos ``(T', nq)`` at ``dst_fps``."""
    layout = hum.layout
    local = solve_locals(to_mj(joints_data), layout)
    root = to_mj(np.asarray(joints_data, dtype=np.float64)[:, 0])
    if src_fps != dst_fps:
        local = resample_quats(local, src_fps, dst_fps)
        root = resample_positions(root, src_fps, dst_fps)
    qpos = np.zeros((len(local), hum.model.nq))
    qpos[:, :3], qpos[:, 3:7] = root, local[:, 0]
    qpos[:, hum.hinge_qpos_adr] = locals_to_angles(local, layout)
    return qpos


def _qvel(model, qpos: np.ndarray, dt: float) -> np.ndarray:
    import mujoco

    T = len(qpos)
    out = np.zeros((T, model.nv))
    if T < 2:
        return out
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        mujoco.mj_differentiatePos(model, out[t], (b - a) * dt, qpos[a], qpos[b])
    return out


def body_states(hum: Humanoid, qpos: np.ndarray, qvel: np.ndarray) -> dict[str, np.ndarray]:
    """MuJoCo forward kinematics per frame: world positions, rotations (w,x,y,z), linear and angular
    velocities of every skeleton body at its origin, ``(T, J, .)``, plus the lowest geom point ``(T,)``."""
    import mujoco

    m, ids = hum.model, hum.body_ids
    d = mujoco.MjData(m)
    T, J = len(qpos), len(ids)
    pos, quat = np.zeros((T, J, 3)), np.zeros((T, J, 4))
    vel, ang = np.zeros((T, J, 3)), np.zeros((T, J, 3))
    low = np.zeros(T)
    floor = m.geom_bodyid == 0
    for t in range(T):
        d.qpos[:], d.qvel[:] = qpos[t], qvel[t]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        pos[t], quat[t] = d.xpos[ids], d.xquat[ids]
        w, v = d.cvel[ids, :3], d.cvel[ids, 3:]
        ang[t] = w
        vel[t] = v + np.cross(w, d.xpos[ids] - d.subtree_com[m.body_rootid[ids]])
        low[t] = _lowest_point(m, d, ~floor)
    return {"body_pos": pos, "body_quat": quat, "body_vel": vel, "body_angvel": ang, "lowest": low}


def _lowest_point(m, d, sel: np.ndarray) -> float:
    """Lowest world z over the selected sphere, capsule and box geoms."""
    z, xmat, size, typ = d.geom_xpos[sel, 2], d.geom_xmat[sel].reshape(-1, 3, 3), m.geom_size[sel], m.geom_type[sel]
    zrow = np.abs(xmat[:, 2, :])  # |z component of each local axis|
    ext = np.where(typ == 6, (zrow * size).sum(-1), 0.0)  # box: half extents projected on z
    ext = np.where(typ == 3, zrow[:, 2] * size[:, 1] + size[:, 0], ext)  # capsule: half length + radius
    ext = np.where(typ == 2, size[:, 0], ext)  # sphere
    return float((z - ext).min())


@dataclass
class ReferenceLibrary:
    """Reference clips at the control rate, concatenated along frames with a clip offset index."""

    names: list[str]
    fps: float
    starts: np.ndarray  # (C+1,) frame offsets
    qpos: np.ndarray  # (F, nq)
    qvel: np.ndarray  # (F, nv)
    body_pos: np.ndarray  # (F, J, 3)
    body_quat: np.ndarray  # (F, J, 4)
    body_vel: np.ndarray
    body_angvel: np.ndarray
    lowest: np.ndarray  # (F,) lowest geom point, for lifting reference states off the floor
    joints: np.ndarray  # (F, J, 3) the dataset's canonical joints, resampled, MuJoCo coordinates

    ARRAYS = ("qpos", "qvel", "body_pos", "body_quat", "body_vel", "body_angvel", "lowest", "joints")

    def __len__(self) -> int:
        return len(self.names)

    def __post_init__(self):
        self.lengths = np.diff(self.starts)  # frames per clip

    def index(self, clip) -> int:
        if isinstance(clip, (int, np.integer)):
            if not 0 <= int(clip) < len(self):
                raise ReferenceError(f"clip index {clip} out of range (0..{len(self) - 1})")
            return int(clip)
        if clip not in self.names:
            near = [n for n in self.names if str(clip).lower() in n.lower()][:5]
            raise ReferenceError(f"no clip named {clip!r} in the reference library"
                                 + (f"; similar: {near}" if near else f"; first clips: {self.names[:3]}"))
        return self.names.index(clip)

    def clip(self, clip) -> dict[str, np.ndarray]:
        i = self.index(clip)
        sl = slice(self.starts[i], self.starts[i + 1])
        return {k: getattr(self, k)[sl] for k in self.ARRAYS}

    def sample(self, n: int, rng: np.random.Generator, horizon: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Random clips (weighted by usable length) and start frames that leave ``horizon`` frames ahead."""
        usable = np.maximum(self.lengths - horizon, 0)
        if usable.sum() == 0:
            raise ReferenceError(f"every clip is shorter than {horizon + 1} frames at {self.fps:g} Hz")
        clips = rng.choice(len(self), size=n, p=usable / usable.sum())
        frames = np.floor(rng.random(n) * usable[clips]).astype(np.int64)
        return clips, frames

    def save(self, path: Path) -> None:
        with atomic_path(path) as tmp:  # keeps the .npz suffix, so savez does not append one
            np.savez(tmp, names=np.array(self.names), fps=self.fps, starts=self.starts, version=LIB_VERSION,
                     **{k: getattr(self, k).astype(np.float64) for k in self.ARRAYS})

    @classmethod
    def from_file(cls, path: Path) -> "ReferenceLibrary":
        with np.load(path) as z:
            if int(z["version"]) != LIB_VERSION:
                raise ValueError("stale cache")
            return cls(names=[str(s) for s in z["names"]], fps=float(z["fps"]), starts=z["starts"],
                       **{k: z[k] for k in cls.ARRAYS})


def build_library(hum: Humanoid, data_path, control_hz: float | None = None, clips=None) -> ReferenceLibrary:
    """Build the library for ``clips`` (names or indices; all by default) of a motion-dataset."""
    from motok.data.dataset import MotionFile

    hz = float(control_hz or hum.control_hz)
    with MotionFile(data_path, "motion-dataset") as mf:
        if [n for n in mf.skeleton.joints] != list(hum.skeleton.joints):
            raise ReferenceError(f"{data_path}: skeleton {mf.skeleton.name!r} does not match the humanoid's "
                                 f"{hum.skeleton.name!r}; build the humanoid from this dataset")
        try:
            idx = list(range(len(mf))) if clips is None else [mf.index(c) for c in clips]
        except KeyError as e:
            raise ReferenceError(e.args[0]) from None
        names, parts = [], {k: [] for k in ReferenceLibrary.ARRAYS}
        for i in idx:
            joints = np.asarray(mf.frames("joints", i), dtype=np.float64)
            qpos = clip_qpos(joints, hum, mf.fps, hz)
            qvel = _qvel(hum.model, qpos, 1.0 / hz)
            st = body_states(hum, qpos, qvel)
            res = resample_positions(joints, mf.fps, hz) if mf.fps != hz else joints
            for k, v in dict(qpos=qpos, qvel=qvel, joints=to_mj(res), **st).items():
                parts[k].append(v)
            names.append(mf.names[i])
    lengths = [len(p) for p in parts["qpos"]]
    return ReferenceLibrary(names=names, fps=hz, starts=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
                            **{k: np.concatenate(v) for k, v in parts.items()})


def default_cache_dir() -> Path:
    return Path(os.environ.get("MOTOK_CACHE", Path.home() / ".cache" / "motok")) / "sim-reference"


def load_library(hum: Humanoid, data_path, control_hz: float | None = None, clips=None,
                 cache_dir=None, use_cache: bool = True) -> ReferenceLibrary:
    """The reference library, from the cache when the dataset, MJCF, rate and clip list match."""
    from motok.artifacts import sha256_file

    hz = float(control_hz or hum.control_hz)
    if not use_cache:
        return build_library(hum, data_path, hz, clips)
    h = hashlib.sha256()
    h.update(sha256_file(data_path).encode())
    h.update(hum.path.read_bytes() if hum.path else repr(hum.meta).encode())
    h.update(f"{hz:.6f}|{LIB_VERSION}|{clips!r}".encode())
    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    path = cache / f"{Path(data_path).stem}-{h.hexdigest()[:16]}.npz"
    if path.exists():
        try:
            return ReferenceLibrary.from_file(path)
        except (ValueError, KeyError, OSError):
            pass  # a stale or truncated cache is rebuilt below
    lib = build_library(hum, data_path, hz, clips)
    cache.mkdir(parents=True, exist_ok=True)
    lib.save(path)
    return lib


def humanoid_for(data_path, cache_dir=None):
    """The default humanoid of a dataset (built once, cached next to the reference libraries)."""
    from motok.artifacts import sha256_file
    from motok.sim.humanoid import build_humanoid, load_humanoid

    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    path = cache / f"{Path(data_path).stem}-{sha256_file(data_path)[:16]}.xml"
    if not path.exists():
        with atomic_path(path) as tmp:
            build_humanoid(data_path, tmp)
    return load_humanoid(path)
