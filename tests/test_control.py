"""The control stage's parts: MDP terms composed into the imitation task, the action maps,
policy-owned distributions (Gaussian and multi-categorical) through one PPO update, and the
PD-tracking baseline. Physics alone is tested in test_sim.py, the expert in test_expert.py."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest
import torch

from motok.control.expert.baselines import pd_track
from motok.control.mdp.actions import ActionConfig, pd_targets, reference_base
from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.rewards import ImitationConfig, imitation_errors, imitation_reward
from motok.control.mdp.terminations import tracking_failure
from motok.control.rl.networks import ActorCritic, RunningNorm, ValueNet
from motok.control.rl.policies import MultiCategoricalPolicy
from motok.control.rl.ppo import PPO, PPOConfig
from motok.control.rl.rollout import Rollout
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.imitation import ImitationTask, ImitationTaskConfig
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.obs import Bodies, TreeKinematics, observation
from conftest import require_module


def _mdp(hum, lib, n, seed=0, base="current", stepper="auto", nan_actions="raise", **task) -> TaskEnv:
    env = HumanoidEnv(hum, SimConfig(num_envs=n, stepper=stepper, nan_actions=nan_actions))
    t = ImitationTask(ImitationTaskConfig(**task), env, lib, np.random.default_rng(seed))
    return TaskEnv(env, t, partial(pd_targets, ActionConfig(base)))


def _pd_actions(mdp):
    """Residual actions (on the current pose) that send the PD targets to the next reference frame."""
    env = mdp.env
    return mdp.task.next_reference()[0][:, env.hinge_adr] - env.qpos[:, env.hinge_adr]


# ----------------------------------------------------------------------------- terms

def test_imitation_reward_terms_against_hand_values():
    pos = np.zeros((1, 3, 3))
    ref = pos.copy()
    ref[0, 0] = [0.1, 0.0, 0.0]  # root off by 0.1 m: e_root = 0.01, and the end effectors' relative error too
    q, q_ref = np.zeros((1, 2)), np.array([[0.1, 0.2]])
    qd, qd_ref = np.zeros((1, 2)), np.array([[1.0, 3.0]])
    err = imitation_errors(pos, ref, q, q_ref, qd, qd_ref, [1, 2])
    assert err["root"][0] == pytest.approx(0.01) and err["q"][0] == pytest.approx(0.05)
    assert err["alpha"][0] == pytest.approx(5.0) and err["ee"][0] == pytest.approx(0.02)
    r = imitation_reward(err, ImitationConfig())
    assert r["r_im"][0] == pytest.approx(math.exp(-10 * 0.01 - 2 * 0.05 - 0.5 * 5.0 - 40 * 0.02))


def _yaw_shift(b: Bodies, yaw: float, shift: np.ndarray) -> Bodies:
    c, s = np.cos(yaw), np.sin(yaw)
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return Bodies(b.pos @ r.T + shift, b.vel @ r.T, b.angvel @ r.T, rot=r @ b.rot)


def test_observation_and_goal_invariant_to_heading_and_position(hum, lib):
    from motok.rotations import qmul

    fk = TreeKinematics(hum)
    rng = np.random.default_rng(1)
    g = rng.integers(0, len(lib.qpos) - 3, 6)
    q, v = lib.qpos[g].copy(), lib.qvel[g].copy()
    q[:, 7:] += rng.normal(0, 0.2, q[:, 7:].shape)  # a sim state off its reference
    sim = fk(q, v)
    ref = Bodies(lib.body_pos[g + 1][:, None], lib.body_vel[g + 1][:, None], lib.body_angvel[g + 1][:, None],
                 quat=lib.body_quat[g + 1][:, None])
    ee = list(hum.skeleton.end_effectors)
    yaw, shift = 2.1, np.array([3.0, -7.5, 0.0])
    q2, v2 = q.copy(), v.copy()
    c, s = np.cos(yaw / 2), np.sin(yaw / 2)
    q2[:, 3:7] = qmul(np.array([c, 0, 0, s]), q[:, 3:7])
    q2[:, :3] = _yaw_shift(Bodies(q[:, None, :3], q[:, None, :3], q[:, None, :3], rot=np.eye(3)[None, None]),
                           yaw, shift).pos[:, 0]
    v2[:, :3] = v[:, :3] @ np.array([[c * c - s * s, 2 * c * s, 0], [-2 * c * s, c * c - s * s, 0], [0, 0, 1]])
    sim2 = fk(q2, v2)
    assert np.allclose(sim2.pos, _yaw_shift(sim, yaw, shift).pos)  # the transform is what we think it is
    ref2 = _yaw_shift(ref, yaw, shift)
    assert np.allclose(observation(q, v, sim, ee), observation(q2, v2, sim2, ee), atol=1e-9)
    assert np.allclose(imitation_goal(sim, ref), imitation_goal(sim2, ref2), atol=1e-9)
    # at the reference itself every difference vanishes (rotation: the identity's two columns)
    on_ref = ref.take((slice(None), 0))
    gz = imitation_goal(on_ref, ref).reshape(len(g), -1, 15)
    assert np.abs(gz[..., :3]).max() < 1e-12 and np.abs(gz[..., 9:]).max() < 1e-12
    assert np.allclose(gz[..., 3:9], [1, 0, 0, 0, 1, 0])


def test_tracking_failure_any_or_mean():
    dist = np.array([[0.1, 0.1, 0.9], [0.6, 0.6, 0.6]])
    assert tracking_failure(dist, "any", 0.5).tolist() == [True, True]
    assert tracking_failure(dist, "mean", 0.5).tolist() == [False, True]
    with pytest.raises(ValueError, match="termination"):
        tracking_failure(dist, "median", 0.5)


# ----------------------------------------------------------------------------- the imitation MDP

def test_same_seed_same_trajectory(hum, lib):
    def run(seed):
        mdp = _mdp(hum, lib, 3, seed=seed)
        obs, _ = mdp.reset()
        rng = np.random.default_rng(7)
        out = [obs]
        for _ in range(12):
            obs, gl, r, term, trunc, info = mdp.step(rng.normal(0, 0.1, (3, mdp.action_dim)))
            out.append(np.concatenate([obs, gl, r["r_im"][:, None]], 1))
            done = np.flatnonzero(term | trunc)
            if len(done):
                mdp.reset(done)
        return np.concatenate([o.ravel() for o in out]), mdp.task.clip.copy()

    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0][:200], c[0][:200])


@pytest.mark.parametrize("stepper", ["batch", "rollout"])
def test_batch_equals_single_envs(hum, lib, stepper):
    if stepper == "batch":
        require_module("mujoco.batch", "this MuJoCo has no mujoco.batch")
    clips, frames = [0, 3, 7, 11], [0, 20, 41, 5]
    batch = _mdp(hum, lib, 4, stepper=stepper)
    batch.reset(clips=clips, frames=frames)
    singles = [_mdp(hum, lib, 1, stepper=stepper) for _ in clips]
    for e, c, f in zip(singles, clips, frames):
        e.reset(clips=[c], frames=[f])
    for _ in range(8):
        a = _pd_actions(batch)
        ob, gb, rb, tb, _, _ = batch.step(a)
        for i, e in enumerate(singles):
            os_, gs, rs, ts, _, _ = e.step(a[i:i + 1])
            assert np.array_equal(ob[i], os_[0]) and np.array_equal(gb[i], gs[0])
            assert rb["r_im"][i] == rs["r_im"][0] and tb[i] == ts[0]


def test_reference_action_base_offsets_from_the_next_reference_frame(hum, lib):
    """The reference base is the next frame's angles plus (kv / kp) times its velocities, so the
    position servo tracks both; zero actions on it are those offsets on the current base (to
    rounding: ``q + (b - q)`` is not bit-identical to ``b``)."""
    clips, frames = [0, 5, 9], [3, 30, 60]
    ref, cur = _mdp(hum, lib, 3, base="reference"), _mdp(hum, lib, 3)
    for e in (ref, cur):
        e.reset(clips=clips, frames=frames)
    m, L = hum.model, lib
    env = ref.env
    assert np.allclose(env.velocity_lead, m.actuator_biasprm[:, 2] / m.actuator_biasprm[:, 1])
    for _ in range(6):
        g = L.starts[ref.task.clip] + ref.task.frame + 1
        target = L.qpos[g][:, 7:] + env.velocity_lead * L.qvel[g][:, 6:]  # hinges follow the free joint
        base = reference_base(env, *ref.task.next_reference())
        assert np.allclose(base, target)
        zero = np.zeros((3, env.action_dim))
        assert np.allclose(pd_targets(ActionConfig("current"), zero, cur.env, cur.task), cur.env.qpos[:, 7:])
        a = base - cur.env.qpos[:, 7:]
        o1, g1, r1, *_ = ref.step(zero)
        o2, g2, r2, *_ = cur.step(a)
        assert np.allclose(o1, o2, atol=1e-7) and np.allclose(g1, g2, atol=1e-7)
        assert np.allclose(r1["r_im"], r2["r_im"], atol=1e-7)
    with pytest.raises(ValueError, match="action base"):
        ActionConfig("target")


def test_nan_actions_are_refused_or_contained(hum, lib):
    mdp = _mdp(hum, lib, 3)
    mdp.reset(clips=[0, 1, 2], frames=[10, 10, 10])
    before = mdp.env.qpos.copy()
    a = _pd_actions(mdp)
    bad = a.copy()
    bad[1, 4] = np.nan
    with pytest.raises(ValueError, match=r"non-finite actions for environments \[1\]"):
        mdp.step(bad)
    assert np.array_equal(mdp.env.qpos, before)  # nothing was stepped
    with pytest.raises(ValueError, match="rows"):
        mdp.step(a[:2])

    clean, contained = _mdp(hum, lib, 3), _mdp(hum, lib, 3, nan_actions="terminate")
    for e in (clean, contained):
        e.reset(clips=[0, 1, 2], frames=[10, 10, 10])
    o1, g1, r1, t1, _, _ = clean.step(a)
    o2, g2, r2, t2, _, info = contained.step(bad)
    assert t2[1] and info["invalid_action"][1] and r2["r_im"][1] == 0.0
    keep = [0, 2]
    assert np.array_equal(o1[keep], o2[keep]) and np.array_equal(g1[keep], g2[keep]) and not t2[keep].any()
    assert np.isfinite(o2).all() and np.isfinite(g2).all()


def test_early_termination_and_truncation_are_distinct(hum, lib):
    mdp = _mdp(hum, lib, 2, max_episode_seconds=0.2)
    env = mdp.env
    mdp.reset(clips=[0, 0], frames=[5, 5])
    q, v = env.qpos.copy(), env.qvel.copy()
    q[1, 0] += 1.0  # env 1 teleported 1 m away from its reference
    env.set_state(np.array([1]), q[1:], v[1:])
    _, _, _, term, trunc, info = mdp.step(_pd_actions(mdp))
    assert term.tolist() == [False, True] and not trunc.any() and info["max_body_error"][1] > 0.5
    mdp.reset([0, 1], clips=[0, 0], frames=[5, 5])
    for t in range(6):
        _, _, _, term, trunc, info = mdp.step(_pd_actions(mdp))
    assert trunc.all() and not term.any() and (info["episode_steps"] == 6).all()
    # the end of the clip truncates too: one step before the goal runs out of reference frames
    n = lib.lengths[0]
    mdp.reset([0, 1], clips=[0, 0], frames=[n - 3, n - 4])
    _, _, _, term, trunc, _ = mdp.step(_pd_actions(mdp))
    assert trunc.tolist() == [True, False] and not term.any()
    with pytest.raises(ValueError, match="no step with 1 reference frames ahead"):
        mdp.reset([0], clips=[0], frames=[n - 2])
    with pytest.raises(KeyError, match="no clip named"):
        mdp.reset([0, 1], clips=["dataset-2_walk_normal_999", 0])


def test_termination_on_any_body_or_on_the_mean(hum, lib):
    """A swung arm puts the hand > 0.5 m off while the body as a whole stays: "any" ends the
    episode, "mean" (PHC's failure test) does not; a 1 m teleport ends both."""
    mdps = {k: _mdp(hum, lib, 2, termination=k) for k in ("any", "mean")}
    k = list(hum.layout.hinge_names).index("UpperArm_L_z")
    for mdp in mdps.values():
        env = mdp.env
        mdp.reset(clips=[0, 0], frames=[5, 5])
        q, v = env.qpos.copy(), env.qvel.copy()
        q[0, env.hinge_adr[k]] += 2.5
        q[1, 0] += 1.0
        env.set_state(np.array([0, 1]), q, v)
    out = {key: mdp.step(_pd_actions(mdp)) for key, mdp in mdps.items()}
    info = out["mean"][5]
    assert info["max_body_error"][0] > 0.5 > info["mean_body_error"][0] and info["mean_body_error"][1] > 0.5
    assert out["any"][3].tolist() == [True, True] and out["mean"][3].tolist() == [False, True]
    with pytest.raises(ValueError, match="termination"):
        ImitationTaskConfig(termination="median")


def test_pd_tracking_baseline_falls_but_follows_at_first(hum, lib):
    res = pd_track(hum, lib, [0, 1, 2, 3], seconds=3.0)
    assert (res["survival_s"] > 0.2).all() and (res["survival_s"] < 3.0).all()
    assert (res["mean_reward"] > 0.05).all() and res["qpos"].shape[1] == 91


# ----------------------------------------------------------------------------- discrete policies

def test_multi_categorical_log_prob_and_entropy_against_hand_values():
    pol = MultiCategoricalPolicy(2, heads=2, classes=3, hidden=())
    logits = torch.tensor([[0.0, math.log(2.0), math.log(3.0)], [0.0, 0.0, 0.0]])  # p = (1,2,3)/6 and uniform
    with torch.no_grad():
        pol.net[0].weight.zero_()
        pol.net[0].bias.copy_(logits.reshape(-1))
    x = torch.zeros(1, 2)
    a = torch.tensor([[2, 0]])
    logp, ent = pol.evaluate(x, a)
    assert logp.item() == pytest.approx(math.log(3 / 6) + math.log(1 / 3), abs=1e-6)
    p = np.array([1, 2, 3]) / 6
    assert ent.item() == pytest.approx(-(p * np.log(p)).sum() + math.log(3), abs=1e-6)
    a2, lp2 = pol.act(x, deterministic=True)
    assert a2.tolist() == [[2, 0]] and lp2.item() == pytest.approx(logp.item(), abs=1e-6)  # ties: first index
    torch.manual_seed(0)
    draws = torch.stack([pol.act(x)[0] for _ in range(3000)])[:, 0, 0]
    assert draws.dtype == torch.int64 and np.allclose(np.bincount(draws.numpy(), minlength=3) / 3000, p, atol=0.03)
    # a gradient reaches the logits through evaluate()
    logp.sum().backward()
    assert pol.net[0].bias.grad.abs().sum() > 0


def test_short_ppo_run_raises_the_return_of_a_discrete_task():
    """Two heads of 4 classes; the observation says which class each head must pick (one-hot);
    reward = number of heads right, episodes of 8 steps. Uniform play earns 0.5 per step; PPO
    through the categorical heads must do clearly better within 30 iterations."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    N, T, H, K = 32, 16, 2, 4
    ac = ActorCritic(RunningNorm(H * K), MultiCategoricalPolicy(H * K, H, K, (32,)), ValueNet(H * K, (32,)))
    ppo = PPO(ac, PPOConfig(horizon=T, lr=3e-3, epochs=4, minibatch_size=128, entropy_coef=0.01), 30)
    target = rng.integers(0, K, (N, H))
    step = np.zeros(N, dtype=np.int64)
    per_step = []
    for it in range(30):
        ro = Rollout(T, N, H * K, ac.policy.action_shape, ac.policy.action_dtype)
        assert ro.actions.dtype == torch.int64 and ro.actions.shape == (T, N, H)
        for t in range(T):
            x = torch.from_numpy(np.eye(K)[target].reshape(N, -1)).float()
            ac.norm.update(x)
            ro.x[t], ro.actions[t], ro.logp[t], ro.values[t] = ac.act(x)
            r = (ro.actions[t].numpy() == target).sum(1).astype(np.float32)
            ro.rewards[t] = torch.from_numpy(r)
            step += 1
            done = step >= 8
            ro.truncated[t] = torch.from_numpy(done)
            if done.any():
                with torch.no_grad():
                    ro.final_values[t, torch.from_numpy(done)] = ac.value(ac.norm(x[done]))
                target[done] = rng.integers(0, K, (int(done.sum()), H))
                step[done] = 0
        with torch.no_grad():
            x = torch.from_numpy(np.eye(K)[target].reshape(N, -1)).float()
            last = ac.value(ac.norm(x))
        stats = ppo.update(ro, last, it)
        per_step.append(float(ro.rewards.mean()))
    assert np.mean(per_step[:3]) < 0.8 and np.mean(per_step[-3:]) > 1.5, np.round(per_step, 2)
    assert stats["entropy"] < 2 * math.log(K)  # the heads became confident


# ----------------------------------------------------------------------------- difficulty sampling

def test_difficulty_probabilities_follow_the_formula_and_draw_failed_clips_more_often(lib):
    from motok.control.mdp.resets import sample_starts
    from motok.control.rl.sampling import DifficultySampler, SamplingConfig, clip_probabilities, failures

    usable = np.array([10.0, 30.0, 60.0])
    f = np.array([0.0, 1.0, 0.5])
    p = clip_probabilities(usable, f, 0.5)
    # (1 - b) L / sum L + b L f / sum L f = 0.5 [0.1, 0.3, 0.6] + 0.5 [0, 30, 30] / 60
    assert np.allclose(p, [0.05, 0.4, 0.55]) and p.sum() == pytest.approx(1.0)
    assert np.allclose(clip_probabilities(usable, np.zeros(3), 0.5), usable / usable.sum())  # nothing failed
    per = {"a": {"success": True, "seconds": 3.0, "clip_seconds": 3.0},
           "b": {"success": False, "seconds": 1.0, "clip_seconds": 4.0}}
    assert failures(per, ["a", "b"]).tolist() == [0.0, 0.75]

    C = len(lib)
    s = DifficultySampler(SamplingConfig(hard_fraction=0.8, every=10), np.maximum(lib.lengths - 2, 0))
    assert s.probabilities() is None and s.due(20) and not s.due(25)
    fail = np.zeros(C)
    fail[[2, 5]] = 1.0
    st = s.update(fail, 20)
    base = s.usable / s.usable.sum()
    assert st["hard_clips"] == 2 and st["hard_share"] == pytest.approx(0.8 + 0.2 * base[[2, 5]].sum())
    clips, frames = sample_starts(lib, 20000, np.random.default_rng(0), 2, s.probabilities())
    share = np.isin(clips, [2, 5]).mean()
    plain, _ = sample_starts(lib, 20000, np.random.default_rng(0), 2)
    assert share > 0.75 and share > 5 * np.isin(plain, [2, 5]).mean()
    assert (frames >= 0).all() and (frames < lib.lengths[clips] - 2).all()
    t = DifficultySampler(SamplingConfig(hard_fraction=0.8, every=10), np.maximum(lib.lengths - 2, 0))
    t.load(s.state())
    assert np.array_equal(t.probabilities(), s.probabilities()) and t.measured_at == 20
