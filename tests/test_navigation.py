"""The navigation task (hybrid-latent paper, appendix C.3): its pure terms against hand-computed
values (Eq. 15 goal, Eq. 16 reward, fall test, target draws), the task on the real humanoid
(retargeting, truncation, rewards of a standing character, a fall) and the evaluation loop."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest

from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.navigation import head_fell, heading_frame_target, navigation_reward, sample_targets
from motok.control.mdp.resets import reference_state
from motok.control.tasks.episodes import episode_quota
from motok.control.tasks.navigation import IDLE_SPEED, MIN_IDLE_SECONDS, evaluate_navigation, idle_matching, stays
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.navigation import NavigationTask, NavigationTaskConfig
from motok.errors import UserError
from motok.rotations import quat_to_matrix
from motok.sim.env import HumanoidEnv, SimConfig

pytestmark = pytest.mark.usefixtures("one_thread")


def yaw_quat(deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """(w, x, y, z) of a yaw about world Z after a pitch about the body Y axis, multiplied by hand:
    (c1, 0, 0, s1) (c2, 0, s2, 0) = (c1 c2, -s1 s2, c1 s2, s1 c2)."""
    a, b = math.radians(deg) / 2, math.radians(pitch_deg) / 2
    return np.array([math.cos(a) * math.cos(b), -math.sin(a) * math.sin(b), math.cos(a) * math.sin(b),
                     math.sin(a) * math.cos(b)])


# ----------------------------------------------------------------------------- pure terms
def test_goal_is_the_target_in_the_heading_frame():
    root = np.array([[1.0, 2.0, 0.9]] * 6)
    c30, s30 = math.cos(math.radians(30)), math.sin(math.radians(30))
    quat = np.stack([yaw_quat(0), yaw_quat(90), yaw_quat(180), yaw_quat(90, pitch_deg=30), yaw_quat(30), yaw_quat(30)])
    target = np.array([[4.0, 2.0], [4.0, 2.0], [4.0, 2.0], [4.0, 2.0],
                       [1 + 4 * c30, 2 + 4 * s30],  # 4 m straight ahead of a root yawed by 30 degrees
                       [1 - 2 * s30, 2 + 2 * c30]])  # 2 m on its left
    g = heading_frame_target(root, quat, target)
    # facing +X: 3 m ahead; facing +Y (yaw 90): world +X is on the right, (0, -3); facing -X: behind.
    # A pitched (leaning) root has the same heading as the upright one: yaw only.
    want = [[3, 0], [0, -3], [-3, 0], [0, -3], [4, 0], [0, 2]]
    np.testing.assert_allclose(g, want, atol=1e-12)
    np.testing.assert_allclose(heading_frame_target(root, quat_to_matrix(quat), target), want, atol=1e-12)


def test_reward_against_hand_values():
    """Eq. 16 on hand states, in the fork's form (the position term decays inside the radius too);
    the paper's maximum on arrival is the next test."""
    cfg = NavigationTaskConfig(full_reward_on_arrival=False)
    e = math.exp
    c45 = math.cos(math.pi / 4)
    cases = [  # (root xy, yaw deg, planar velocity, target, r_vel)
        ((0, 0), 0, (0, 0), (0.3, 0), 1.0),  # at the goal, standing: the velocity term is full
        ((0, 0), 0, (0, 0), (0, 0), 1.0),  # exactly on it (no direction): still full
        ((0, 0), 0, (0, 0), (5, 0), e(-1)),  # far, standing still
        ((0, 0), 0, (1.5, 0), (2, 0), 1.0),  # walking toward it faster than u
        ((0, 0), 0, (0.5, 0), (2, 0), e(-0.25)),  # toward it at half the speed
        ((0, 0), 180, (-1.5, 0), (2, 0), e(-2.5 ** 2)),  # walking away from it: v = -1.5
        ((0, 0), 180, (1.5, 0), (2, 0), e(-1)),  # backwards toward it: forward part clamped at 0
        ((0, 0), 0, (0, 1.0), (0, 2), e(-1)),  # side-stepping toward it: no forward component
        ((0, 0), 45, (c45, c45), (2, 0), e(-(1 - c45) ** 2)),  # 1 m/s at 45 degrees off the target
        ((0, 0), 0, (0, 0), (0.5, 0), e(-1)),  # the radius is strict: 0.5 m is not "within"
        ((3, -1), 90, (0, 2.0), (3, 2), 1.0),  # away from the origin, facing +Y toward a target at +Y
    ]
    root = np.array([[x, y, 0.9] for (x, y), *_ in cases])
    quat = np.stack([yaw_quat(c[1]) for c in cases])
    vel = np.array([[vx, vy, 3.0] for _, _, (vx, vy), *_ in cases])  # a vertical velocity changes nothing
    target = np.array([c[3] for c in cases], dtype=float)
    r = navigation_reward(root, vel, quat, target, cfg)
    d = np.hypot(*(target - root[:, :2]).T)
    np.testing.assert_allclose(r["r_vel"], [c[4] for c in cases], rtol=1e-12)
    np.testing.assert_allclose(r["r_pos"], np.exp(-0.5 * d ** 2), rtol=1e-12)
    np.testing.assert_allclose(r["r_task"], 0.7 * np.exp(-0.5 * d ** 2) + 0.3 * np.array([c[4] for c in cases]),
                               rtol=1e-12)
    assert r["r_task"][0] == pytest.approx(0.7 * e(-0.045) + 0.3)
    assert r["r_task"][2] == pytest.approx(0.7 * e(-12.5) + 0.3 * e(-1))
    assert r["r_task"][3] > r["r_task"][4] > r["r_task"][6] > r["r_task"][5]  # toward > slower > still-ish > away
    # The paper's form (the default) differs only within the radius, where it is the maximum
    paper = navigation_reward(root, vel, quat, target, NavigationTaskConfig())
    inside = d < 0.5
    assert inside.tolist() == [True, True] + [False] * 9
    np.testing.assert_array_equal(paper["r_task"][inside], 1.0)
    np.testing.assert_array_equal(paper["r_task"][~inside], r["r_task"][~inside])


