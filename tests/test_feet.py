"""Feet that stand: the contact model in the MJCF and its metadata, a resume refused on another
one, a standing pose whose feet hold still under PD, the foot metrics of ``expert eval`` on
hand-made slides of real poses, and the foot-velocity term of the imitation reward."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from motok.sim.humanoid import HumanoidConfig, HumanoidError, config_difference, humanoid_from_model


@pytest.fixture(scope="module")
def body(small_dataset):
    from motok.sim.mjcf import measure_humanoid

    return measure_humanoid(small_dataset)


def _model(body, **kw):
    from motok.sim.mjcf import humanoid_xml

    return mujoco.MjModel.from_xml_string(humanoid_xml(body, HumanoidConfig(**kw))[0])


def test_the_contact_model_is_in_the_mjcf_and_its_metadata(body):
    m = _model(body, cone="elliptic", impratio=10, noslip_iterations=4, contact_solref=(0.015, 1.5),
               contact_solimp=(0.8, 0.97, 0.002))
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 10 and m.opt.noslip_iterations == 4
    # every geom, the floor's and the feet's included, carries the contact's softness
    np.testing.assert_allclose(m.geom_solref, np.tile([0.015, 1.5], (m.ngeom, 1)))
    np.testing.assert_allclose(m.geom_solimp[:, :3], np.tile([0.8, 0.97, 0.002], (m.ngeom, 1)))
    hum = humanoid_from_model(m)
    assert hum.meta["config"]["cone"] == "elliptic" and hum.meta["config"]["contact_solref"] == [0.015, 1.5]
    # the defaults are MuJoCo's own: the same model as an MJCF that does not name them
    d = _model(body)
    assert d.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL and d.opt.impratio == 1 and d.opt.noslip_iterations == 0
    np.testing.assert_allclose(d.geom_solref[0], mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><geom size='1'/></worldbody></mujoco>").geom_solref[0])
    assert config_difference(hum, humanoid_from_model(d)) == (
        "cone: elliptic -> pyramidal, impratio: 10 -> 1, noslip_iterations: 4 -> 0, "
        "contact_solref: [0.015, 1.5] -> [0.02, 1.0], contact_solimp: [0.8, 0.97, 0.002] -> [0.9, 0.95, 0.001]")
    for bad, match in (({"cone": "round"}, "cone must be"), ({"impratio": 0.5}, "impratio must be"),
                       ({"impratio": float("nan")}, "impratio must be"), ({"noslip_iterations": -1}, "noslip"),
                       ({"contact_solref": (0.0, 1.0)}, "contact_solref"), ({"contact_solref": (0.02,)}, "contact_solref"),
                       ({"contact_solimp": (0.99, 0.9, 0.001)}, "contact_solimp")):
        with pytest.raises(HumanoidError, match=match):
            HumanoidConfig(**bad)


def test_ankle_stiffness_scales_the_ankles_gains_alone(body):
    m, half = _model(body), _model(body, ankle_stiffness_scale=0.5)
    hum = humanoid_from_model(m)
    sk = hum.skeleton
    ankles = {hum.layout.names[a] for a in (sk.feet_left[0], sk.feet_right[0])}
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in range(m.nu)]
    at_ankle = np.array([n.rsplit("_", 1)[0] in ankles for n in names])
    assert at_ankle.sum() == 6  # three hinges per ankle
    np.testing.assert_allclose(half.actuator_gainprm[at_ankle, 0], 0.5 * m.actuator_gainprm[at_ankle, 0])
    np.testing.assert_allclose(half.actuator_biasprm[at_ankle, 1:3], 0.5 * m.actuator_biasprm[at_ankle, 1:3])
    np.testing.assert_array_equal(half.actuator_gainprm[~at_ankle], m.actuator_gainprm[~at_ankle])
    with pytest.raises(HumanoidError, match="ankle_stiffness_scale"):
        HumanoidConfig(ankle_stiffness_scale=0)


def _feet_drift(m, hum, seconds=5.0, settle=0.5):
    """Largest displacement (m) of any foot or toe body between ``settle`` s and ``seconds`` s of the
    rest pose under PD targets 0; and the root's height drop."""
    d = mujoco.MjData(m)
    sk = hum.skeleton
    feet = hum.body_ids[[*sk.feet_left, *sk.feet_right]]
    z0, start = d.qpos[2], None
    for k in range(int(round(seconds / m.opt.timestep))):
        mujoco.mj_step(m, d)
        if start is None and (k + 1) * m.opt.timestep >= settle:
            start = d.xpos[feet].copy()
    return np.linalg.norm(d.xpos[feet] - start, axis=-1).max(), z0 - d.qpos[2]


@pytest.mark.parametrize("contacts", [{}, {"cone": "elliptic", "impratio": 3}, {"noslip_iterations": 10},
                                      {"derivative_time": 0.2}, {"ankle_stiffness_scale": 0.5}])
