"""The physics world (motok.sim): humanoid, reference library, batched environment, commands."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

import mujoco

from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import HumanoidError, load_humanoid, to_mj
from motok.sim.obs import TreeKinematics, observation
from motok.sim.kinematics import body_states
from motok.sim.reference import ReferenceError, build_library, load_library
from conftest import require_module

runner = CliRunner()


# ----------------------------------------------------------------------------- humanoid

def test_humanoid_structure_mass_ranges_and_gains(hum_path, hum):
    m = mujoco.MjModel.from_xml_path(str(hum_path))  # the file itself loads in plain MuJoCo
    assert 60.0 <= m.body_subtreemass[1] <= 75.0
    kinds = dict(zip(hum.layout.names, hum.layout.kinds))
    assert kinds["Hips"] == "free" and kinds["Head"] == "fixed" and kinds["Toes_L"] == "fixed"
    assert {kinds[j] for j in ("LowerLeg_L", "LowerLeg_R", "LowerArm_L", "LowerArm_R")} == {"hinge"}
    assert {kinds[j] for j in ("UpperLeg_L", "UpperArm_R", "Spine", "Foot_L")} == {"ball"}
    assert m.nu == 11 * 3 + 4 and m.nq == 7 + m.nu
    # Knees flex backwards, elbows forwards (positive hinge angle), per the data's range of motion.
    lo, hi = m.jnt_range[[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ("LowerLeg_L_y", "LowerArm_L_z")]].T
    assert (hi > 1.0).all() and (lo <= 0.0).all()
    # Gains scale with the mass moved: a stance ankle moves the whole body, an elbow a forearm.
    kp = dict(zip(hum.layout.hinge_names, m.actuator_gainprm[:, 0]))
    assert kp["Foot_L_x"] > 10 * kp["LowerArm_L_z"] / 2 and kp["Spine_x"] > kp["Neck_x"]
    assert (m.actuator_biasprm[:, 2] < 0).all()  # velocity feedback (kv) on every actuator
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT == 0  # parent-child contacts off
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST and hum.substeps * m.opt.timestep == pytest.approx(1 / 30)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert d.ncon == 0  # the rest pose stands on the floor without interpenetration


def test_standing_pose_is_held_for_5_seconds(hum):
    m = hum.model
    d = mujoco.MjData(m)  # qpos0: the rest pose standing on the floor; PD targets (ctrl) = 0 hold it
    z0 = d.qpos[2]
    head = hum.body_ids[hum.skeleton.head]
    for _ in range(int(round(5.0 / m.opt.timestep))):
        mujoco.mj_step(m, d)
    assert d.qpos[2] > 0.95 * z0 and d.xpos[head, 2] > 1.2
    assert np.linalg.norm(d.qpos[:2]) < 0.1 and np.abs(d.qvel).max() < 0.5


def test_bad_mjcf_gets_clear_errors(tmp_path, hum_path):
    with pytest.raises(HumanoidError, match="no such file"):
        load_humanoid(tmp_path / "missing.xml")
    broken = tmp_path / "broken.xml"
    broken.write_text(hum_path.read_text()[:2000])
    with pytest.raises(HumanoidError, match="MuJoCo cannot load this MJCF"):
        load_humanoid(broken)
    plain = tmp_path / "plain.xml"
    plain.write_text("<mujoco><worldbody><body><freejoint/><geom size='.1'/></body></worldbody></mujoco>")
    with pytest.raises(HumanoidError, match="not a motok humanoid"):
        load_humanoid(plain)
    renamed = tmp_path / "renamed.xml"
    renamed.write_text(hum_path.read_text().replace('body name="Head"', 'body name="Skull"'))
    with pytest.raises(HumanoidError, match="no body of that name"):
        load_humanoid(renamed)


# ----------------------------------------------------------------------------- reference library

def test_reference_fk_reproduces_dataset_joints(hum, lib, small_dataset):
    from motok.data.dataset import MotionFile

    # docs/sim.md and docs/results.md claim 3.6 mm at 20 fps (mean 0.4) and 8.6 mm at 30 Hz (mean
    # 0.6) on these 24 clips, which `python benchmarks/fk_accuracy.py` prints: tested at what is
    # claimed, to the 0.1 mm it is stated in.
    err = np.linalg.norm(lib.body_pos - lib.joints, axis=-1)  # 30 Hz, every clip and body
    assert len(lib) == 24 and round(err.max() * 1e3, 1) <= 8.6 and round(err.mean() * 1e3, 1) <= 0.6, err.max()
    native = build_library(hum, small_dataset, control_hz=20.0)  # the dataset's own rate, all 24 clips
    err20 = np.linalg.norm(native.body_pos - native.joints, axis=-1)
    assert round(err20.max() * 1e3, 1) <= 3.6 and round(err20.mean() * 1e3, 1) <= 0.4, err20.max()
    with MotionFile(small_dataset) as mf:  # and against the file itself, not the library's copy
        for i in (0, 5):
            joints = to_mj(mf.clip(native.names[i]).joints)
            assert np.linalg.norm(native.clip(i)["body_pos"] - joints, axis=-1).max() < 3.65e-3
    # qvel and the body velocities agree with finite differences of the kinematics
    c = lib.clip(3)
    fd = (c["body_pos"][2:] - c["body_pos"][:-2]) * lib.fps / 2
    assert np.abs(fd - c["body_vel"][1:-1]).mean() < 0.01
    assert len(lib) == 24 and lib.fps == 30.0


def test_reference_cache_is_reused(hum, small_dataset, tmp_path):
    a = load_library(hum, small_dataset, clips=[1, 2], cache_dir=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    stamp = files[0].stat().st_mtime_ns
    b = load_library(hum, small_dataset, clips=[1, 2], cache_dir=tmp_path)
    assert files[0].stat().st_mtime_ns == stamp and np.array_equal(a.qpos, b.qpos) and a.names == b.names
    c = load_library(hum, small_dataset, control_hz=20.0, clips=[1, 2], cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 2 and c.fps == 20.0 and len(c.qpos) < len(a.qpos)


def test_unknown_clips_get_clear_errors(hum, lib, small_dataset, tmp_path):
    with pytest.raises(ReferenceError, match="no clip named 'walk_nope'"):
        load_library(hum, small_dataset, clips=["walk_nope"], cache_dir=tmp_path)
    with pytest.raises(ReferenceError, match="no clip named"):
        lib.index("dataset-2_walk_normal_999")


# ----------------------------------------------------------------------------- kinematics, observations

def test_numpy_kinematics_match_mujoco(hum, lib):
    rng = np.random.default_rng(0)
    q, v = lib.qpos[::97].copy(), lib.qvel[::97].copy()
    q[:, 7:] += rng.normal(0, 0.4, q[:, 7:].shape)
    v += rng.normal(0, 2.0, v.shape)
    mine, ref = TreeKinematics(hum)(q, v), body_states(hum, q, v)
    assert np.abs(mine.pos - ref["body_pos"]).max() < 1e-9
    assert np.abs(mine.vel - ref["body_vel"]).max() < 1e-9
    assert np.abs(mine.angvel - ref["body_angvel"]).max() < 1e-9
    assert np.abs(np.abs((mine.quat * ref["body_quat"]).sum(-1)) - 1).max() < 1e-9


def test_body_states_equal_mujoco_frame_by_frame(hum, lib):
    """The library's kinematics, computed on all frames at once, against MuJoCo asked one frame and
    one body at a time: ``mj_objectVelocity`` for the velocity at each body's origin, and every geom's
    lowest point (sphere: centre - r; capsule: the lower end of its axis - r; box: its lowest corner)."""
    import itertools

    import mujoco

    m = hum.model
    d = mujoco.MjData(m)
    q, v = lib.qpos[::211].copy(), lib.qvel[::211].copy()
    got = body_states(hum, q, v)
    corners = np.array(list(itertools.product((-1, 1), repeat=3)), dtype=np.float64)
    res = np.zeros(6)
    for t in range(len(q)):
        d.qpos[:], d.qvel[:] = q[t], v[t]
        mujoco.mj_forward(m, d)
        for j, b in enumerate(hum.body_ids):
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, int(b), res, 0)  # body origin, world axes
            np.testing.assert_allclose(got["body_angvel"][t, j], res[:3], atol=1e-10)
            np.testing.assert_allclose(got["body_vel"][t, j], res[3:], atol=1e-10)
        np.testing.assert_allclose(got["body_pos"][t], d.xpos[hum.body_ids], atol=0)
        low = np.inf
        for g in np.flatnonzero(m.geom_bodyid != 0):
            c, R, size = d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3), m.geom_size[g]
            if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
                z = c[2] - size[0]
            elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
                z = min(c[2] + R[2, 2] * size[1], c[2] - R[2, 2] * size[1]) - size[0]
            elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
                z = (c[2] + (corners * size) @ R[2]).min()
            else:
                z = c[2]
            low = min(low, z)
        assert got["lowest"][t] == pytest.approx(low, abs=1e-12)
    empty = body_states(hum, q[:0], v[:0])
    assert empty["body_pos"].shape == (0, len(hum.body_ids), 3) and empty["lowest"].shape == (0,)


# ----------------------------------------------------------------------------- environment

def test_batch_stepper_is_plain_mujoco(hum, lib):
    require_module("mujoco.batch", "this MuJoCo has no mujoco.batch")
    from motok.sim.steppers import BatchStepper

    m, g = hum.model, np.array([10, 500, 2000])
    st = BatchStepper(hum, 3, hum.substeps, nthread=2)
    st.set_state(np.arange(3), lib.qpos[g], lib.qvel[g])
    datas = [mujoco.MjData(m) for _ in g]
    for d, i in zip(datas, g):
        d.qpos[:], d.qvel[:] = lib.qpos[i], lib.qvel[i]
    for t in range(6):
        ctrl = lib.qpos[g + t + 1][:, hum.hinge_qpos_adr]
        assert not st.step(ctrl).any()
        for d, c in zip(datas, ctrl):
            d.ctrl[:] = c
            for _ in range(hum.substeps):
                mujoco.mj_step(m, d)
    assert np.array_equal(st.qpos, np.array([d.qpos for d in datas]))  # bit-identical to mj_step
    mine = st.bodies()
    for i, d in enumerate(datas):
        mujoco.mj_forward(m, d)
        assert np.allclose(mine.pos[i], d.xpos[hum.body_ids], atol=1e-12)


@pytest.mark.parametrize("stepper", ["batch", "rollout"])
def test_physics_env_steps_pd_targets_and_contains_bad_ones(hum, lib, stepper):
    """The environment is physics only: states in, PD targets held for the substeps, Eq. 7 out;
    a batch equals its environments run one by one; non-finite targets hold that env's pose."""
    if stepper == "batch":
        require_module("mujoco.batch", "this MuJoCo has no mujoco.batch")
    g = np.array([10, 500, 2000])
    env = HumanoidEnv(hum, SimConfig(num_envs=3, stepper=stepper, nan_actions="terminate"))
    singles = [HumanoidEnv(hum, SimConfig(num_envs=1, stepper=stepper)) for _ in g]
    env.set_state(np.arange(3), lib.qpos[g], lib.qvel[g])
    for e, i in zip(singles, g):
        e.set_state([0], lib.qpos[i:i + 1], lib.qvel[i:i + 1])
    assert env.obs_dim == env.observation().shape[1] == 1 + 6 + 3 + 3 + 2 * env.action_dim + 3 * len(env.end_effectors)
    for t in range(4):
        targets = lib.qpos[g + t + 1][:, env.hinge_adr]
        diverged, invalid = env.step(targets)
        assert not diverged.any() and not invalid.any()
        for k, e in enumerate(singles):
            e.step(targets[k:k + 1])
            assert np.array_equal(env.observation()[k], e.observation()[0])
    obs = env.observation()
    assert np.allclose(obs, observation(env.qpos, env.qvel, TreeKinematics(hum)(env.qpos, env.qvel),
                                        env.end_effectors), atol=1e-9)
    bad = lib.qpos[g + 5][:, env.hinge_adr].copy()
    bad[2, 0] = np.nan
    held = env.qpos[2, env.hinge_adr].copy()
    diverged, invalid = env.step(bad)
    assert invalid.tolist() == [False, False, True] and np.isfinite(env.qpos).all()
    assert np.abs(env.qpos[2, env.hinge_adr] - held).max() < 0.2  # held its pose, not thrown anywhere
    with pytest.raises(ValueError, match="shape"):
        env.step(bad[:2])
    with pytest.raises(ValueError, match="nan_actions"):
        HumanoidEnv(hum, SimConfig(num_envs=1, nan_actions="ignore"))


