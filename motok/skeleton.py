"""Skeleton definitions as data.

A :class:`Skeleton` names the joints, their tree, the rest direction of each bone in the
canonical T-pose (Y up, facing +Z, the character's left on +X), the kinematic chains the
HumanML3D inverse kinematics walks, and the joints that features need: the face joints
(right hip, left hip, right shoulder, left shoulder), the foot joints for contacts, the leg
bones used for scaling, the head and the end effectors. Built-in definitions live in
``motok/skeletons/*.yaml``; a user passes a path to a YAML file of the same form.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from motok.errors import MotokError

BUILTIN_DIR = Path(__file__).with_name("skeletons")


class SkeletonError(MotokError, ValueError):
    pass


@dataclass(frozen=True, eq=False)
class Skeleton:
    name: str
    joints: tuple[str, ...]
    parents: np.ndarray  # (J,) int, -1 for the root
    directions: np.ndarray  # (J, 3) unit rest directions of bone parent->joint (root: zeros)
    chains: tuple[tuple[int, ...], ...]
    face_joints: tuple[int, int, int, int]  # r_hip, l_hip, r_shoulder, l_shoulder
    feet_left: tuple[int, ...]
    feet_right: tuple[int, ...]
    leg_joints: tuple[int, int]
    head: int
    end_effectors: tuple[int, ...]
    contact_threshold: float = 0.002  # m^2 per frame at 20 fps, see docs/features.md

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    @property
    def feature_dim(self) -> int:
        return 12 * self.num_joints - 1

    def index(self, name: str) -> int:
        try:
            return self.joints.index(name)
        except ValueError:
            raise SkeletonError(f"skeleton {self.name!r} has no joint {name!r}") from None

    def to_dict(self) -> dict:
        j = self.joints
        return {
            "name": self.name,
            "joints": [[n, None if p < 0 else j[p], [float(x) for x in d]]
                       for n, p, d in zip(j, self.parents.tolist(), self.directions)],
            "chains": [[j[i] for i in c] for c in self.chains],
            "face_joints": [j[i] for i in self.face_joints],
            "feet_left": [j[i] for i in self.feet_left],
            "feet_right": [j[i] for i in self.feet_right],
            "leg_joints": [j[i] for i in self.leg_joints],
            "head": j[self.head],
            "end_effectors": [j[i] for i in self.end_effectors],
            "contact_threshold": self.contact_threshold,
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "<dict>") -> "Skeleton":
        def need(key):
            if key not in d:
                raise SkeletonError(f"{source}: skeleton definition lacks field {key!r}")
            return d[key]

        rows = need("joints")
        names = [str(r[0]) for r in rows]
        if len(set(names)) != len(names):
            raise SkeletonError(f"{source}: field 'joints' repeats a joint name")
        lookup = {n: i for i, n in enumerate(names)}

        def idx(name, field):
            if name not in lookup:
                raise SkeletonError(f"{source}: field {field!r} names unknown joint {name!r}")
            return lookup[name]

        parents = []
        for i, r in enumerate(rows):
            if len(r) != 3:
                raise SkeletonError(f"{source}: joints[{i}] must be [name, parent, [dx, dy, dz]], got {r!r}")
            p = -1 if r[1] is None else idx(r[1], f"joints[{i}].parent")
            if p >= i:
                raise SkeletonError(f"{source}: joints[{i}] ({names[i]}) must come after its parent {r[1]!r}")
            parents.append(p)
        if parents[0] != -1 or parents.count(-1) != 1:
            raise SkeletonError(f"{source}: exactly one root, listed first, is expected")
        dirs = np.array([r[2] for r in rows], dtype=np.float64)
        norms = np.linalg.norm(dirs[1:], axis=-1)
        if np.any(norms < 1e-8):
            raise SkeletonError(f"{source}: every non-root joint needs a non-zero rest direction")
        dirs[1:] /= norms[:, None]
        chains = tuple(tuple(idx(n, "chains") for n in c) for c in need("chains"))
        covered = {i for c in chains for i in c[1:]}
        if covered != set(range(1, len(names))):
            missing = [names[i] for i in sorted(set(range(1, len(names))) - covered)]
            raise SkeletonError(f"{source}: field 'chains' must reach every joint once; missing {missing}")
        for c in chains:
            for a, b in zip(c[:-1], c[1:]):
                if parents[b] != a:
                    raise SkeletonError(f"{source}: chain step {names[a]}->{names[b]} is not a parent->child bone")
        face = tuple(idx(n, "face_joints") for n in need("face_joints"))
        if len(face) != 4:
            raise SkeletonError(f"{source}: field 'face_joints' needs 4 joints (r_hip, l_hip, r_shoulder, l_shoulder)")
        leg = tuple(idx(n, "leg_joints") for n in need("leg_joints"))
        if len(leg) != 2:
            raise SkeletonError(f"{source}: field 'leg_joints' needs 2 joints")
        return cls(
            name=str(need("name")),
            joints=tuple(names),
            parents=np.array(parents, dtype=np.int64),
            directions=dirs,
            chains=chains,
            face_joints=face,  # type: ignore[arg-type]
            feet_left=tuple(idx(n, "feet_left") for n in need("feet_left")),
            feet_right=tuple(idx(n, "feet_right") for n in need("feet_right")),
            leg_joints=leg,  # type: ignore[arg-type]
            head=idx(need("head"), "head"),
            end_effectors=tuple(idx(n, "end_effectors") for n in d.get("end_effectors", [])),
            contact_threshold=float(d.get("contact_threshold", 0.002)),
        )


def builtin_names() -> list[str]:
    return sorted(p.stem for p in BUILTIN_DIR.glob("*.yaml"))


def load_skeleton(name_or_path: str | Path) -> Skeleton:
    """A built-in skeleton by name (``smpl22``, ``bandai21``) or a user YAML file by path."""
    p = Path(name_or_path)
    if not p.suffix and (BUILTIN_DIR / f"{p.name}.yaml").exists():
        p = BUILTIN_DIR / f"{p.name}.yaml"
    if not p.exists():
        raise SkeletonError(
            f"unknown skeleton {str(name_or_path)!r}: not a built-in ({', '.join(builtin_names())}) "
            "and no such YAML file")
    try:
        d = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise SkeletonError(f"{p}: not valid YAML: {e}") from None
    if not isinstance(d, dict):
        raise SkeletonError(f"{p}: a skeleton definition must be a mapping")
    return Skeleton.from_dict(d, source=str(p))


def detect_skeleton(joint_names: list[str] | None = None, num_joints: int | None = None) -> Skeleton:
    """Pick the built-in skeleton whose joints are all among ``joint_names`` (or, for a
    bare position array, the only built-in with ``num_joints`` joints)."""
    matches = []
    for name in builtin_names():
        sk = load_skeleton(name)
        if joint_names is not None and set(sk.joints) <= set(joint_names):
            matches.append(sk)
        elif joint_names is None and num_joints == sk.num_joints:
            matches.append(sk)
    if len(matches) == 1:
        return matches[0]
    what = f"joints {list(joint_names)[:8]}..." if joint_names is not None else f"{num_joints} joints"
    if not matches:
        raise SkeletonError(f"no built-in skeleton matches {what}; pass --skeleton PATH.yaml "
                            f"(see docs/features.md for the format)")
    raise SkeletonError(f"several skeletons match {what}: {[m.name for m in matches]}; pass --skeleton")