def test_a_standing_pose_keeps_its_feet_still_for_5_seconds(body, contacts):
    """Once the soles have settled into the soft floor (half a second), the feet of the rest pose
    under PD hold within 3 mm for the next 4.5 s, in the default world and the others measured
    (elliptic cones at impratio 10 diverge within 0.3 s at this timestep, so they are not among them)."""
    m = _model(body, **contacts)
    drift, sink = _feet_drift(m, humanoid_from_model(m))
    assert drift < 3e-3, (contacts, drift)
    assert sink < 0.05 * m.body_pos[1, 2]


def test_foot_metrics_of_a_hand_made_slide_give_the_known_values(hum, lib):
    """A real standing frame slid along the floor at 0.3 m/s forward and 0.4 m/s sideways: every
    touching sole corner and the toes slip at exactly 50 cm/s; held still, 0; the reference beside
    it (held still) stays 0, so the rows cannot be swapped."""
    from motok.control.tasks.imitation import FEET, clip_feet, clip_slip, feet_report
    from motok.sim.soles import reference_corners, soles

    f = lib.starts[0]
    T, dt = 31, 1 / 30
    pos = np.repeat(lib.body_pos[f][None], T, 0)
    quat = np.repeat(lib.body_quat[f][None], T, 0)
    pos[..., 2] -= reference_corners(soles(hum), pos[:1], quat[:1])[..., 2].min()  # the lowest corner on the floor
    slide = pos.copy()
    t = np.arange(T) * dt
    slide[..., 0] += (0.3 * t)[:, None]  # MuJoCo x (forward) and y (left)
    slide[..., 1] += (0.4 * t)[:, None]
    sole = soles(hum)
    out = {"pos": slide[None], "ref": pos[None], "alive": np.ones((1, T), bool), "dt": dt,
           "sole_sim": reference_corners(sole, slide, quat)[None], "sole_ref": reference_corners(sole, pos, quat)[None]}
    sk = hum.skeleton
    joints, soles_ = clip_feet(out, 0, (tuple(sk.feet_left), tuple(sk.feet_right))), clip_slip(out, 0)
    rep = feet_report(joints, soles_)
    assert set(FEET) <= set(rep["simulated"])
    assert rep["simulated"]["sole_slip_cm_s"] == pytest.approx(50.0) and rep["reference"]["sole_slip_cm_s"] == 0
    assert rep["simulated"]["skate_cm_s"] == pytest.approx(50.0) and rep["reference"]["skate_cm_s"] == 0
    assert rep["simulated"]["jitter_m_s3"] == pytest.approx(0.0, abs=1e-6)  # constant velocity: no jerk
    assert rep["simulated"]["sole_penetration_mm"] == pytest.approx(0.0, abs=1e-9)
    # sunk by 4 mm, the lowest corner is 4 mm below the floor in every state
    sunk = slide.copy()
    sunk[..., 2] -= 0.004
    out["sole_sim"] = reference_corners(sole, sunk, quat)[None]
    assert feet_report(joints, clip_slip(out, 0))["simulated"]["sole_penetration_mm"] == pytest.approx(4.0)


def test_the_foot_velocity_term_multiplies_eq10_by_its_factor(hum, lib):
    """``k_feet`` multiplies r_im by exp(-k_feet e_feet), e_feet the mean squared velocity error of
    the ankles and toes (the skeleton's feet), computed here independently from the states."""
    from functools import partial

    from motok.control.mdp.actions import ActionConfig, pd_targets
    from motok.control.mdp.rewards import ImitationConfig, feet_error, imitation_reward
    from motok.control.mdp.task_env import TaskEnv
    from motok.control.tasks.imitation import ImitationTask, ImitationTaskConfig
    from motok.sim.env import HumanoidEnv, SimConfig

    v = np.zeros((1, 5, 3))
    ref = v.copy()
    ref[0, 1, 0], ref[0, 3, 1] = 0.2, 0.4
    assert feet_error(v, ref, [1, 3])[0] == pytest.approx((0.04 + 0.16) / 2)
    err = {"root": np.zeros(1), "q": np.zeros(1), "alpha": np.zeros(1), "ee": np.zeros(1), "feet": np.array([0.5])}
    assert imitation_reward(err, ImitationConfig(k_feet=2.0))["r_im"][0] == pytest.approx(np.exp(-1.0))
    assert "r_feet" not in imitation_reward(err, ImitationConfig())  # 0: the paper's Eq. 10

    rows = {}
    for k in (0.0, 2.0):
        env = HumanoidEnv(hum, SimConfig(num_envs=2))
        task = ImitationTask(ImitationTaskConfig(reward=ImitationConfig(k_feet=k)), env, lib, np.random.default_rng(0))
        mdp = TaskEnv(env, task, partial(pd_targets, ActionConfig(base="reference")))
        mdp.reset(clips=[0, 1], frames=[5, 9])
        out = mdp.step(np.zeros((2, env.action_dim)))
        g = lib.frame_index(task.clip, task.frame)
        sk = hum.skeleton
        rows[k] = (out[2]["r_im"] if isinstance(out[2], dict) else out[2], env.bodies.vel.copy(), lib.body_vel[g])
    r0, vel, ref_vel = rows[0.0]
    feet = [*sk.feet_left, *sk.feet_right]
    e = ((vel[:, feet] - ref_vel[:, feet]) ** 2).sum(-1).mean(-1)
    assert (e > 1e-4).all()  # the feet do move differently from the reference's after a step
    np.testing.assert_allclose(rows[2.0][0], r0 * np.exp(-2.0 * e), rtol=1e-9)