def test_target_filter_low_passes_the_pd_targets_and_restarts_at_a_reset(hum, lib):
    """``target_filter`` b steps the filtered targets y_t = b a_t + (1 - b) y_(t-1), from the joints'
    angles after every reset: bit for bit an unfiltered environment given y."""
    g, b = np.array([10, 500]), 0.3
    filt, plain, raw = (HumanoidEnv(hum, SimConfig(num_envs=2, target_filter=f)) for f in (b, 1.0, 1.0))
    for e in (filt, plain, raw):
        e.set_state(np.arange(2), lib.qpos[g], lib.qvel[g])
    y = lib.qpos[g][:, filt.hinge_adr]
    for t in range(3):
        if t == 2:  # environment 1 starts again elsewhere: its filter with it
            for e in (filt, plain, raw):
                e.set_state([1], lib.qpos[[900]], lib.qvel[[900]])
            y[1] = lib.qpos[900, filt.hinge_adr]
        a = lib.qpos[g + 5 * t + 5][:, filt.hinge_adr]
        y = b * a + (1 - b) * y
        filt.step(a)
        plain.step(y)
        raw.step(a)
        assert np.array_equal(filt.qpos, plain.qpos) and not np.allclose(filt.qpos, raw.qpos)
    for bad in (0.0, 1.5):
        with pytest.raises(UserError, match="target_filter"):
            HumanoidEnv(hum, SimConfig(num_envs=1, target_filter=bad))