def test_the_reward_is_its_maximum_anywhere_within_the_arrival_radius():
    """C.3 / Eq. 16: arrival earns the maximum, w_pos + w_vel = 1, wherever inside the 0.5 m radius
    the root stands and however it moves (walking on, away, backwards); just outside, less."""
    cfg = NavigationTaskConfig()
    rng = np.random.default_rng(3)
    n = 200
    ang, rad = rng.uniform(0, 2 * np.pi, n), np.r_[0.0, 0.499999, rng.uniform(0, 0.5, n - 2)]
    target = np.array([[2.0, -1.0]])
    root = np.c_[target + rad[:, None] * np.c_[np.cos(ang), np.sin(ang)], np.full(n, 0.9)]
    quat = np.stack([yaw_quat(a) for a in rng.uniform(-180, 180, n)])
    vel = np.c_[rng.uniform(-2, 2, (n, 2)), np.zeros(n)]
    r = navigation_reward(root, vel, quat, np.repeat(target, n, 0), cfg)
    np.testing.assert_array_equal(r["r_task"], 1.0)
    np.testing.assert_array_equal(r["r_pos"], 1.0)
    out = navigation_reward(root[:1] + [0.5, 0, 0], np.zeros((1, 3)), quat[:1], target, cfg)
    assert out["r_task"][0] == pytest.approx(0.7 * math.exp(-0.125) + 0.3 * math.exp(-1))


def test_head_fall_skips_the_first_step():
    h = np.array([0.4, 0.4, 0.4, 0.6, 0.5])
    steps = np.array([1, 2, 50, 50, 50])
    assert head_fell(h, steps, 0.5).tolist() == [False, True, True, False, False]


