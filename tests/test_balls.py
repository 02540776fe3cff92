"""Thrown balls (motok.sim.balls) and the perturbation test (motok.control.highlevel.perturb), hybrid-latent
paper section 6.3.3: the ball model, the humanoid's state as a prefix of it, launches, hits
checked against MuJoCo's own contact list, the pool, and perturb()'s counts."""

from __future__ import annotations

import numpy as np
import pytest

import mujoco

from motok.control.highlevel.perturb import PerturbConfig, Windows, perturb
from motok.control.mdp.task_env import Task, TaskEnv
from motok.errors import UserError
from motok.sim.balls import (ball_states, build_ball_model, detect_hits, find_balls, humanoid_capsules, launch_balls,
                             park_balls, segment_distance, set_balls)
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import HumanoidError, load_humanoid
from motok.sim.obs import observation
from motok.sim.steppers import make_stepper

pytestmark = pytest.mark.usefixtures("one_thread")
K = 3


@pytest.fixture(scope="module")
def ball_path(hum, tmp_path_factory):
    return build_ball_model(hum, tmp_path_factory.mktemp("balls") / "balls.xml", K)


@pytest.fixture(scope="module")
def bhum(ball_path):
    return load_humanoid(ball_path)


def standing(env, ids=None):
    ids = np.arange(env.num_envs) if ids is None else ids
    env.set_state(ids, np.tile(env.hum.model.qpos0[:env.nq], (len(ids), 1)), np.zeros((len(ids), env.nv)))


class Stand(Task):
    """A test task: stand (PD targets are the actions) from the rest pose; the head below 0.5 m
    terminates (when ``fall_ends``), ``seconds`` truncate."""

    goal_dim, reward_key = 0, "r_task"

    def __init__(self, env, seconds, fall_ends=True):
        self.env, self.limit, self.fall_ends = env, int(round(seconds * env.control_hz)), fall_ends
        self.steps = np.zeros(env.num_envs, dtype=np.int64)

    def reset(self, ids):
        standing(self.env, ids)
        self.steps[ids] = 0

    def goal(self):
        return np.zeros((self.env.num_envs, 0))

    def step_limit(self):
        return self.limit

    def update(self, diverged, invalid):
        self.steps += 1
        fell = (self.env.bodies.pos[:, self.env.hum.skeleton.head, 2] < 0.5) & self.fall_ends
        term = fell | diverged | invalid
        return {"r_task": np.ones(self.env.num_envs)}, term, (self.steps >= self.limit) & ~term, {"diverged": diverged}


def hold(env):
    return lambda obs, goal: np.zeros((env.num_envs, env.action_dim))  # the rest pose's PD targets


# ----------------------------------------------------------------------------- the model

