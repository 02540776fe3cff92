"""Loop-based reference for the HumanML3D features, for speed comparison only.

Structured the way the official HumanML3D pipeline is (``motion_representation.process_file``
with ``common/skeleton.py``): a loop over joints for the offsets, a loop over kinematic chains
and over the joints of each chain for inverse and forward kinematics, and quaternion helpers
that round-trip numpy arrays through float32 torch tensors as the official ``*_np`` wrappers
do. It reproduces the official (``legacy=True``) numbers; it is not used by the package.

Run ``python benchmarks/features_baseline.py`` for frames/s of this baseline and of
``motok.features.humanml3d.extract_features`` on the golden clip (one core), and their ratio.
The official code itself is not run (it needs the HumanML3D repository and SMPL files): the
ratio this script prints is against this baseline only; any figure against the official
code is quoted, not measured here (docs/results.md).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, for both implementations

import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.ndimage import gaussian_filter1d  # noqa: E402


# Quaternion helpers (w, x, y, z), numpy in/out through float32 torch, one formula per function.
def _t(a):
    return torch.from_numpy(np.ascontiguousarray(a)).float()


def q_mul(a, b):
    a, b = _t(a), _t(b)
    w1, x1, y1, z1 = a.unbind(-1)
    w2, x2, y2, z2 = b.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1).numpy()


def q_inv(q):
    return (_t(q) * torch.tensor([1.0, -1.0, -1.0, -1.0])).numpy()


def q_rot(q, v):
    q, v = _t(q), _t(v)
    u = q[..., 1:]
    uv = torch.cross(u, v, dim=-1)
    return (v + 2 * (q[..., :1] * uv + torch.cross(u, uv, dim=-1))).numpy()


def q_between(v0, v1):
    v0, v1 = _t(v0), _t(v1)
    axis = torch.cross(v0, v1, dim=-1)
    w = torch.sqrt((v0 ** 2).sum(-1, keepdim=True) * (v1 ** 2).sum(-1, keepdim=True)) + (v0 * v1).sum(-1, keepdim=True)
    q = torch.cat([w, axis], -1)
    return (q / q.norm(dim=-1, keepdim=True)).numpy()


def q_to_cont6d(q):
    q = _t(q)
    w, x, y, z = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1)
    col0 = torch.stack([1 - s * (y * y + z * z), s * (x * y + z * w), s * (x * z - y * w)], -1)
    col1 = torch.stack([s * (x * y - z * w), 1 - s * (x * x + z * z), s * (y * z + x * w)], -1)
    return torch.cat([col0, col1], -1).numpy()


class LoopSkeleton:
    def __init__(self, raw_offsets, chains):
        self.raw = np.asarray(raw_offsets, dtype=np.float64)
        self.chains = [list(c) for c in chains]
        self.parents = [-1] * len(self.raw)
        for chain in self.chains:
            for a, b in zip(chain[:-1], chain[1:]):
                self.parents[b] = a
        self.offsets = None

    def offsets_from(self, frame):
        out = self.raw.copy()
        for j in range(1, len(out)):
            out[j] = np.linalg.norm(frame[j] - frame[self.parents[j]]) * out[j]
        self.offsets = out
        return out

    def ik(self, joints, face, smooth):
        l_hip, r_hip, sdr_r, sdr_l = face  # the official unpacking order (hip term flipped)
        across = joints[:, r_hip] - joints[:, l_hip] + joints[:, sdr_r] - joints[:, sdr_l]
        across = across / np.linalg.norm(across, axis=-1, keepdims=True)
        forward = np.cross(np.array([[0.0, 1.0, 0.0]]), across)
        if smooth:
            forward = gaussian_filter1d(forward, 20, axis=0, mode="nearest")
        forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
        root = q_between(forward, np.repeat([[0.0, 0.0, 1.0]], len(forward), 0))
        root[0] = [1.0, 0.0, 0.0, 0.0]
        quats = np.zeros(joints.shape[:-1] + (4,))
        quats[:, 0] = root
        for chain in self.chains:
            r = root
            for j in range(len(chain) - 1):
                u = np.repeat(self.raw[chain[j + 1]][None], len(joints), 0)
                v = joints[:, chain[j + 1]] - joints[:, chain[j]]
                v = v / np.linalg.norm(v, axis=-1, keepdims=True)
                local = q_mul(q_inv(r), q_between(u, v))
                quats[:, chain[j + 1]] = local
                r = q_mul(r, local)
        return quats

    def fk(self, quats, root_pos):
        joints = np.zeros(quats.shape[:-1] + (3,))
        joints[:, 0] = root_pos
        offsets = np.repeat(self.offsets[None], len(quats), 0)
        for chain in self.chains:
            r = quats[:, 0]
            for i in range(1, len(chain)):
                r = q_mul(r, quats[:, chain[i]])
                joints[:, chain[i]] = q_rot(r, offsets[:, chain[i]]) + joints[:, chain[i - 1]]
        return joints


def baseline_features(positions, raw_offsets, chains, face, feet_l, feet_r, leg, thresh=0.002):
    """The legacy HumanML3D features of ``positions`` (T, J, 3) on the clip's own skeleton."""
    positions = np.asarray(positions, dtype=np.float64)
    skel = LoopSkeleton(raw_offsets, chains)
    off = skel.offsets_from(positions[0])
    tgt = off.copy()
    tgt_leg = np.abs(tgt[leg[0]]).max() + np.abs(tgt[leg[1]]).max()
    scale = tgt_leg / (np.abs(off[leg[0]]).max() + np.abs(off[leg[1]]).max())
    quats = skel.ik(positions, face, smooth=False)
    skel.offsets = tgt
    positions = skel.fk(quats, positions[:, 0] * scale)

    positions[:, :, 1] -= positions.min(axis=0).min(axis=0)[1]
    init = positions[0].copy()
    positions = positions - init[0] * np.array([1.0, 0.0, 1.0])
    r_hip, l_hip, sdr_r, sdr_l = face
    across = init[r_hip] - init[l_hip] + init[sdr_r] - init[sdr_l]
    fwd = np.cross([0.0, 1.0, 0.0], across / np.linalg.norm(across))
    fwd = fwd / np.linalg.norm(fwd)
    q0 = q_between(fwd[None], np.array([[0.0, 0.0, 1.0]]))
    positions = q_rot(np.ones(positions.shape[:-1] + (4,)) * q0, positions).astype(np.float64)
    glob = positions.copy()

    contacts = []
    for feet in (feet_l, feet_r):
        dx = (positions[1:, feet, 0] - positions[:-1, feet, 0]) ** 2
        dy = (positions[1:, feet, 1] - positions[:-1, feet, 1]) ** 2
        dz = (positions[1:, feet, 2] - positions[:-1, feet, 2]) ** 2
        contacts.append((dx + dy + dz < thresh).astype(np.float32))

    quats = skel.ik(positions, face, smooth=True)
    cont6d = q_to_cont6d(quats)
    r_rot = quats[:, 0].copy()
    vel = q_rot(r_rot[1:], positions[1:, 0] - positions[:-1, 0])
    r_vel = q_mul(r_rot[1:], q_inv(r_rot[:-1]))
    positions[..., 0] -= positions[:, 0:1, 0]
    positions[..., 2] -= positions[:, 0:1, 2]
    ric = q_rot(np.repeat(r_rot[:, None], positions.shape[1], 1), positions)
    local_vel = q_rot(np.repeat(r_rot[:-1, None], glob.shape[1], 1), glob[1:] - glob[:-1])
    n = len(glob) - 1
    return np.concatenate([
        np.arcsin(r_vel[:, 2:3]), vel[:, [0, 2]], ric[:-1, 0, 1:2], ric[:-1, 1:].reshape(n, -1),
        cont6d[:-1, 1:].reshape(n, -1), local_vel.reshape(n, -1), *contacts], -1)


