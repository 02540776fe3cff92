"""The humanoid's MJCF (``motok sim build-humanoid``): :func:`build_humanoid` measures a
motion-dataset (or any motion artifact: ``motok view`` on generated motion) and writes the model;
:func:`body_geoms` and :func:`mjcf_text` are the geometry and the XML around it.

The builder takes the rest geometry from the data (:func:`motok.sim.retarget.rest_geometry`: the
dataset's bone lengths, the mocap's own sibling geometry at the hips and chest, feet pitched to lie
flat at rest), the joint layout from :func:`motok.sim.humanoid.make_layout`, joint ranges from the
data's range of motion (every sampled frame through the inverse kinematics) plus a margin, and PD
gains proportional to the mass each joint moves. Collision geometry is sized from the skeleton:
capsules along bones with radii by body part, head and hand spheres, box feet and toes, one density
for the configured total mass. A contact filter by body part (:func:`contact_bits`) chooses which
bodies may touch each other; the pairs it allows that touch at rest are excluded. The builder is
split so a benchmark can measure a body once and write it with many options:
:func:`measure_humanoid` (the data) and :func:`humanoid_xml` (gains, contacts, solver).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from motok.artifacts import command_line, hash_inputs
from motok.atomic import atomic_path
from motok.data.dataset import MotionFile
from motok.sim.humanoid import (META_NAME, META_VERSION, UP, HumanoidConfig, Layout, joint_chain, load_humanoid,
                                make_layout, to_mj)
from motok.sim.retarget import rest_geometry, solve_pose
from motok.skeleton import Skeleton


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


# ----------------------------------------------------------------------------- contacts

FLOOR = 1  # bit 0: every body geom has it in contype and the floor in conaffinity, so all touch the floor
# One bit per pair of body-part groups that may touch: group A carries it in contype, group B in
# conaffinity, and MuJoCo lets two geoms collide when (contype1 & conaffinity2) | (contype2 &
# conaffinity1) is non-zero. A bit's two sides are disjoint, so it joins A to B and nothing else
# (not A to A), and body conaffinities never carry the floor bit.
PAIR_BITS = {"arms-trunk": 2, "arms-thighs": 4, "arm-arm": 8, "leg-leg": 16}
MODE_PAIRS = {"data": ("arms-trunk", "arms-thighs", "arm-arm", "leg-leg"), "legs": ("leg-leg",), "none": ()}


def contact_groups(layout: Layout, skeleton: Skeleton) -> dict[str, list[set]]:
    """Body parts by joint index, from the skeleton's feet, toes, hands and head (no names assumed):
    ``trunk`` (root up to the joint the arms branch from), ``arms`` (upper arm, forearm, hand; one
    set per arm), ``legs`` (thigh to toes; one set per leg), ``thighs``. Head, neck and clavicles
    belong to none: they touch only the floor."""
    parts = _parts(layout, skeleton)
    spine, par = parts["spine"], layout.parents
    arms = [{k for k in joint_chain(layout, h) if k not in spine and par[k] not in spine}
            for h in sorted(parts["hands"])]
    branch = {int(par[k]) for h in parts["hands"] for k in joint_chain(layout, h) if par[k] in spine and k not in spine}
    trunk = {0} | {k for b in branch for k in joint_chain(layout, b)}
    legs = [set(joint_chain(layout, f[0])) | {f[1]} for f in (skeleton.feet_left, skeleton.feet_right)]
    return {"trunk": [trunk], "arms": arms, "legs": legs, "thighs": [{k for k in legs[0] | legs[1] if par[k] == 0}]}


def contact_bits(layout: Layout, skeleton: Skeleton, mode: str) -> list[tuple[int, int]]:
    """``(contype, conaffinity)`` of each joint's geoms for a ``HumanoidConfig.self_collision`` mode.

    ``all``: every geom collides with every other (MuJoCo still skips parent and child). ``data``:
    the arms with the trunk, the thighs and the other arm, and one leg with the other, the pairs
    that touch in Bandai-Namco set 2 (reference poses and PD tracking with falls: upper arm vs
    spine, forearm and hand vs hips and thigh, hand vs hand, shins, feet and toes of the two legs).
    ``legs``: the legs only. ``none``: the floor only."""
    J = len(layout.names)
    if mode == "all":
        return [(FLOOR, FLOOR)] * J
    g = contact_groups(layout, skeleton)
    sides = {"arms-trunk": (g["trunk"][0], set().union(*g["arms"])),
             "arms-thighs": (g["thighs"][0], set().union(*g["arms"])),
             "arm-arm": tuple(g["arms"]), "leg-leg": tuple(g["legs"])}
    ct, ca = [FLOOR] * J, [0] * J
    for pair in MODE_PAIRS[mode]:
        a, b = sides[pair]
        for j in a:
            ct[j] |= PAIR_BITS[pair]
        for j in b:
            ca[j] |= PAIR_BITS[pair]
    return list(zip(ct, ca))


# ----------------------------------------------------------------------------- XML

_HEADER = """<mujoco model="motok_humanoid">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:.8g}" integrator="implicitfast" iterations="{it}" ls_iterations="{ls}"
          jacobian="{jacobian}" cone="{cone}" impratio="{impratio:.8g}" noslip_iterations="{noslip}"/>
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
          conaffinity="1" solref="{solref}" solimp="{solimp}"/>
    <position ctrllimited="true"/>
  </default>
  <worldbody>
    <light name="sun" pos="0 0 4" dir="0 0 -1" directional="true" castshadow="true" diffuse=".8 .8 .8"/>
    <geom name="floor" type="plane" size="0 0 0.05" material="floor" contype="1" conaffinity="1" solref="{solref}"
          solimp="{solimp}"/>
  </worldbody>