def test_ball_model_appends_balls_after_the_humanoid(hum, bhum, ball_path, tmp_path):
    m, p = bhum.model, hum.model
    assert (m.nq, m.nv, m.nu) == (p.nq + 7 * K, p.nv + 6 * K, p.nu)
    assert (bhum.nq, bhum.nv) == (hum.nq, hum.nv) == (p.nq, p.nv)
    pool = find_balls(m)
    assert pool.count == K and np.array_equal(pool.qadr, p.nq + 7 * np.arange(K))
    assert np.array_equal(pool.vadr, p.nv + 6 * np.arange(K))
    assert np.allclose(m.body_mass[pool.body], 4.2) and np.allclose(m.geom_size[pool.geom, 0], 0.1)
    assert (m.geom_type[pool.geom] == mujoco.mjtGeom.mjGEOM_SPHERE).all() and (m.dof_armature[pool.vadr] == 0).all()
    # The humanoid itself is unchanged: bodies, joints, gains, geometry, options.
    assert np.array_equal(bhum.body_ids, hum.body_ids) and np.array_equal(bhum.hinge_qpos_adr, hum.hinge_qpos_adr)
    for f in ("actuator_gainprm", "actuator_biasprm", "actuator_ctrlrange", "jnt_range", "dof_armature"):
        assert np.array_equal(getattr(m, f)[:len(getattr(p, f))], getattr(p, f)), f
    for f in ("geom_size", "geom_pos", "geom_contype", "geom_conaffinity", "body_mass", "body_pos"):
        assert np.array_equal(getattr(m, f)[:len(getattr(p, f))], getattr(p, f)), f
    assert m.opt.timestep == p.opt.timestep and np.array_equal(m.qpos0[:p.nq], p.qpos0)
    # Contact filter: a ball meets every humanoid geom and the floor, never another ball.
    ct, ca = m.geom_contype, m.geom_conaffinity
    collide = ((ct[:, None] & ca[None]) | (ct[None] & ca[:, None])) != 0
    body_geoms = np.flatnonzero(np.isin(m.geom_bodyid, hum.body_ids))
    assert collide[np.ix_(pool.geom, body_geoms)].all() and collide[pool.geom, 0].all()
    assert not collide[np.ix_(pool.geom, pool.geom)].any()
    # Parked on the floor, far away, and still there after a second of simulation.
    d = mujoco.MjData(m)
    for _ in range(120):
        mujoco.mj_step(m, d)
    pos = d.qpos[pool.qcols[:, :3]]
    assert (np.linalg.norm(pos[:, :2], axis=1) > 100).all() and np.allclose(pos[:, 2], 0.1, atol=2e-3)
    assert np.abs(d.qvel[pool.vcols]).max() < 1e-3
    with pytest.raises(UserError, match="already has balls"):
        build_ball_model(ball_path, tmp_path / "twice.xml", 2)
    with pytest.raises(UserError, match="no thrown balls"):
        find_balls(p)
    # Anything added *before* the humanoid would shift its state: the loader refuses it.
    text = hum.path.read_text()
    at = text.index("<body name=")
    bad = tmp_path / "first.xml"
    bad.write_text(text[:at] + '<body name="x" pos="5 5 1"><freejoint/><geom type="sphere" size=".1"/></body>' + text[at:])
    with pytest.raises(HumanoidError, match="must come first"):
        load_humanoid(bad)


@pytest.mark.parametrize("kind", ["batch", "rollout"])
def test_plain_humanoid_path_is_bit_identical(hum, bhum, kind):
    """HumanoidEnv on the plain model gives, to the last bit, what its stepper gives when driven
    as the environment drove it before balls existed (full states in, clipped targets, the
    stepper's bodies, Eq. 7 on the whole qpos/qvel); the ball model gives the same humanoid."""
    N, T = 6, 25
    rng = np.random.default_rng(0)
    q0 = np.tile(hum.model.qpos0, (N, 1))
    q0[:, 7:] += rng.normal(0, 0.2, q0[:, 7:].shape)
    v0 = rng.normal(0, 0.5, (N, hum.model.nv))
    targets = rng.normal(0, 0.3, (T, N, hum.model.nu))
    env = HumanoidEnv(hum, SimConfig(num_envs=N, stepper=kind, nthread=1))
    ref = make_stepper(kind, hum, N, env.substeps, 1)
    lo, hi = hum.model.actuator_ctrlrange.T
    ee = list(hum.skeleton.end_effectors)
    all_ids, part = np.arange(N), np.array([1, 4])
    for s in (env, ref):
        s.set_state(all_ids, q0, v0)
    benv = HumanoidEnv(bhum, SimConfig(num_envs=N, stepper=kind, nthread=1))
    benv.set_state(all_ids, q0, v0)
    for t in range(T):
        if t == 12:  # a partial reset mid-way
            env.set_state(part, q0[part], v0[part])
            ref.set_state(part, q0[part], v0[part])
            benv.set_state(part, q0[part], v0[part])
        d_env, _ = env.step(targets[t])
        d_ref = ref.step(np.clip(targets[t], lo, hi))
        benv.step(targets[t])
        b = ref.bodies()
        assert np.array_equal(d_env, d_ref) and not d_env.any()
        assert np.array_equal(env.qpos, ref.qpos) and np.array_equal(env.qvel, ref.qvel)
        assert np.array_equal(env.bodies.pos, b.pos) and np.array_equal(env.bodies.quat, b.quat)
        assert np.array_equal(env.observation(), observation(ref.qpos, ref.qvel, b, ee))
        assert benv.qpos.shape == env.qpos.shape and benv.observation().shape == env.observation().shape
    # Parked balls share only the solver's global convergence test with the humanoid.
    assert np.abs(benv.qpos - env.qpos).max() < 1e-6 and np.abs(benv.observation() - env.observation()).max() < 1e-5
    assert np.abs(ball_states(benv, find_balls(bhum.model))[1]).max() < 1e-3  # the balls stayed parked


