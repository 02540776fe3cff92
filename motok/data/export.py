"""``motok export bvh``: a clip of any motion artifact as a standard BVH.

HumanML3D's local rotations are per bone (siblings under one joint rotate independently),
which BVH cannot say: a BVH joint has one rotation that moves all of its children rigidly.
So the export re-derives per-joint rotations from the joint positions:

* rest offsets: each single-child joint keeps the canonical T-pose offset (direction x bone
  length); at a branching joint (hips, chest) the children's offsets are their frame-0 bone
  vectors in the best-fit (Kabsch) T-pose frame, so the rest pose is the T-pose up to the
  actor's own sibling geometry;
* per frame, top-down: a single-child joint takes the shortest rotation, relative to its
  parent, that points its child bone where the data has it (no twist, smooth); a branching
  joint takes the Kabsch rotation of its children's rest offsets onto their current vectors.

For rigid skeletons (mocap, SMPL) this reproduces the joint positions exactly up to float
round-off; the test checks < 1 mm after a write/parse round trip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motok.data.bvh import write_bvh
from motok.data.skeleton import Skeleton
from motok.rotations import matrix_to_quat, qbetween, qinv, qmul, qrot


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rotations R (T,3,3) minimising sum |R src_k - dst_k|^2; src (K,3), dst (T,K,3)."""
    h = np.einsum("ki,tkj->tij", src, dst)  # covariance sum_k src_k dst_k^T
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("tji,tkj->tik", vt, u)))
    fix = np.ones(u.shape[:-1])
    fix[:, -1] = d
    return np.einsum("tji,tj,tkj->tik", vt, fix, u)


def _levels(parents: np.ndarray) -> list[np.ndarray]:
    depth = np.zeros(len(parents), dtype=int)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [np.flatnonzero(depth == d) for d in range(depth.max() + 1)]


def bvh_pose(joints: np.ndarray, skeleton: Skeleton, offsets: np.ndarray):
    """Per-joint BVH rest offsets (J,3) and local quaternions (T,J,4) that reproduce ``joints``."""
    joints = np.asarray(joints, dtype=np.float64)
    T, J, _ = joints.shape
    parents = skeleton.parents
    children = [np.flatnonzero(parents == j) for j in range(J)]
    bone = joints - joints[:, np.maximum(parents, 0)]  # (T,J,3); row 0 unused
    rest = np.array(offsets, dtype=np.float64)
    rest[0] = 0.0
    lengths = np.linalg.norm(bone[0], axis=-1)
    rest[1:] = skeleton.directions[1:] * lengths[1:, None]

    branching = [j for j in range(J) if len(children[j]) > 1]
    for j in branching:
        r0 = _kabsch(rest[children[j]], bone[:1, children[j]])[0]
        rest[children[j]] = bone[0, children[j]] @ r0  # r0^T v: frame-0 vectors in the rest frame

    glob = np.zeros((T, J, 4))
    glob[..., 0] = 1.0
    for level in _levels(parents):
        for j in level:  # a level holds few joints; the work per joint is vectorized over frames
            kids = children[j]
            parent_rot = glob[:, parents[j]] if parents[j] >= 0 else glob[:, j]
            if len(kids) == 0:
                glob[:, j] = parent_rot
            elif len(kids) == 1:
                c = kids[0]
                target = qrot(qinv(parent_rot), bone[:, c])
                swing = qbetween(np.broadcast_to(rest[c], target.shape), target)
                glob[:, j] = qmul(parent_rot, swing)
            else:
                glob[:, j] = matrix_to_quat(_kabsch(rest[kids], bone[:, kids]))
    local = glob.copy()
    local[:, 1:] = qmul(qinv(glob[:, parents[1:]]), glob[:, 1:])
    return rest, local


def export_bvh(path: str | Path, joints: np.ndarray, skeleton: Skeleton, offsets: np.ndarray, fps: float,
               order: str = "ZXY", units: float = 100.0) -> Path:
    """Write joint positions (metres) as a BVH in ``units`` per metre (100: centimetres)."""
    rest, local = bvh_pose(joints, skeleton, offsets)
    ends = {}
    for j in range(skeleton.num_joints):
        if not np.any(skeleton.parents == j):
            # End Sites need a length for viewers to draw the last bone: a quarter of the bone before it.
            ends[j] = 0.25 * rest[j] if j > 0 else np.array([0.0, 0.1, 0.0])
    write_bvh(path, list(skeleton.joints), skeleton.parents, rest * units, local, joints[:, 0] * units, fps,
              order=order, end_sites={k: v * units for k, v in ends.items()})
    return Path(path)