def test_targets_are_uniform_in_direction_and_distance():
    rng = np.random.default_rng(0)
    root = np.tile([3.0, -2.0, 0.9], (40000, 1))
    t = sample_targets(root, rng, 5.0, 10.0)
    disp = t - root[:, :2]
    d = np.hypot(*disp.T)
    assert d.min() >= 5.0 and d.max() <= 10.0
    assert d.mean() == pytest.approx(7.5, abs=0.05)
    assert (d < 7.5).mean() == pytest.approx(0.5, abs=0.01)  # uniform in distance (by area: 0.417)
    unit = disp / d[:, None]
    assert np.hypot(*unit.mean(0)) < 0.02  # no preferred direction
    counts = np.bincount((np.arctan2(unit[:, 1], unit[:, 0]) // (np.pi / 4)).astype(int) + 4, minlength=8)
    assert np.abs(counts / len(d) - 1 / 8).max() < 0.01
    same = sample_targets(root[:3], np.random.default_rng(1), 2.0, 2.0)
    np.testing.assert_allclose(np.hypot(*(same - root[:3, :2]).T), 2.0)
    with pytest.raises(UserError, match="min_dist"):
        sample_targets(root[:3], rng, 10.0, 5.0)


def test_config_errors_name_the_field():
    with pytest.raises(UserError, match="min_distance"):
        NavigationTaskConfig(min_distance=11.0)
    with pytest.raises(UserError, match="retarget_seconds"):
        NavigationTaskConfig(retarget_seconds=0)
    with pytest.raises(UserError, match="w_vel"):
        NavigationTaskConfig(w_vel=-1)


# ----------------------------------------------------------------------------- on the humanoid
SHORT = dict(episode_seconds=1.0, retarget_seconds=0.5)  # 30 steps, a new target after 15


def _mdp(hum, lib, n, seed=0, nan_actions="raise", **cfg) -> TaskEnv:
    env = HumanoidEnv(hum, SimConfig(num_envs=n, nthread=1, nan_actions=nan_actions))
    task = NavigationTask(NavigationTaskConfig(**cfg), env, lib, np.random.default_rng(seed))
    return TaskEnv(env, task, partial(pd_targets, ActionConfig("current")))


def _hold(mdp):
    """Zero residuals on the current pose: PD targets hold the current hinge angles."""
    return np.zeros((mdp.num_envs, mdp.action_dim))


def _forward(q):
    """Unit planar forward axis of (w, x, y, z) quaternions, from the rotation matrix's first column."""
    w, x, y, z = q.T
    f = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z)], -1)
    return f / np.linalg.norm(f, axis=-1, keepdims=True)


def test_head_body_by_name(hum, lib):
    env = HumanoidEnv(hum, SimConfig(num_envs=1, nthread=1))
    task = NavigationTask(NavigationTaskConfig(), env, lib, np.random.default_rng(0))
    assert hum.skeleton.joints[task.head] == "Head"
    assert NavigationTask(NavigationTaskConfig(head_body="Neck"), env, lib, np.random.default_rng(0)).head == \
        hum.skeleton.joints.index("Neck")
    with pytest.raises(UserError, match="head_body 'Skull' .*bodies: Hips"):
        NavigationTask(NavigationTaskConfig(head_body="Skull"), env, lib, np.random.default_rng(0))