def test_set_state_takes_the_humanoid_and_leaves_the_balls(bhum):
    env = HumanoidEnv(bhum, SimConfig(num_envs=3, nthread=1))
    pool = find_balls(bhum.model)
    set_balls(env, pool, [0, 1, 2], [1, 2, 0], np.array([[3.0, 0, 1], [0, 4, 1], [1, 1, 2]]), [1.0, 2.0, 3.0])
    pos, vel = ball_states(env, pool)
    assert np.array_equal(pos[[0, 1, 2], [1, 2, 0]], [[3.0, 0, 1], [0, 4, 1], [1, 1, 2]])
    assert np.array_equal(vel[[0, 1, 2], [1, 2, 0]], [[1.0, 2, 3]] * 3)
    assert np.array_equal(env.stepper.qpos[:, pool.qcols[:, 3]][[0, 1, 2], [1, 2, 0]], [1.0] * 3)  # unit quaternions
    q = env.qpos.copy()
    standing(env, np.array([0, 2]))
    p2, v2 = ball_states(env, pool)
    assert np.array_equal(p2, pos) and np.array_equal(v2, vel)  # balls untouched by a humanoid reset
    assert np.array_equal(env.qpos[1], q[1]) and np.array_equal(env.qpos[0], bhum.model.qpos0[:bhum.nq])
    full_q, full_v = env.stepper.qpos[[1]].copy(), env.stepper.qvel[[1]].copy()
    full_q[0, pool.qadr[0]] = 7.0
    env.set_state([1], full_q, full_v)  # the model's whole state works too
    assert ball_states(env, pool)[0][1, 0, 0] == 7.0
    with pytest.raises(ValueError, match="columns"):
        env.set_state([1], full_q[:, :10], full_v)
    park_balls(env, pool, [1])
    assert np.array_equal(ball_states(env, pool)[0][1], pool.park) and not ball_states(env, pool)[1][1].any()


# ----------------------------------------------------------------------------- launches, hits

def test_launch_geometry():
    rng = np.random.default_rng(0)
    n = 4000
    root = rng.uniform(-5, 5, (n, 3))
    root[:, 2] = rng.uniform(0.8, 1.0, n)
    for gravity in (0.0, 9.81):
        start, vel = launch_balls(root, np.random.default_rng(1), gravity=gravity)
        off = start[:, :2] - root[:, :2]
        assert np.allclose(np.linalg.norm(off, axis=1), 1.0, atol=1e-12)
        assert (start[:, 2] >= 0.5).all() and (start[:, 2] <= 1.5).all()
        s = np.linalg.norm(vel, axis=1)
        assert (s >= 10 - 1e-9).all() and (s <= 20 + 1e-9).all() and s.min() < 10.2 and s.max() > 19.8
        u = off / 1.0
        assert np.abs(u.mean(0)).max() < 0.05 and np.abs((u ** 2).mean(0) - 0.5).max() < 0.05  # uniform directions
        to = root - start
        cos = (to * vel).sum(1) / np.linalg.norm(to, axis=1) / s
        if gravity == 0:
            assert (cos > 1 - 1e-12).all()  # straight at the root
        else:
            assert (cos > np.cos(np.deg2rad(5))).all()  # a little above the line
            T = 1.0 / np.hypot(vel[:, 0], vel[:, 1])  # time to cover the horizontal metre
            at = start + vel * T[:, None] + 0.5 * np.array([0, 0, -gravity]) * T[:, None] ** 2
            assert np.abs(at - root).max() < 1e-9  # the ballistic arc goes through the root
    a, b = launch_balls(root[:5], np.random.default_rng(7)), launch_balls(root[:5], np.random.default_rng(7))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    aim = root[:5] + [0, 0, 0.5]
    st, v = launch_balls(root[:5], np.random.default_rng(7), target=aim, gravity=0.0)
    assert np.allclose(np.cross(aim - st, v), 0, atol=1e-9)
    with pytest.raises(UserError, match="speed"):
        launch_balls(root, rng, speed=(20, 10))
    with pytest.raises(UserError, match="out of reach"):
        launch_balls(root[:3], rng, distance=50.0, speed=(1.0, 1.0))