def test_a_resume_on_another_contact_model_is_refused(small_dataset, body, tmp_path):
    from typer.testing import CliRunner

    from motok.cli.main import app
    from motok.sim.mjcf import humanoid_xml

    other = tmp_path / "elliptic.xml"
    other.write_text(humanoid_xml(body, HumanoidConfig(cone="elliptic", impratio=10))[0])
    run = tmp_path / "expert"
    args = ["--quiet", "control", "expert", "train", "-d", str(small_dataset), "--clips", "dataset-2_walk_normal_001",
            "--set", "env.num_envs=4", "--set", "ppo.horizon=4", "--set", "ppo.minibatch_size=16",
            "--set", "iterations=2", "-o", str(run)]
    r = CliRunner().invoke(app, [*args, "--until", "1"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, [*args, "--resume", "--humanoid", str(other)])
    assert r.exit_code == 2 and "cone: pyramidal -> elliptic, impratio: 1 -> 10" in r.output, r.output
    assert json.loads((run / "bundle.json").read_text())["extra"]["iteration"] == 1  # untouched
    r = CliRunner().invoke(app, [*args, "--resume"])  # its own world: goes on
    assert r.exit_code == 0 and json.loads((run / "bundle.json").read_text())["extra"]["iteration"] == 2


def test_the_recipes_humanoid_section_builds_the_world_and_a_resume_keeps_it(small_dataset, tmp_path):
    """``humanoid.ankle_stiffness_scale`` in an expert recipe builds that humanoid for the new run (its
    MJCF in the run, the bundle's config saying so); resuming with another value is refused, naming it."""
    from typer.testing import CliRunner

    from motok.cli.main import app
    from motok.sim.humanoid import load_humanoid

    run = tmp_path / "expert"
    args = ["--quiet", "control", "expert", "train", "-d", str(small_dataset), "--clips", "dataset-2_walk_normal_001",
            "--set", "env.num_envs=4", "--set", "ppo.horizon=4", "--set", "ppo.minibatch_size=16",
            "--set", "iterations=2", "-o", str(run)]
    r = CliRunner().invoke(app, [*args, "--set", "humanoid.ankle_stiffness_scale=0.5", "--until", "1"])
    assert r.exit_code == 0, r.output
    hum = load_humanoid(run / "humanoid.xml")
    assert hum.meta["config"]["ankle_stiffness_scale"] == 0.5
    assert json.loads((run / "bundle.json").read_text())["config"]["humanoid"]["ankle_stiffness_scale"] == 0.5
    r = CliRunner().invoke(app, [*args, "--set", "humanoid.ankle_stiffness_scale=0.7", "--resume"])
    assert r.exit_code == 2 and "humanoid.ankle_stiffness_scale 0.5 -> 0.7" in r.output, r.output
    r = CliRunner().invoke(app, [*args, "--set", "humanoid.ankle_stiffness_scale=0.5", "--resume"])
    assert r.exit_code == 0 and json.loads((run / "bundle.json").read_text())["extra"]["iteration"] == 2


def test_video_contact_markers_colour_slides_and_count_slip_as_the_metric_does(hum, lib):
    """The same real standing frame held for 10 steps, then slid at 0.5 m/s for 10, then lifted
    5 cm: touching corners are drawn (green while held, red while sliding), lifted ones are not,
    and the running slip at the end equals :func:`slip_sums`' value over the same corners."""
    from motok.sim.soles import HOLD, SLIDE, contact_markers, reference_corners, slip_sums, soles

    f, dt = lib.starts[0], 1 / 30
    pos = np.repeat(lib.body_pos[f][None], 25, 0)
    quat = np.repeat(lib.body_quat[f][None], 25, 0)
    sole = soles(hum)
    pos[..., 2] -= reference_corners(sole, pos[:1], quat[:1])[..., 2].min()
    pos[10:, :, 0] += 0.5 * dt * np.arange(1, 16)[:, None]  # slides from step 10 on
    pos[20:, :, 2] += 0.05  # lifted for the last 5 states
    c = reference_corners(sole, pos, quat)
    marks, rgba, running = contact_markers(c, dt)
    down = c[0, :, 2] <= 0.01
    assert down.sum() >= 4 and np.isnan(marks[20:]).all() and np.isfinite(marks[:20][:, down]).all()
    assert np.allclose(rgba[5, down], HOLD) and np.allclose(rgba[15, down], SLIDE)
    assert running[9] == 0 and running[19] == pytest.approx(100 * 0.5 * 10 / 19)  # 10 sliding steps of 19
    assert running[-1] == pytest.approx(slip_sums(c, dt).result()["sole_slip_cm_s"])