def test_targets_change_every_retarget_period_and_episodes_truncate(hum, lib):
    mdp = _mdp(hum, lib, 2, early_termination=False, **SHORT)
    task, env = mdp.task, mdp.env
    _, goal = mdp.reset(clips=[0, 1], frames=[3, 7])
    np.testing.assert_allclose(env.qpos, reference_state(lib, np.array([0, 1]), np.array([3, 7]))[0])
    root = env.qpos[:, :2].copy()
    d0 = np.hypot(*(task.target - root).T)
    assert (d0 <= 10).all() and (task.target_index == 0).all()
    # Eq. 15 by hand: the displacement turned by minus the root's heading
    f = _forward(env.qpos[:, 3:7])
    disp = task.target - root
    np.testing.assert_allclose(goal, np.stack([(disp * f).sum(1), f[:, 0] * disp[:, 1] - f[:, 1] * disp[:, 0]], 1),
                               atol=1e-9)
    first = task.target.copy()
    for t in range(1, 31):
        _, goal, r, term, trunc, info = mdp.step(_hold(mdp))
        assert info["target_time"] == pytest.approx(np.full(2, (t - 1) % 15 + 1) / 30)
        assert (info["target_index"] == (t - 1) // 15).all() and not term.any()
        assert info["target_ends"].all() == (t % 15 == 0) and trunc.all() == (t == 30) and trunc.any() == (t == 30)
        if t < 15:
            np.testing.assert_array_equal(task.target, first)
        if t == 15:  # a new target within 10 m of where the root is now, and the goal already shows it
            assert (task.target_index == 1).all() and not np.isclose(task.target, first).any()
            d = np.hypot(*(task.target - env.qpos[:, :2]).T)
            assert (d <= 10).all()
            np.testing.assert_allclose(goal, heading_frame_target(env.qpos[:, :3], env.qpos[:, 3:7], task.target))
            np.testing.assert_allclose(info["distance"], np.hypot(*(first - env.qpos[:, :2]).T))  # the old one's
    assert (task.target_index == 1).all()  # no third target at the truncation step
    mdp.reset([1])
    assert task.target_index.tolist() == [1, 0] and task.steps.tolist() == [30, 0]


def test_given_starts_must_lie_inside_their_clips(hum, lib):
    mdp = _mdp(hum, lib, 2)
    end = int(lib.lengths[1])
    mdp.reset(clips=[0, 1], frames=[0, end - 1])  # the last frame is a start
    with pytest.raises(UserError, match=rf"^navigation task: start frames \[{end}\] are outside their clips "
                                        rf"\(lengths \[{end}\]\)"):
        mdp.reset(clips=[0, 1], frames=[0, end])


def test_the_papers_targets_within_10_m_renewed_every_4_s(hum, lib):
    """C.3 with the defaults: a target within 10 m of the root, a new one exactly every 4 s (120
    control steps) drawn around where the root is then, 8 s episodes; the same seed draws the same
    targets. Over many draws the distance is uniform on [0, 10] m."""
    d = np.hypot(*(sample_targets(np.zeros((40000, 3)), np.random.default_rng(0), 0.0, 10.0)).T)
    assert d.max() <= 10.0 and d.mean() == pytest.approx(5.0, abs=0.05)
    assert (d < 0.5).mean() == pytest.approx(0.05, abs=0.005)  # uniform in distance: 5 % start within the radius
    runs = []
    for _ in range(2):
        mdp = _mdp(hum, lib, 2, seed=7, early_termination=False)
        task, env = mdp.task, mdp.env
        assert (task.retarget_steps, task.max_steps) == (120, 240)
        mdp.reset(clips=[0, 1], frames=[3, 7])
        targets, changed = [task.target.copy()], []
        assert (np.hypot(*(task.target - env.qpos[:, :2]).T) <= 10.0).all()
        for t in range(1, 241):
            _, _, _, _, trunc, info = mdp.step(_hold(mdp))
            if not np.array_equal(task.target, targets[-1]):
                changed.append(t)
                targets.append(task.target.copy())
                assert (np.hypot(*(task.target - env.qpos[:, :2]).T) <= 10.0).all()
            assert trunc.all() == (t == 240)
        assert changed == [120]  # renewed at 4 s; the episode ends at 8 s, before a third
        runs.append(np.stack(targets))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_standing_humanoid_rewards_and_a_dropped_one_terminates(hum, lib):
    mdp = _mdp(hum, lib, 3)
    task, env = mdp.task, mdp.env
    mdp.reset(clips=[0, 0, 0], frames=[0, 0, 0])
    q = env.qpos.copy()
    env.set_state(np.arange(3), q, np.zeros_like(env.qvel))  # at rest
    f = _forward(q[:, 3:7])
    # env 0: 6 m ahead; env 1: 0.3 m ahead (at the goal); env 2: dropped on the floor at step 1 (grace)
    task.set_targets([0, 1, 2], q[:, :2] + f * np.array([[6.0], [0.3], [6.0]]))
    lying = q[2].copy()
    lying[2], lying[3:7] = 0.25, yaw_quat(0, pitch_deg=90)  # pitched face-down, the head near the floor
    env.set_state(np.array([2]), lying[None], np.zeros((1, env.qvel.shape[1])))
    assert env.bodies.pos[2, task.head, 2] < 0.5 < env.bodies.pos[0, task.head, 2]
    _, _, r, term, trunc, info = mdp.step(_hold(mdp))
    assert not term.any() and not info["fell"].any()  # the first step is never a fall
    v = env.qvel[:, :2]
    fwd = _forward(env.qpos[:, 3:7])
    toward = np.maximum((v * fwd).sum(1), 0) * ((task.target - env.qpos[:, :2]) * fwd).sum(1) / info["distance"]
    d = info["distance"]
    assert np.abs(np.hypot(*v.T)[:2]).max() < 0.1 and abs(d[1] - 0.3) < 0.02  # standing still
    np.testing.assert_allclose(r["r_vel"][0], math.exp(-(1 - toward[0]) ** 2), rtol=1e-4)
    assert r["r_vel"][1] == 1.0
    np.testing.assert_allclose(r["r_task"][0], 0.7 * np.exp(-0.5 * d[0] ** 2) + 0.3 * r["r_vel"][0], rtol=1e-12)
    assert r["r_task"][0] == pytest.approx(0.7 * math.exp(-18) + 0.3 * math.exp(-1), abs=0.02)
    assert r["r_task"][1] == 1.0 and r["r_pos"][1] == 1.0  # at the goal: Eq. 16's maximum (C.3)
    assert info["reached"].tolist() == [False, True, False] and info["time_to_reach"][1] == pytest.approx(1 / 30)
    _, _, r, term, trunc, info = mdp.step(_hold(mdp))
    assert term.tolist() == [False, False, True] and info["fell"].tolist() == [False, False, True]
    assert not trunc.any() and r["r_task"][2] > 0  # a fall is not a diverged simulation: rewarded as usual
    # a fall in mid-episode, dropped after the grace step
    env.set_state(np.array([0]), lying[None], np.zeros((1, env.qvel.shape[1])))
    _, _, _, term, _, info = mdp.step(_hold(mdp))
    assert term[0] and info["fell"][0]


def test_invalid_actions_get_no_reward_and_terminate(hum, lib):
    mdp = _mdp(hum, lib, 2, nan_actions="terminate")
    mdp.reset(clips=[0, 0], frames=[5, 5])
    a = _hold(mdp)
    a[1, 0] = np.nan
    _, goal, r, term, _, info = mdp.step(a)
    assert term.tolist() == [False, True] and info["invalid_action"][1]
    assert r["r_task"][1] == 0.0 and r["r_task"][0] > 0 and np.isfinite(goal).all()


def test_evaluation_counts_targets_falls_and_goal_speeds(hum, lib):
    assert episode_quota(7, 3).tolist() == [3, 2, 2] and episode_quota(2, 3).tolist() == [1, 1, 0]

    def run(episodes, n=2, idle_speed=IDLE_SPEED, **cfg):
        mdp = _mdp(hum, lib, n, **cfg)
        return evaluate_navigation(mdp, lambda obs, goal: np.zeros((len(obs), mdp.action_dim)), episodes, idle_speed)

    # Targets 5-10 m away (the fork's draw) are never reached by a character holding its pose.
    far = run(3, min_distance=5.0, early_termination=False, **SHORT)
    assert far["episodes"] == 3 and far["targets"] == 6 and far["reached_share"] == 0.0
    assert math.isnan(far["time_to_reach_mean_s"]) and len(far["goal_speeds"]) == 0 and far["falls_per_episode"] == 0
    # Targets within the radius are reached on the first step (a walking start state carries the
    # character on, but a new target is drawn around it before it leaves the radius).
    near = run(2, min_distance=0.0, max_distance=0.05, early_termination=False, **SHORT)
    assert near["targets"] == 4 and near["reached_share"] == 1.0
    assert near["time_to_reach_mean_s"] == pytest.approx(1 / 30)
    assert near["time_to_reach_median_s"] == pytest.approx(1 / 30)
    speeds = near["goal_speeds"]
    assert 4 <= len(speeds) <= 2 * 30 and (speeds >= 0).all()
    assert near["goal_speed_mean"] == pytest.approx(speeds.mean()) and near["goal_speed_median"] == np.median(speeds)
    assert near["mean_reward"] > far["mean_reward"]
    # The idle phase's bodies: every stay at a target of at least MIN_IDLE_SECONDS, within one
    # episode, slower than the idling speed (with none, the walking start's drift counts too).
    assert far["idle_bodies"] == []
    every = run(2, idle_speed=np.inf, min_distance=0.0, max_distance=0.05, early_termination=False, **SHORT)
    idle = every["idle_bodies"]
    lengths = [len(b) for b in idle]
    assert idle and min(lengths) >= round(MIN_IDLE_SECONDS * 30) and sum(lengths) <= len(speeds)
    assert all(b.shape[1:] == (hum.model.nbody - 1, 3) and np.isfinite(b).all() for b in idle)

    def drift(b):  # m/s, the root's planar speed over a stay
        return np.linalg.norm(b[-1, 0, :2] - b[0, 0, :2]) / ((len(b) - 1) / 30)

    assert max(drift(b) for b in idle) > IDLE_SPEED  # walking through the circle is there without the test
    slow = near["idle_bodies"]
    assert sum(len(b) for b in slow) <= (speeds < IDLE_SPEED).sum() < sum(lengths)
    assert all(drift(b) <= IDLE_SPEED + 0.05 for b in slow)
    # A head "below" 3 m is a fall on every second step: one fall per episode, its target missed.
    fall = run(3, fall_height=3.0, min_distance=5.0, **SHORT)
    assert fall["falls_per_episode"] == 1.0 and fall["targets"] == 3 and fall["reached_share"] == 0.0
    # Per target: the distance when it appeared (drawn 5-10 m around the root) and the closest approach.
    st, cl = far["start_distances"], far["closest_distances"]
    assert len(st) == len(cl) == far["targets"] and ((st >= 5 - 1e-9) & (st <= 10 + 1e-9)).all()
    assert far["approach_share"] == pytest.approx(np.mean(1 - cl / st))
    assert far["start_distance_mean_m"] == pytest.approx(st.mean()) and far["closest_distance_mean_m"] == cl.mean()
    for res in (far, near, fall, run(4, min_distance=0.0, max_distance=10.0, early_termination=False, **SHORT)):
        st, cl = res["start_distances"], res["closest_distances"]
        # a character holding its pose drifts at most ~1 m in a target's 0.5 s: the closest approach is the
        # start distance of *this* target less that drift (a start or minimum carried over from the target
        # before would break it), and a target is reached exactly when it came within the radius
        assert (cl <= st + 1e-9).all() and (st - cl <= 1.0).all() and (cl >= 0).all()
        assert int((cl < 0.5).sum()) == round(res["reached_share"] * res["targets"])
        assert res["approach_share"] == pytest.approx(np.mean(1 - cl / st))  # the mean share of the distance closed
    with pytest.raises(UserError, match="episodes"):
        run(0)


def test_stays_are_runs_within_one_episode():
    m = np.array([[1, 0], [1, 1], [1, 1], [0, 1], [1, 1], [1, 0]], dtype=bool)
    ep = np.array([[0, 0], [0, 0], [0, 1], [0, 1], [0, 1], [0, 1]])
    # env 0: steps 0-2 on, off, 4-5 on; env 1: on at 1-4 but a new episode starts at step 2
    assert stays(m, ep, 1) == [(0, 0, 3), (0, 4, 6), (1, 1, 2), (1, 2, 5)]
    assert stays(m, ep, 3) == [(0, 0, 3), (1, 2, 5)]
    assert stays(np.zeros((4, 3), bool), np.zeros((4, 3), int), 1) == []


def test_idle_motion_matching_tells_data_from_noise(hum, lib, small_dataset):
    """Motion at the target is matched against the dataset (Eq. 8): reference motion itself comes
    out near the data (the library is the data through the humanoid's FK at 30 Hz), the same
    motion with 3 cm of jitter on every body far from it."""
    segs = [lib.body_pos[lib.starts[i]:lib.starts[i] + 45] for i in range(3)]  # 1.5 s of three clips
    rng = np.random.default_rng(0)
    noisy = [s + rng.normal(0, 0.03, s.shape) for s in segs]
    real = idle_matching(segs, small_dataset, lib.names, lib.fps)
    bad = idle_matching(noisy, small_dataset, lib.names, lib.fps)
    assert real["segments"] == 3 and real["transitions"] == 3 * (30 - 2)  # 45 steps at 30 Hz: 30 frames at 20 fps
    # the distance is Eq. 8's mean over the valid transitions: the noisy motion has (almost) none
    assert real["distance_mean"] < real["threshold"] and real["valid"] > 0.8 * real["transitions"]
    assert real["filtered_rate"] < 0.2 < 0.8 < bad["filtered_rate"] and bad["valid"] < 0.2 * bad["transitions"]
    none = idle_matching([], small_dataset, lib.names, lib.fps)
    assert none["transitions"] == 0 and math.isnan(none["distance_mean"])