def test_segment_distance_matches_brute_force():
    rng = np.random.default_rng(2)
    P0, P1, Q0, Q1 = (rng.normal(0, 1, (200, 3)) for _ in range(4))
    P1[:40], Q1[40:80] = P0[:40], Q0[40:80]  # points
    Q1[80:120] = Q0[80:120] + 2 * (P1[80:120] - P0[80:120])  # parallel
    u = np.linspace(0, 1, 101)
    a, b = P0[:, None] + (P1 - P0)[:, None] * u[:, None], Q0[:, None] + (Q1 - Q0)[:, None] * u[:, None]
    brute = np.linalg.norm(a[:, :, None] - b[:, None], axis=-1).min((1, 2))
    d = segment_distance(P0, P1, Q0, Q1)
    assert (d <= brute + 1e-12).all() and (brute - d).max() < 1e-2


def test_a_ball_hits_a_standing_humanoid(bhum):
    """Balls at the root hit; one thrown over the head, one dropped on the floor 0.6 m in front
    and an env without a throw do not. The detector agrees with MuJoCo's contact list, read after
    every substep of a plain MjData loop that reproduces the batch to the last bit."""
    m, N = bhum.model, 5
    env = HumanoidEnv(bhum, SimConfig(num_envs=N, stepper="batch", nthread=1))
    pool, caps = find_balls(m), humanoid_capsules(bhum)
    standing(env)
    for _ in range(3):  # settle, so the solver has a warm start for the launch to leave alone
        env.step(np.zeros((N, env.action_dim)))
    root = env.bodies.pos[:, 0].copy()
    aim = root.copy()
    aim[2, 2] += 3.0  # over the head
    start, vel = launch_balls(root[:3], np.random.default_rng(3), speed=(12.0, 12.0), target=aim[:3])
    q_before, warm = env.qpos.copy(), env.stepper._warm.copy()
    set_balls(env, pool, [0, 1, 2], 0, start, vel)
    set_balls(env, pool, [3], 0, root[3] + [0.6, 0.0, -0.6], [0.0, 0.0, -3.0])  # lands on the floor at once
    assert np.array_equal(env.qpos, q_before) and np.array_equal(env.stepper._warm, warm) and warm.any()
    datas = []
    for i in range(N):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:], d.qacc_warmstart[:] = env.stepper.qpos[i], env.stepper.qvel[i], env.stepper._warm[i]
        mujoco.mj_forward(m, d)
        datas.append(d)
    body_geom = np.isin(m.geom_bodyid, bhum.body_ids)
    truth, seen = np.zeros((N, K), dtype=bool), np.zeros((N, K), dtype=bool)
    for t in range(20):
        before, bodies = ball_states(env, pool), env.bodies
        env.step(np.zeros((N, env.action_dim)))
        seen |= detect_hits(pool, caps, before, ball_states(env, pool), bodies, env.bodies, m.opt.gravity, env.dt)
        for i, d in enumerate(datas):
            for _ in range(env.substeps):
                mujoco.mj_step(m, d)
                for c in d.contact[:d.ncon]:
                    for a, b in (c.geom, c.geom[::-1]):
                        if a in pool.geom and body_geom[b]:
                            truth[i, list(pool.geom).index(a)] = True
            assert np.array_equal(d.qpos, env.stepper.qpos[i])
    assert np.array_equal(seen, truth)
    assert truth[:2, 0].all() and not truth[2:].any() and not truth[:, 1:].any()
    assert ball_states(env, pool)[0][3, 0, 2] < 0.11  # that one is on the floor
    moved = np.linalg.norm(env.qpos[:, :3] - env.qpos[4, :3], axis=1)
    assert (moved[:2] > 0.05).all() and (moved[2:4] < 1e-3).all()  # the hits pushed the humanoid; the misses did not