# ----------------------------------------------------------------------------- commands

def test_sim_commands(small_dataset, hum_path, tmp_path, monkeypatch):
    from motok.cli.main import app

    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    xml = tmp_path / "h.xml"
    r = runner.invoke(app, ["--quiet", "sim", "build-humanoid", "--data", str(small_dataset), "-o", str(xml),
                            "--total-mass", "70", "--json"])
    assert r.exit_code == 0, r.output
    assert mujoco.MjModel.from_xml_path(str(xml)).body_subtreemass[1] == pytest.approx(70.0, rel=1e-4)
    gif = tmp_path / "replay.gif"
    r = runner.invoke(app, ["--quiet", "sim", "replay", "--data", str(small_dataset), "--clip", "2", "-o", str(gif),
                            "--max-frames", "6", "--stick"])
    assert r.exit_code == 0 and gif.stat().st_size > 0, r.output
    mp4 = tmp_path / "pd.mp4"
    r = runner.invoke(app, ["--quiet", "sim", "pd-track", "--data", str(small_dataset), "--humanoid", str(hum_path),
                            "--clip", "dataset-2_walk_normal_004", "--seconds", "0.3", "--render", str(mp4), "--json"])
    assert r.exit_code == 0 and mp4.stat().st_size > 0, r.output
    assert '"survival_mean_s"' in r.output
    r = runner.invoke(app, ["sim", "replay", "--data", str(small_dataset), "--clip", "nope", "-o", str(gif)])
    assert r.exit_code == 2 and "no clip named 'nope'" in r.output
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody>")
    r = runner.invoke(app, ["sim", "pd-track", "--data", str(small_dataset), "--humanoid", str(bad)])
    assert r.exit_code == 2 and "MuJoCo cannot load this MJCF" in r.output


