"""The humanoid's MJCF text: collision geometry sized from the skeleton (capsules along bones with
radii by body part, head and hand spheres, box feet and toes) and the XML around it. Called by
:func:`motok.sim.humanoid.build_humanoid`, which measures the data and chooses ranges and gains."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np

from motok.data.skeleton import Skeleton
from motok.sim.humanoid import META_NAME, UP, HumanoidConfig, Layout, joint_chain


def _fmt(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.atleast_1d(v))


def _parts(layout: Layout, skeleton: Skeleton) -> dict[str, set]:
    """Joint sets by body part, from the skeleton's feet, hands and head (no names assumed)."""
    ankles = {skeleton.feet_left[0], skeleton.feet_right[0]}
    return {"ankles": ankles, "toes": {skeleton.feet_left[1], skeleton.feet_right[1]},
            "hands": {e for e in skeleton.end_effectors if e not in ankles and e != skeleton.head},
            "legs": {k for f in ankles for k in joint_chain(layout, f)}, "spine": {0, *joint_chain(layout, skeleton.head)}}


# Capsule radii (m, for a 1.70 m person) by bone: the part of the body a bone parent -> child crosses.
RADII = {"pelvis": 0.09, "lower_torso": 0.10, "upper_torso": 0.11, "neck": 0.05, "chest_to_shoulder": 0.065,
         "clavicle": 0.05, "upper_arm": 0.045, "forearm": 0.04, "thigh": 0.065, "shin": 0.05}


def _bone_part(j: int, c: int, par: np.ndarray, parts: dict, head: int) -> str | None:
    spine, legs = parts["spine"], parts["legs"]
    if c in parts["toes"] or (j == 0 and c in legs):
        return None  # the foot box and the pelvis capsule cover these
    if j in spine and c in spine:
        return "neck" if c == head else ("lower_torso" if j == 0 else "upper_torso")
    if j in spine:
        return "chest_to_shoulder"
    if j in legs:
        return "thigh" if par[j] == 0 else "shin"
    if par[j] in spine:
        return "clavicle"
    return "forearm" if c in parts["hands"] else "upper_arm"


def body_geoms(layout: Layout, skeleton: Skeleton, foot: dict, s: float) -> dict[int, list[dict]]:
    """Capsules along bones with radii by body part, a head sphere, hand spheres, box feet and toes."""
    par, rest, kids = layout.parents, layout.rest, layout.children
    parts = _parts(layout, skeleton)
    out: dict[int, list[dict]] = {j: [] for j in range(len(layout.names))}

    def capsule(j, a, b, r):
        if np.linalg.norm(b - a) > 1e-4:
            out[j].append(dict(type="capsule", fromto=_fmt(np.concatenate([a, b])), size=_fmt(r * s)))

    hips = [c for c in kids[0] if c in parts["legs"]]
    if len(hips) == 2:  # pelvis: one capsule across the hip joints, a little inside them
        capsule(0, rest[hips[0]] * 0.8, rest[hips[1]] * 0.8, RADII["pelvis"])
    for j in range(len(layout.names)):
        for c in kids[j]:
            part = _bone_part(j, c, par, parts, skeleton.head)
            if part is not None:
                # Thighs start below the hip joint so the two legs do not touch at rest.
                start = rest[c] * 0.15 if part == "thigh" else np.zeros(3)
                capsule(j, start, rest[c], RADII[part])
    out[skeleton.head].append(dict(type="sphere", pos=_fmt(UP * 0.085 * s), size=_fmt(0.095 * s)))
    for h in parts["hands"]:
        d = rest[h] / np.linalg.norm(rest[h])
        out[h].append(dict(type="sphere", pos=_fmt(d * 0.05 * s), size=_fmt(0.042 * s)))
    for a, t in zip((skeleton.feet_left[0], skeleton.feet_right[0]), (skeleton.feet_left[1], skeleton.feet_right[1])):
        sole = -foot["ankle_height"]  # the rest pose stands the foot flat: sole at the stance ankle height
        heel, tip = -0.05 * s, rest[t][0]
        height = 0.6 * foot["ankle_height"] + 0.02
        out[a].append(dict(type="box", pos=_fmt([(heel + tip) / 2, rest[t][1] / 2, sole + height / 2]),
                           size=_fmt([(tip - heel) / 2, 0.045 * s, height / 2])))
        toe_sole = sole - rest[t][2]
        out[t].append(dict(type="box", pos=_fmt([0.025 * s, 0, toe_sole + 0.0125 * s]),
                           size=_fmt([0.025 * s, 0.04 * s, 0.0125 * s])))
    return out