# ----------------------------------------------------------------------------- perturb()

def test_recovery_windows():
    """A hit is recovered when the head is up at the window's end, fallen in between or not."""
    w = Windows.empty(4, 3, length=3)
    w.open(np.arange(4), np.array([0, 1, 2, 3]), np.ones(4, dtype=np.int64))  # launch 3 wraps to entry 0
    heads = {2: [0, 1, 0, 0], 3: [0, 1, 1, 0], 4: [0, 0, 1, 1]}  # down? per env, steps 2-4
    got = [w.update(np.full(4, t, dtype=np.int64), np.array(heads[t], dtype=bool)) for t in (2, 3, 4)]
    # env 0 stayed up: recovered; env 1 fell and got up: recovered, and it fell; env 2 is down at the
    # end: not recovered; env 3 fell on the last step: not recovered.
    assert got[:2] == [(0, 0, 0), (0, 0, 0)] and got[2] == (4, 2, 3)
    assert (w.since == -1).all()
    w.open(np.array([0, 0]), np.array([4, 5]), np.array([5, 6]))
    w.update(np.full(4, 6, dtype=np.int64), np.array([1, 0, 0, 0], dtype=bool))
    assert w.close(np.array([0])) == (2, 2) and w.close(np.arange(4)) == (0, 0)


def test_pool_size_recycling_and_period(bhum):
    assert PerturbConfig().pool == 3 and PerturbConfig(period=0.1).pool == 6 and PerturbConfig(pool_size=2).pool == 2
    N = 2
    env = HumanoidEnv(bhum, SimConfig(num_envs=N, nthread=1))
    pool = find_balls(bhum.model)
    seen = []

    def act(obs, goal):  # called after each step's throws: a ball just thrown is 1 m from the root
        pos = ball_states(env, pool)[0]
        off = np.hypot(*(pos[..., :2] - env.bodies.pos[:, None, 0, :2]).transpose(2, 0, 1))
        seen.append((np.abs(off - 1.0) < 1e-9, np.linalg.norm(pos - pool.park, axis=-1) < 0.01))  # resting: mm deep
        return np.zeros((N, env.action_dim))

    mdp = TaskEnv(env, Stand(env, 2.0, fall_ends=False), lambda a, env, task: a)
    out = perturb(mdp, act, 2 * N, PerturbConfig(pool_size=2))  # two 60-step episodes per environment
    fresh = np.array([s[0] for s in seen])  # (T, N, K)
    parked = np.array([s[1] for s in seen])
    assert len(seen) == 120
    steps, envs, slots = np.nonzero(fresh)
    for e in range(N):
        st, sl = steps[envs == e], slots[envs == e]
        throws = 9 * np.arange(1, 7)
        assert np.array_equal(st, np.concatenate([throws, 60 + throws]))  # every 0.3 s of each episode
        assert np.array_equal(sl, np.arange(12) % 2)  # the oldest ball of the pool each time
    assert parked[:, :, 2].all()  # the third ball never flies
    assert parked[:9].all() and parked[60:69].all()  # none before the first throw; a reset parks them all
    assert out["launched"] == 12 * N and out["pool_size"] == 2 and out["period_s"] == pytest.approx(0.3)
    small = HumanoidEnv(bhum, SimConfig(num_envs=1, nthread=1))
    with pytest.raises(UserError, match="count=4"):
        perturb(TaskEnv(small, Stand(small, 1.0), lambda a, e, t: a), hold(small), 1, PerturbConfig(pool_size=4))
    with pytest.raises(UserError, match="0.1 m / 4.2 kg"):
        perturb(TaskEnv(small, Stand(small, 1.0), lambda a, e, t: a), hold(small), 1, PerturbConfig(mass=5.0))