# ----------------------------------------------------------------------------- lookups

def test_frame_index_clamps_to_each_clips_last_frame(lib):
    last = len(lib) - 1
    clips, frames = np.array([0, 0, 3, 3, last]), np.array([0, 5, lib.lengths[3] - 1, lib.lengths[3] + 7, 10**6])
    g = lib.frame_index(clips, frames)
    np.testing.assert_array_equal(g, [lib.starts[0], lib.starts[0] + 5, lib.starts[4] - 1, lib.starts[4] - 1,
                                      lib.starts[-1] - 1])
    np.testing.assert_array_equal(lib.qpos[g[3]], lib.clip(3)["qpos"][-1])  # past the end: the clip's last state
    np.testing.assert_array_equal(lib.frame_index(np.array([1, 2]), 1), lib.starts[[1, 2]] + 1)  # broadcasts
    assert lib.frame_index(2, 0) == lib.starts[2]


def test_kabsch_recovers_rotations_and_never_reflects():
    from motok.rotations import kabsch, qnormalize, quat_to_matrix

    rng = np.random.default_rng(0)
    rot = quat_to_matrix(qnormalize(rng.normal(size=(5, 4))))
    src = rng.normal(size=(4, 3))
    np.testing.assert_allclose(kabsch(src, np.einsum("fij,kj->fki", rot, src)), rot, atol=1e-12)
    mirrored = kabsch(src, (src * [1, 1, -1])[None])  # the best orthogonal fit is a reflection
    assert np.linalg.det(mirrored) == pytest.approx([1.0])


# ----------------------------------------------------------------------------- contact filter, solver options

@pytest.fixture(scope="module")
def body(small_dataset):
    from motok.sim.mjcf import measure_humanoid

    return measure_humanoid(small_dataset)


def _may_collide(m, a: str, b: str) -> bool:
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in (a, b)]
    ga, gb = (np.flatnonzero(m.geom_bodyid == i) for i in ids)
    return any((m.geom_contype[i] & m.geom_conaffinity[j]) or (m.geom_contype[j] & m.geom_conaffinity[i])
               for i in ga for j in gb)


