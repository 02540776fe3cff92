"""The physics world (motok.sim): humanoid, reference library, batched environment, commands."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.sim.humanoid import HumanoidError, build_humanoid, load_humanoid, to_mj  # before mujoco: sets MUJOCO_GL
from motok.sim.env import EnvConfig, HumanoidEnv, pd_track  # noqa: E402
from motok.sim.obs import Bodies, RewardConfig, TreeKinematics, goal, observation, reward_terms  # noqa: E402
from motok.sim.reference import ReferenceError, body_states, build_library, load_library  # noqa: E402

import mujoco  # noqa: E402

runner = CliRunner()


@pytest.fixture(scope="module")
def hum_path(small_dataset, tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "humanoid.xml"
    build_humanoid(small_dataset, path)
    return path


@pytest.fixture(scope="module")
def hum(hum_path):
    return load_humanoid(hum_path)


@pytest.fixture(scope="module")
def lib(hum, small_dataset, tmp_path_factory):
    return load_library(hum, small_dataset, cache_dir=tmp_path_factory.mktemp("refcache"))


def _env(hum, lib, **kw):
    return HumanoidEnv(hum, lib, EnvConfig(**kw))


def _pd_actions(env):
    """Residual actions that send the PD targets to the next reference frame."""
    L = env.lib
    g = np.minimum(L.starts[env.clip] + env.frame + 1, L.starts[env.clip + 1] - 1)
    return L.qpos[g][:, env.hinge_adr] - env.qpos[:, env.hinge_adr]


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

    err = np.linalg.norm(lib.body_pos - lib.joints, axis=-1)  # 30 Hz, every clip and body
    assert err.max() < 0.02, err.max()
    native = build_library(hum, small_dataset, control_hz=20.0, clips=[0, 5])  # the dataset's own rate
    with MotionFile(small_dataset) as mf:
        for i, name in enumerate(native.names):
            joints = to_mj(mf.clip(name).joints)
            assert np.linalg.norm(native.clip(i)["body_pos"] - joints, axis=-1).max() < 0.02
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
    env = _env(hum, lib, num_envs=2)
    with pytest.raises(ReferenceError, match="no clip named"):
        env.reset(clips=["dataset-2_walk_normal_999", 0])
    with pytest.raises(ValueError, match="no step with 1 reference frames ahead"):
        env.reset(clips=[0, 0], frames=[0, 10_000])


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


def _yaw_shift(b: Bodies, yaw: float, shift: np.ndarray) -> Bodies:
    c, s = np.cos(yaw), np.sin(yaw)
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return Bodies(b.pos @ r.T + shift, b.vel @ r.T, b.angvel @ r.T, rot=r @ b.rot)


def test_observations_goals_rewards_invariant_to_heading_and_position(hum, lib):
    fk = TreeKinematics(hum)
    rng = np.random.default_rng(1)
    g = rng.integers(0, len(lib.qpos) - 3, 6)
    q, v = lib.qpos[g].copy(), lib.qvel[g].copy()
    q[:, 7:] += rng.normal(0, 0.2, q[:, 7:].shape)  # a sim state off its reference
    sim = fk(q, v)
    ref = Bodies(lib.body_pos[g + 1][:, None], lib.body_vel[g + 1][:, None], lib.body_angvel[g + 1][:, None],
                 quat=lib.body_quat[g + 1][:, None])
    ee = list(hum.skeleton.end_effectors)
    base = observation(q, v, sim, ee), goal(sim, ref), reward_terms(sim, ref.take((slice(None), 0)), RewardConfig())
    yaw, shift = 2.1, np.array([3.0, -7.5, 0.0])
    q2, v2 = q.copy(), v.copy()
    c, s = np.cos(yaw / 2), np.sin(yaw / 2)
    from motok.rotations import qmul
    q2[:, 3:7] = qmul(np.array([c, 0, 0, s]), q[:, 3:7])
    q2[:, :3] = _yaw_shift(Bodies(q[:, None, :3], q[:, None, :3], q[:, None, :3], rot=np.eye(3)[None, None]),
                           yaw, shift).pos[:, 0]
    v2[:, :3] = v[:, :3] @ np.array([[c * c - s * s, 2 * c * s, 0], [-2 * c * s, c * c - s * s, 0], [0, 0, 1]])
    sim2 = fk(q2, v2)
    assert np.allclose(sim2.pos, _yaw_shift(sim, yaw, shift).pos)  # the transform is what we think it is
    ref2 = _yaw_shift(ref, yaw, shift)
    moved = observation(q2, v2, sim2, ee), goal(sim2, ref2), reward_terms(sim2, ref2.take((slice(None), 0)), RewardConfig())
    assert np.allclose(base[0], moved[0], atol=1e-9) and np.allclose(base[1], moved[1], atol=1e-9)
    for k in base[2]:
        assert np.allclose(base[2][k], moved[2][k])
    # at the reference itself every difference vanishes and every reward term is 1
    on_ref = ref.take((slice(None), 0))
    gz = goal(on_ref, ref).reshape(len(g), -1, 15)
    assert np.abs(gz[..., :3]).max() < 1e-12 and np.abs(gz[..., 9:]).max() < 1e-12
    assert np.allclose(gz[..., 3:9], [1, 0, 0, 0, 1, 0])
    assert np.allclose(reward_terms(on_ref, on_ref, RewardConfig())["total"], 1.0)


# ----------------------------------------------------------------------------- environment

def test_same_seed_same_trajectory(hum, lib):
    def run(seed):
        env = _env(hum, lib, num_envs=3, seed=seed)
        obs, _ = env.reset()
        rng = np.random.default_rng(7)
        out = [obs]
        for _ in range(12):
            obs, gl, r, term, trunc, info = env.step(rng.normal(0, 0.1, (3, env.action_dim)))
            out.append(np.concatenate([obs, gl, r["total"][:, None]], 1))
            done = np.flatnonzero(term | trunc)
            if len(done):
                env.reset(done)
        return np.concatenate([o.ravel() for o in out]), env.clip.copy()

    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0][:200], c[0][:200])


@pytest.mark.parametrize("stepper", ["batch", "rollout"])
def test_batch_equals_single_envs(hum, lib, stepper):
    pytest.importorskip("mujoco.batch") if stepper == "batch" else None
    clips, frames = [0, 3, 7, 11], [0, 20, 41, 5]
    batch = _env(hum, lib, num_envs=4, stepper=stepper)
    batch.reset(clips=clips, frames=frames)
    singles = [_env(hum, lib, num_envs=1, stepper=stepper) for _ in clips]
    for e, c, f in zip(singles, clips, frames):
        e.reset(clips=[c], frames=[f])
    for _ in range(8):
        a = _pd_actions(batch)
        ob, gb, rb, tb, _, _ = batch.step(a)
        for i, e in enumerate(singles):
            os_, gs, rs, ts, _, _ = e.step(a[i:i + 1])
            assert np.array_equal(ob[i], os_[0]) and np.array_equal(gb[i], gs[0])
            assert rb["total"][i] == rs["total"][0] and tb[i] == ts[0]


def test_reference_action_base_offsets_from_the_next_reference_frame(hum, lib):
    """The reference base is the next frame's angles plus (kv / kp) times its velocities, so the
    position servo tracks both; zero actions on it are those offsets on the current base (to
    rounding: ``q + (b - q)`` is not bit-identical to ``b``)."""
    clips, frames = [0, 5, 9], [3, 30, 60]
    ref = _env(hum, lib, num_envs=3, action_base="reference")
    cur = _env(hum, lib, num_envs=3)
    for e in (ref, cur):
        e.reset(clips=clips, frames=frames)
    m, L = hum.model, lib
    assert np.allclose(ref.velocity_lead, m.actuator_biasprm[:, 2] / m.actuator_biasprm[:, 1])
    for _ in range(6):
        g = L.starts[ref.clip] + ref.frame + 1
        target = L.qpos[g][:, 7:] + ref.velocity_lead * L.qvel[g][:, 6:]  # hinges follow the free joint
        assert np.allclose(ref.action_base(), target) and np.allclose(cur.action_base(), cur.qpos[:, 7:])
        a = ref.action_base() - cur.action_base()
        o1, g1, r1, *_ = ref.step(np.zeros((3, ref.action_dim)))
        o2, g2, r2, *_ = cur.step(a)
        assert np.allclose(o1, o2, atol=1e-7) and np.allclose(g1, g2, atol=1e-7)
        assert np.allclose(r1["total"], r2["total"], atol=1e-7)
    with pytest.raises(ValueError, match="action_base"):
        _env(hum, lib, num_envs=1, action_base="target")


def test_batch_stepper_is_plain_mujoco(hum, lib):
    pytest.importorskip("mujoco.batch")
    from motok.sim.env import BatchStepper

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


def test_nan_actions_are_refused_or_contained(hum, lib):
    env = _env(hum, lib, num_envs=3)
    env.reset(clips=[0, 1, 2], frames=[10, 10, 10])
    before = env.qpos.copy()
    a = _pd_actions(env)
    bad = a.copy()
    bad[1, 4] = np.nan
    with pytest.raises(ValueError, match=r"non-finite actions for environments \[1\]"):
        env.step(bad)
    assert np.array_equal(env.qpos, before)  # nothing was stepped
    with pytest.raises(ValueError, match="shape"):
        env.step(a[:2])

    clean = _env(hum, lib, num_envs=3)
    contained = _env(hum, lib, num_envs=3, nan_actions="terminate")
    for e in (clean, contained):
        e.reset(clips=[0, 1, 2], frames=[10, 10, 10])
    o1, g1, r1, t1, _, _ = clean.step(a)
    o2, g2, r2, t2, _, info = contained.step(bad)
    assert t2[1] and info["invalid_action"][1] and r2["total"][1] == 0.0
    keep = [0, 2]
    assert np.array_equal(o1[keep], o2[keep]) and np.array_equal(g1[keep], g2[keep]) and not t2[keep].any()
    assert np.isfinite(o2).all() and np.isfinite(g2).all()


def test_early_termination_and_truncation_are_distinct(hum, lib):
    env = _env(hum, lib, num_envs=2, max_episode_seconds=0.2)
    env.reset(clips=[0, 0], frames=[5, 5])
    q, v = env.qpos.copy(), env.qvel.copy()
    q[1, 0] += 1.0  # env 1 teleported 1 m away from its reference
    env.stepper.set_state(np.array([1]), q[1:], v[1:])
    _, _, _, term, trunc, info = env.step(_pd_actions(env))
    assert term.tolist() == [False, True] and not trunc.any() and info["max_body_error"][1] > 0.5
    env.reset([0, 1], clips=[0, 0], frames=[5, 5])
    for t in range(6):
        _, _, _, term, trunc, info = env.step(_pd_actions(env))
    assert trunc.all() and not term.any() and (info["episode_steps"] == 6).all()
    # the end of the clip truncates too: one step before the goal runs out of reference frames
    n = lib.lengths[0]
    env.reset([0, 1], clips=[0, 0], frames=[n - 3, n - 4])
    _, _, _, term, trunc, _ = env.step(_pd_actions(env))
    assert trunc.tolist() == [True, False] and not term.any()


def test_termination_on_any_body_or_on_the_mean(hum, lib):
    """A swung arm puts the hand > 0.5 m off while the body as a whole stays: "any" ends the
    episode, "mean" (PHC's failure test) does not; a 1 m teleport ends both."""
    envs = {k: _env(hum, lib, num_envs=2, termination=k) for k in ("any", "mean")}
    k = list(hum.layout.hinge_names).index("UpperArm_L_z")
    for env in envs.values():
        env.reset(clips=[0, 0], frames=[5, 5])
        q, v = env.qpos.copy(), env.qvel.copy()
        q[0, env.hinge_adr[k]] += 2.5
        q[1, 0] += 1.0
        env.stepper.set_state(np.array([0, 1]), q, v)
    out = {key: env.step(_pd_actions(env)) for key, env in envs.items()}
    info = out["mean"][5]
    assert info["max_body_error"][0] > 0.5 > info["mean_body_error"][0] and info["mean_body_error"][1] > 0.5
    assert out["any"][3].tolist() == [True, True] and out["mean"][3].tolist() == [False, True]
    with pytest.raises(ValueError, match="termination"):
        _env(hum, lib, num_envs=1, termination="median")


def test_pd_tracking_baseline_falls_but_follows_at_first(hum, lib):
    res = pd_track(hum, lib, [0, 1, 2, 3], seconds=3.0)
    assert (res["survival_s"] > 0.2).all() and (res["survival_s"] < 3.0).all()
    assert (res["mean_reward"] > 0.2).all() and res["qpos"].shape[1] == 91


# ----------------------------------------------------------------------------- commands

def test_sim_commands(small_dataset, hum_path, tmp_path, monkeypatch):
    from motok.cli.main import app

    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    xml = tmp_path / "h.xml"
    r = runner.invoke(app, ["--quiet", "sim", "build-humanoid", "--data", str(small_dataset), "-o", str(xml),
                            "--mass", "70", "--json"])
    assert r.exit_code == 0, r.output
    assert mujoco.MjModel.from_xml_path(str(xml)).body_subtreemass[1] == pytest.approx(70.0, rel=1e-4)
    gif = tmp_path / "replay.gif"
    r = runner.invoke(app, ["--quiet", "sim", "replay", "--data", str(small_dataset), "--clip", "2", "-o", str(gif),
                            "--max-frames", "6", "--stick"])
    assert r.exit_code == 0 and gif.stat().st_size > 0, r.output
    mp4 = tmp_path / "pd.mp4"
    r = runner.invoke(app, ["--quiet", "sim", "pd-track", "--data", str(small_dataset), "--humanoid", str(hum_path),
                            "--clip", "dataset-2_walk_normal_004", "--seconds", "0.3", "-o", str(mp4), "--json"])
    assert r.exit_code == 0 and mp4.stat().st_size > 0, r.output
    assert '"survival_mean_s"' in r.output
    r = runner.invoke(app, ["sim", "replay", "--data", str(small_dataset), "--clip", "nope", "-o", str(gif)])
    assert r.exit_code == 2 and "no clip named 'nope'" in r.output
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody>")
    r = runner.invoke(app, ["sim", "pd-track", "--data", str(small_dataset), "--humanoid", str(bad)])
    assert r.exit_code == 2 and "MuJoCo cannot load this MJCF" in r.output