@pytest.mark.parametrize("fall_ends", [True, False])
def test_perturb_counts_are_consistent(bhum, fall_ends):
    N = 3
    env = HumanoidEnv(bhum, SimConfig(num_envs=N, nthread=1))
    mdp = TaskEnv(env, Stand(env, 1.5, fall_ends), lambda a, env, task: a)
    out = perturb(mdp, hold(env), 6, PerturbConfig(recovery_seconds=0.5, seed=1))
    assert out["episodes"] == 6 and out["pool_size"] == 3
    assert 0 < out["hits"] <= out["launched"] <= 6 * 4 and out["hit_rate"] == out["hits"] / out["launched"]
    assert out["hits_resolved"] + out["hits_censored"] == out["hits"]
    assert out["recoveries"] <= out["hits_resolved"] and out["hits_followed_by_fall"] <= out["hits_resolved"]
    assert out["hits_resolved"] - out["recoveries"] <= out["hits_followed_by_fall"]  # not recovered: it fell
    assert out["recovery_rate"] == out["recoveries"] / out["hits_resolved"]
    assert out["success"] + out["terminated_share"] == pytest.approx(1.0) and out["mean_reward"] == 1.0
    assert out["falls"] > 0 and out["diverged"] == 0  # 4.2 kg at 10-20 m/s fells a PD-held pose
    if fall_ends:  # every terminated episode is exactly one fall
        assert out["falls"] == round(out["terminated_share"] * 6)
    else:
        assert out["success"] == 1.0 and out["launched"] == 6 * 4 and out["seconds"] == pytest.approx(6 * 1.5)
        bodies = perturb(mdp, hold(env), 3, PerturbConfig(aim="body", seed=2))  # at a random body each time
        assert bodies["launched"] == 12 and 0 < bodies["hits"] <= 12
    # Windows longer than the episodes can never end standing: they are censored, falls and all
    # (counting only their falls would bias the recovery rate low).
    long = perturb(mdp, hold(env), 6, PerturbConfig(recovery_seconds=10.0, seed=1))
    assert long["recoveries"] == 0 and long["hits"] > 0 and long["falls"] > 0
    assert long["hits_censored"] == long["hits"] and long["hits_resolved"] == 0 and long["hits_followed_by_fall"] == 0
    assert np.isnan(long["recovery_rate"])
    # The control: no throws within an episode, no hits, no falls (the pose holds).
    calm = perturb(mdp, hold(env), 3, PerturbConfig(period=2.0))
    assert calm["launched"] == calm["hits"] == calm["falls"] == 0 and calm["success"] == 1.0
    assert np.isnan(calm["recovery_rate"]) and np.isnan(calm["hit_rate"])


def test_perturb_on_navigation_keeps_the_task_measurable(hum, bhum, lib):
    """The real use: the navigation task's starts from the plain humanoid's library, on the ball model."""
    from motok.control.tasks.navigation import NavigationTask, NavigationTaskConfig

    env = HumanoidEnv(bhum, SimConfig(num_envs=3, nthread=1))
    task = NavigationTask(NavigationTaskConfig(episode_seconds=1.0), env, lib, np.random.default_rng(0))
    mdp = TaskEnv(env, task, lambda a, env, task: a)
    out = perturb(mdp, lambda obs, goal: env.qpos[:, env.hinge_adr].copy(), 3)
    assert out["episodes"] == 3 and 0 <= out["hits"] <= out["launched"] <= 3 * 3
    assert out["targets"] >= 3 and 0.0 <= out["reached_share"] <= 1.0
    assert out["success"] + out["terminated_share"] == pytest.approx(1.0)