def test_default_contacts_keep_the_feet_on_the_floor_for_5_seconds(hum):
    """The default filter (self_collision "data") and solver options; the rest pose under PD targets 0
    stands on its soles: after 5 s every contact is a foot or toe on the floor, both feet touch."""
    m = hum.model
    assert hum.meta["config"]["self_collision"] == "data"
    assert (m.opt.iterations, m.opt.ls_iterations) == (10, 5) and m.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_ISLAND
    d = mujoco.MjData(m)
    z0 = d.qpos[2]
    for _ in range(int(round(5.0 / m.opt.timestep))):
        mujoco.mj_step(m, d)
    assert d.qpos[2] > 0.95 * z0 and np.abs(d.qvel).max() < 0.5
    sk = hum.skeleton
    sides = [set(hum.body_ids[list(f)].tolist()) for f in (sk.feet_left, sk.feet_right)]
    touching = [sorted(m.geom_bodyid[c.geom].tolist()) for c in d.contact[:d.ncon]]
    assert touching and all(a == 0 and b in sides[0] | sides[1] for a, b in touching)
    assert all(any(b in side for _, b in touching) for side in sides)


def test_self_collision_modes_set_the_contact_bits_and_excludes(body):
    from motok.sim.humanoid import SELF_COLLISION, HumanoidConfig
    from motok.sim.mjcf import humanoid_xml

    arms_trunk = [("Hand_L", "Hips"), ("UpperArm_R", "Spine"), ("LowerArm_L", "Chest")]
    arms_thighs_arms = [("LowerArm_R", "UpperLeg_R"), ("Hand_L", "UpperLeg_R"), ("Hand_L", "Hand_R")]
    legs = [("UpperLeg_L", "UpperLeg_R"), ("Foot_L", "Foot_R"), ("Toes_L", "LowerLeg_R")]
    never = [("Head", "Hand_L"), ("Neck", "UpperArm_R"), ("Shoulder_L", "Hand_R"), ("Hand_L", "LowerLeg_L"),
             ("Hand_R", "Foot_R"), ("Spine", "UpperLeg_L"), ("Hand_L", "UpperArm_L"), ("UpperLeg_L", "Foot_L")]
    allowed = {"all": arms_trunk + arms_thighs_arms + legs + never, "data": arms_trunk + arms_thighs_arms + legs,
               "legs": legs, "none": []}
    for mode in SELF_COLLISION:
        xml, excludes = humanoid_xml(body, HumanoidConfig(self_collision=mode))
        m = mujoco.MjModel.from_xml_string(xml)
        for a, b in arms_trunk + arms_thighs_arms + legs + never:
            assert _may_collide(m, a, b) == ((a, b) in allowed[mode]), (mode, a, b)
        floor = np.flatnonzero(m.geom_bodyid == 0)
        assert all(_may_collide(m, "world", n) for n in body.layout.names if m.body_geomnum[
            mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)]) and len(floor) == 1
        # Pairs the filter allows that overlap at rest are excluded, so the rest pose starts contact-free.
        assert len(m.exclude_signature) == len(excludes)
        assert excludes == {"all": excludes, "data": [("Chest", "UpperArm_L"), ("Chest", "UpperArm_R")],
                            "legs": [], "none": []}[mode]
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        assert d.ncon == 0, mode
    assert len(humanoid_xml(body, HumanoidConfig(self_collision="all"))[1]) == 7


def test_solver_options_and_legacy_values(body, small_dataset, tmp_path):
    from motok.cli.main import app
    from motok.sim.humanoid import HumanoidConfig, HumanoidError
    from motok.sim.mjcf import humanoid_xml

    cfg = HumanoidConfig(solver_iterations=20, ls_iterations=10, jacobian="auto", islands=True)
    m = mujoco.MjModel.from_xml_string(humanoid_xml(body, cfg)[0])
    assert (m.opt.iterations, m.opt.ls_iterations, m.opt.jacobian) == (20, 10, mujoco.mjtJacobian.mjJAC_AUTO)
    assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_ISLAND
    assert HumanoidConfig(self_collision=True).self_collision == "all"  # the option used to be a boolean
    assert HumanoidConfig(self_collision="false").self_collision == "none"
    with pytest.raises(HumanoidError, match="self_collision must be one of"):
        HumanoidConfig(self_collision="arms")
    with pytest.raises(ValueError, match="total_mass"):
        humanoid_xml(body, HumanoidConfig(total_mass=80.0))  # the body was measured for 65 kg
    xml = tmp_path / "legs.xml"
    r = runner.invoke(app, ["--quiet", "sim", "build-humanoid", "--data", str(small_dataset), "-o", str(xml),
                            "--set", "self_collision=legs", "--set", "solver_iterations=8", "--json"])
    assert r.exit_code == 0, r.output
    assert '"self_collision": "legs"' in r.output and load_humanoid(xml).model.opt.iterations == 8