</mujoco>"""


def mjcf_text(layout: Layout, geoms: dict, cfg: HumanoidConfig, density: float, ranges: dict, gains: dict,
              excludes: list, meta: dict, bits: list[tuple[int, int]] | None = None) -> str:
    """The XML; ``bits``: per joint ``(contype, conaffinity)`` from :func:`contact_bits` (default: all collide)."""
    root = ET.fromstring(_HEADER.format(timestep=cfg.timestep, it=cfg.solver_iterations, ls=cfg.ls_iterations,
                                        jacobian=cfg.jacobian, armature=cfg.armature, density=density,
                                        friction=cfg.friction, cone=cfg.cone, impratio=cfg.impratio,
                                        noslip=cfg.noslip_iterations, solref=_fmt(cfg.contact_solref),
                                        solimp=_fmt(cfg.contact_solimp)))
    if not cfg.islands:
        ET.SubElement(root.find("option"), "flag", island="disable")
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
        ct, ca = bits[j] if bits else (FLOOR, FLOOR)
        filt = {} if (ct, ca) == (FLOOR, FLOOR) else {"contype": str(ct), "conaffinity": str(ca)}
        for g in geoms[j]:
            ET.SubElement(b, "geom", **g, **filt)
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


# ----------------------------------------------------------------------------- building

# What measure_humanoid reads from the config; humanoid_xml may vary everything else.
BODY_FIELDS = ("total_mass", "range_margin_deg", "max_frames")


@dataclass
class HumanoidBody:
    """What the data decides (geometry, ranges, mass), before gains, contacts and solver options."""

    cfg: HumanoidConfig
    skeleton: Skeleton
    layout: Layout
    geoms: dict
    density: float
    ranges: dict
    foot: dict
    root_height: float
    height: float
    frames_used: int
    source: str
    inputs: dict


def _moved_mass(model, layout: Layout, skeleton: Skeleton, body_ids: np.ndarray) -> dict[str, float]:
    """Mass each hinge moves: its subtree, or for leg joints the larger side (a stance leg carries the body)."""
    total = float(model.body_subtreemass[body_ids[0]])
    legs = set(joint_chain(layout, skeleton.feet_left[0])) | set(joint_chain(layout, skeleton.feet_right[0]))
    out = {}
    for j, name in enumerate(layout.names):
        sub = float(model.body_subtreemass[body_ids[j]])
        out.update({f"{name}_{a[-1]}": max(sub, total - sub) if j in legs else sub for a in layout.axes[j]})
    return out


def measure_humanoid(data_path, cfg: HumanoidConfig | None = None) -> HumanoidBody:
    """The slow, data-dependent half of :func:`build_humanoid` (inverse kinematics of the sampled frames)."""
    cfg = cfg or HumanoidConfig()
    # Any motion artifact: a dataset measures the body best (its range of motion sets the joint
    # ranges), but generated motion has the same skeleton and shows on the body its frames measure.
    with MotionFile(data_path) as mf:
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
    geoms = body_geoms(layout, skeleton, foot, height / 1.70)
    volume = sum(geom_volume(g) for gs in geoms.values() for g in gs)
    # qpos0 stands the rest pose on the floor: root height = leg drop to the ankle + stance ankle height.
    drop = -sum(layout.rest[k][2] for k in joint_chain(layout, skeleton.feet_left[0]))
    return HumanoidBody(cfg, skeleton, layout, geoms, cfg.total_mass / volume, ranges, foot,
                        float(drop + foot["ankle_height"] + 1e-3), height, len(frames), str(data_path),
                        hash_inputs([data_path]))


def humanoid_xml(body: HumanoidBody, cfg: HumanoidConfig | None = None) -> tuple[str, list[tuple[str, str]]]:
    """The MJCF text of a measured body with ``cfg``'s gains, contacts and solver; and the excluded pairs."""
    import mujoco

    cfg = cfg or body.cfg
    changed = [f for f in BODY_FIELDS if getattr(cfg, f) != getattr(body.cfg, f)]
    if changed:
        raise ValueError(f"{', '.join(changed)} differ from the config the body was measured with")
    layout, skeleton = body.layout, body.skeleton
    meta = dict(version=META_VERSION, skeleton=skeleton.to_dict(), control_hz=cfg.control_hz, config=asdict(cfg),
                foot=body.foot, root_height=body.root_height, source=body.source, inputs=body.inputs,
                command=command_line())
    bits = contact_bits(layout, skeleton, cfg.self_collision)
    parts = (layout, body.geoms, cfg, body.density, body.ranges)
    model = mujoco.MjModel.from_xml_string(mjcf_text(*parts, {n: 1.0 for n in layout.hinge_names}, [], meta, bits))
    body_ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in layout.names])
    gains = {n: max(cfg.stiffness_per_kg * m, cfg.min_stiffness)
             for n, m in _moved_mass(model, layout, skeleton, body_ids).items()}
    for a in (skeleton.feet_left[0], skeleton.feet_right[0]):
        for hn in (f"{layout.names[a]}_{x[-1]}" for x in layout.axes[a]):
            gains[hn] *= cfg.ankle_stiffness_scale
    excludes = _rest_contacts(model)
    return mjcf_text(*parts, gains, excludes, meta, bits), excludes


def build_humanoid(data_path, out, cfg: HumanoidConfig | None = None) -> dict:
    """Write the MJCF for a motion artifact (a ``motion-dataset`` for physics); returns a summary
    (mass, DoF, ranges...)."""
    cfg = cfg or HumanoidConfig()
    body = measure_humanoid(data_path, cfg)
    xml, excludes = humanoid_xml(body, cfg)
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.write_text(xml)
    hum = load_humanoid(out)
    m = hum.model
    return {"output": str(out), "bodies": m.nbody - 1, "hinges": m.nu, "nq": m.nq, "nv": m.nv,
            "mass_kg": round(float(m.body_subtreemass[1]), 2), "height_m": round(body.height, 3),
            "timestep_s": m.opt.timestep, "substeps": hum.substeps, "control_hz": cfg.control_hz,
            "self_collision": cfg.self_collision, "excluded_pairs": len(excludes), "frames_used": body.frames_used}


def _rest_contacts(model) -> list[tuple[str, str]]:
    """Body pairs the contact filter lets collide that touch at qpos0: structural overlaps (chest vs
    upper arms, ...), excluded."""
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
