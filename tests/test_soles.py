"""Sole slip (motok.sim.soles): the box corners against MuJoCo's own geometry, known slip values
for planted, sliding and rolling feet, and the reference walks' slip on real data; the floor
contacts' forces and slip against a box resting and one pushed along the floor."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from motok.rotations import quat_to_matrix
from motok.sim.soles import SLIP_SPEED, contact_runs, floor_contacts, slip_sums, soles


def test_corners_are_the_bottom_corners_of_mujocos_boxes(hum, lib):
    m, d = hum.model, mujoco.MjData(hum.model)
    f = lib.starts[0] + 10
    d.qpos[:] = lib.qpos[f]
    mujoco.mj_kinematics(m, d)
    sole = soles(hum)
    boxes = np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_BOX)
    assert len(boxes) == 4 and len(sole.joint) == 16  # two feet and two toes, four corners each
    mine = sole.world(d.xpos[hum.body_ids], d.xmat[hum.body_ids].reshape(-1, 3, 3))
    for b, g in enumerate(boxes):
        sx, sy, sz = m.geom_size[g]
        want = [d.geom_xpos[g] + d.geom_xmat[g].reshape(3, 3) @ [x, y, -sz] for x in (-sx, sx) for y in (-sy, sy)]
        np.testing.assert_allclose(mine[4 * b:4 * b + 4], want, atol=1e-9)
    # the same from the library's own body states (quaternions), which the reference is measured on
    via_quat = sole.world(lib.body_pos[f], quat_to_matrix(lib.body_quat[f]))
    np.testing.assert_allclose(via_quat, mine, atol=1e-6)


def test_known_slip_values():
    dt = 1 / 30
    T, K = 31, 4
    planted = np.zeros((T, K, 3))
    s = slip_sums(planted, dt).result()
    assert s["sole_slip_cm_s"] == 0 and s["sole_contact_fraction"] == 1 and s["sole_slip_ratio"] == 0
    # sliding at 0.3 m/s along x and 0.4 along y: 50 cm/s at every corner step
    slide = planted.copy()
    slide[..., 0] = (np.arange(T) * 0.3 * dt)[:, None]
    slide[..., 1] = (np.arange(T) * 0.4 * dt)[:, None]
    s = slip_sums(slide, dt).result()
    assert s["sole_slip_cm_s"] == pytest.approx(50.0) and s["sole_slip_ratio"] == 1
    # lifted corners (above 1 cm) are not in contact, whatever they do; a step counts only when
    # the corner touches at both ends
    lifted = slide.copy()
    lifted[:, 2:, 2] = 0.05
    s = slip_sums(lifted, dt)
    assert s.contact == (T - 1) * 2 and s.steps == (T - 1) * K
    # a foot rolling over its front edge: the edge's corners stay put while the heel's rise
    roll = np.zeros((T, K, 3))
    roll[:, :2, 0] = 0.2  # the toe edge
    angle = np.linspace(0, 0.6, T)
    roll[:, 2:, 0] = 0.2 - 0.2 * np.cos(angle)[:, None]
    roll[:, 2:, 2] = (0.2 * np.sin(angle))[:, None]
    s = slip_sums(roll, dt)
    assert s.slip < 0.05 * s.contact  # only the heel's first steps, still within 1 cm, move a little
    assert slip_sums(roll[:, :2], dt).result()["sole_slip_cm_s"] == 0
    # states outside the clip (valid False) are not steps of it
    valid = np.ones(T, bool)
    valid[20:] = False
    assert slip_sums(slide, dt, valid).contact == 19 * K


def test_reference_walks_hardly_slide_and_a_drifting_copy_does(hum, lib):
    """The data's soles, measured on the library's poses at the control rate: walking, most of
    their touching corner steps are slower than 5 cm/s; the same walks dragged sideways at 0.5 m/s
    (a skating reference) slide at about that speed at nearly every step."""
    sole = soles(hum)
    corners = sole.world(lib.body_pos, quat_to_matrix(lib.body_quat))
    dt = 1 / hum.control_hz

    def measure(c):
        total = slip_sums(c[lib.starts[0]:lib.starts[1]], dt)
        for a, b in zip(lib.starts[1:-1], lib.starts[2:]):
            total.add(slip_sums(c[a:b], dt))
        return total.result()

    walk = np.median(np.linalg.norm(lib.body_vel[:, 0, :2], axis=-1))
    assert walk > 0.8  # these are walks
    r = measure(corners)
    assert 0.2 < r["sole_contact_fraction"] < 0.8  # each foot touches for part of the gait
    assert r["sole_slip_ratio"] < 0.5 and r["sole_slip_cm_s"] < 0.25 * 100 * walk
    drift = corners.copy()
    for a, b in zip(lib.starts[:-1], lib.starts[1:]):
        drift[a:b, :, 1] += (np.arange(b - a) * 0.5 * dt)[:, None]
    d = measure(drift)
    assert d["sole_contact_fraction"] == r["sole_contact_fraction"]  # heights untouched
    assert d["sole_slip_ratio"] > 0.95 and 40 < d["sole_slip_cm_s"] < 50 + r["sole_slip_cm_s"]
    assert SLIP_SPEED == 0.05


BOX_ON_FLOOR = """<mujoco><option timestep="0.0083333333" integrator="implicitfast"/>
<worldbody><geom type="plane" size="0 0 0.05" friction="0.8"/>
<body pos="0 0 0.04"><freejoint/><geom type="box" size="0.07 0.04 0.03" mass="10" friction="0.8"/></body>
</worldbody></mujoco>"""


def test_floor_contacts_carry_the_weight_and_slide_at_the_cone_when_pushed():
    m = mujoco.MjModel.from_xml_string(BOX_ON_FLOOR)
    d, feet, weight = mujoco.MjData(m), m.geom_bodyid > 0, 10 * 9.81
    for _ in range(120):  # settle
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    c = floor_contacts(m, d, feet)
    assert len(c) == 4 and set(c[:, 4]) == {1}  # the box's four bottom corners, all the box's geom
    assert c[:, 0].sum() == pytest.approx(weight, rel=0.01) and c[:, 2].max() < 1e-3 and (c[:, 3] < 0).all()
    # pushed at twice what friction holds: it slides, each contact's friction at the cone's edge
    # (the pyramid's, within a few %) and its slip the box's own speed (the box does not turn)
    d.xfrc_applied[1, 0] = 2 * 0.8 * weight
    for _ in range(60):
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    c = floor_contacts(m, d, feet)
    assert c[:, 1].sum() == pytest.approx(0.8 * c[:, 0].sum(), rel=0.05)
    np.testing.assert_allclose(c[:, 2], np.hypot(*d.qvel[:2]), rtol=1e-3)
    assert d.qvel[0] > 1.0
    assert len(floor_contacts(m, d, np.zeros(m.ngeom, bool))) == 0  # no foot marked: nothing


def test_contact_runs_are_the_lengths_of_unbroken_contacts():
    flags = np.array([[0, 1], [1, 1], [1, 0], [0, 0], [1, 0]], bool)  # (T, G)
    assert contact_runs(flags).tolist() == [2, 1, 2]  # geom 0: 2 then 1 (at the end), geom 1: 2 (from the start)
    assert contact_runs(np.zeros((3, 2), bool)).size == 0