def geom_volume(g: dict) -> float:
    r = np.array(g["size"].split(), dtype=float)
    if g["type"] != "capsule":
        return 4 / 3 * np.pi * r[0] ** 3 if g["type"] == "sphere" else 8 * np.prod(r)
    ft = np.array(g["fromto"].split(), dtype=float)
    return np.pi * r[0] ** 2 * np.linalg.norm(ft[3:] - ft[:3]) + 4 / 3 * np.pi * r[0] ** 3


_HEADER = """<mujoco model="motok_humanoid">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:.8g}" integrator="implicitfast" iterations="{it}" ls_iterations="{ls}"/>
  <visual><global offwidth="1280" offheight="720"/><quality shadowsize="2048"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".82 .84 .86" rgb2=".7 .72 .76" width="512" height="512"/>
    <texture name="sky" type="skybox" builtin="gradient" rgb1=".96 .96 .95" rgb2=".8 .84 .9" width="256" height="256"/>
    <material name="floor" texture="grid" texrepeat="8 8" reflectance="0.05"/>
    <material name="body" rgba=".85 .6 .42 1"/>
  </asset>
  <default>
    <joint armature="{armature:g}" damping="0" limited="true"/>
    <geom density="{density:.9g}" friction="{friction:g} 0.005 0.0001" material="body" condim="3" contype="1"
          conaffinity="{self_collide}"/>
    <position ctrllimited="true"/>
  </default>
  <worldbody>
    <light name="sun" pos="0 0 4" dir="0 0 -1" directional="true" castshadow="true" diffuse=".8 .8 .8"/>
    <geom name="floor" type="plane" size="0 0 0.05" material="floor" contype="1" conaffinity="1"/>
  </worldbody>
</mujoco>"""


def mjcf_text(layout: Layout, geoms: dict, cfg: HumanoidConfig, density: float, ranges: dict, gains: dict,
          excludes: list, meta: dict) -> str:
    root = ET.fromstring(_HEADER.format(timestep=cfg.timestep, it=cfg.solver_iterations,
                                        ls=max(4, cfg.solver_iterations // 2), armature=cfg.armature, density=density,
                                        friction=cfg.friction, self_collide=int(cfg.self_collision)))
    elems = {-1: root.find("worldbody")}
    for j, name in enumerate(layout.names):
        p = layout.parents[j]
        pos = layout.rest[j] if p >= 0 else np.array([0, 0, meta["root_height"]])
        b = elems[j] = ET.SubElement(elems[p], "body", name=name, pos=_fmt(pos))
        if layout.kinds[j] == "free":
            ET.SubElement(b, "freejoint", name="root")
        for k, a in enumerate(layout.axes[j]):
            hn = f"{name}_{a[-1]}"
            ET.SubElement(b, "joint", name=hn, type="hinge", axis=_fmt(layout.axis_vectors(j)[k]), range=_fmt(ranges[hn]))
        for g in geoms[j]:
            ET.SubElement(b, "geom", **g)
    contact = ET.SubElement(root, "contact")
    for a, b in excludes:
        ET.SubElement(contact, "exclude", body1=a, body2=b)
    act = ET.SubElement(root, "actuator")
    for hn in layout.hinge_names:
        kp = gains[hn]
        ET.SubElement(act, "position", name=hn, joint=hn, kp=f"{kp:.6g}", kv=f"{kp * cfg.derivative_time:.6g}",
                      ctrlrange=_fmt(ranges[hn]))
    ET.SubElement(ET.SubElement(root, "custom"), "text", name=META_NAME, data=json.dumps(meta, separators=(",", ":")))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode")