def _rate(fn, frames, repeats=7, batch_time=0.3):
    """Frames/s of the best of ``repeats`` timed batches (robust to other load on the machine)."""
    fn()
    start, calls = time.perf_counter(), 0
    while time.perf_counter() - start < batch_time:
        fn()
        calls += 1
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - start) / calls)
    return frames / best


def main():
    from motok.data.root import resolve_data_root
    from motok.features.humanml3d import extract_features
    from motok.skeleton import load_skeleton

    torch.set_num_threads(1)
    golden_dir = resolve_data_root() / "humanml3d-sample"
    joints = np.load(golden_dir / "new_joints_012314.npy")
    golden = np.load(golden_dir / "new_joint_vecs_012314.npy")
    sk = load_skeleton("smpl22")
    raw = sk.directions
    args = (raw, sk.chains, sk.face_joints, list(sk.feet_left), list(sk.feet_right), sk.leg_joints)

    ours = extract_features(joints, sk, legacy=True).features
    base = baseline_features(joints, *args)
    frames = len(joints)
    r_base = _rate(lambda: baseline_features(joints, *args), frames)
    r_ours = _rate(lambda: extract_features(joints, sk, legacy=True), frames)
    r_def = _rate(lambda: extract_features(joints, sk), frames)
    print(f"golden clip: {frames} frames, 22 joints, one core")
    print(f"max |ours(legacy) - baseline| = {np.abs(ours - base).max():.2e}")
    print(f"max |baseline - official|, frames 0-88 = {np.abs(base[:89] - golden[:89]).max():.2e}")
    print(f"baseline (loops)        : {r_base:10.0f} frames/s")
    print(f"ours legacy=True        : {r_ours:10.0f} frames/s  ({r_ours / r_base:.1f}x)")
    print(f"ours default            : {r_def:10.0f} frames/s  ({r_def / r_base:.1f}x)")


if __name__ == "__main__":
    main()
