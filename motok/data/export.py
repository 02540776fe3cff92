"""``motok export bvh``: a clip of any motion artifact as a standard BVH, and the BVH writer.

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

import math
from pathlib import Path

import numpy as np

from motok.atomic import atomic_path
from motok.data.dataset import MotionFile
from motok.errors import UserError
from motok.rotations import kabsch, matrix_to_quat, qbetween, qinv, qmul, qrot, quat_to_euler
from motok.skeleton import Skeleton


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
        r0 = kabsch(rest[children[j]], bone[:1, children[j]])[0]
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
                glob[:, j] = matrix_to_quat(kabsch(rest[kids], bone[:, kids]))
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


def export_clip(artifact, clip, path: str | Path, order: str = "ZXY") -> Path:
    """Clip ``clip`` (name or index) of a motion or motion-dataset artifact as BVH in centimetres."""
    with MotionFile(artifact) as mf:
        c = mf.clip(clip)
        return export_bvh(path, c.joints, mf.skeleton, mf.offsets, mf.fps, order=order)


def write_bvh(path, names, parents, offsets, rotations, root_positions, fps, order="ZXY",
              end_sites=None) -> None:
    """Write BVH as Blender's importer reads it: one keyword per line, braces on their own lines,
    6 channels on the root, 3 rotation channels elsewhere (so non-root translations are the
    ``offsets``), an End Site on every leaf (``end_sites[j]``, else a zero offset). ``rotations``
    are local quaternions ``(T, J, 4)``; ``root_positions`` is ``(T, 3)``."""
    names = [str(n) for n in names]
    parents = np.asarray(parents, dtype=np.int64)
    offsets, rotations = np.asarray(offsets, dtype=np.float64), np.asarray(rotations, dtype=np.float64)
    root_positions = np.asarray(root_positions, dtype=np.float64)
    J, T, order = len(names), len(rotations), str(order).upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise UserError(f"order must be a permutation of XYZ, got {order!r}")
    if parents.shape != (J,) or offsets.shape != (J, 3) or rotations.shape != (T, J, 4) \
            or root_positions.shape != (T, 3):
        raise ValueError(f"{J} names but parents {parents.shape}, offsets {offsets.shape} (J,3), "
                         f"rotations {rotations.shape} (T,J,4), root_positions {root_positions.shape} (T,3)")
    bad = [n for n in names if not n.strip() or any(c in n for c in "{}\r\n")]
    if bad or len(set(names)) != J or not (math.isfinite(fps) and fps > 0) or (parents < 0).sum() != 1:
        raise ValueError(f"need distinct joint names without braces or newlines (bad: {bad}), fps > 0 "
                         f"(got {fps}) and exactly one root (parent -1)")
    children = [np.flatnonzero(parents == j).tolist() for j in range(J)]
    rot_ch, fmt, end_sites = " ".join(f"{a}rotation" for a in order), "%.6f", end_sites or {}
    lines, written = ["HIERARCHY"], []

    def emit(j, pad):
        root = parents[j] < 0
        lines.extend([f"{pad}{'ROOT' if root else 'JOINT'} {names[j]}", f"{pad}{{",
                      f"{pad}\tOFFSET " + " ".join(fmt % v for v in offsets[j]),
                      f"{pad}\tCHANNELS " + ("6 Xposition Yposition Zposition " if root else "3 ") + rot_ch])
        written.append(j)
        for c in children[j]:
            emit(c, pad + "\t")
        if not children[j]:
            end = np.asarray(end_sites.get(j, np.zeros(3)), dtype=np.float64).reshape(3)
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET " + " ".join(fmt % v for v in end),
                          f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    emit(int(np.flatnonzero(parents < 0)[0]), "")
    if len(written) != J:
        raise ValueError("parents do not form one tree reaching every joint")
    table = np.concatenate([root_positions, quat_to_euler(rotations[:, written], order).reshape(T, -1)], axis=1)
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / fps:.8f}"]
    row = " ".join([fmt] * table.shape[1])
    lines += [row % tuple(r) for r in table.tolist()]
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as f:
        f.write("\n".join(lines) + "\n")
