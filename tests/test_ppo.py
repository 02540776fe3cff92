"""PPO pieces (motok.control.rl.ppo, networks) and the AMP discriminator (motok.control.rl.amp)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from motok.control.rl.amp import AMP, AMPConfig, ReplayBuffer, gradient_penalty, style_reward
from motok.control.rl.networks import ActorCritic, RunningNorm
from motok.control.rl.policies import EncoderDecoderPolicy
from motok.control.rl.ppo import PPO, PPOConfig, gae, kl_warning, learning_rate
from motok.control.rl.rollout import Rollout


pytestmark = pytest.mark.usefixtures("one_thread")


def test_gae_three_steps_with_termination_and_truncation():
    # One env: step 0 mid-episode, step 1 truncated (time limit: bootstrap from V(final obs) = 4),
    # step 2 terminated (no future at all, so the last value 9 must not leak in).
    g, lam = 0.9, 0.8
    ro = Rollout(3, 1, 2, (1,))
    ro.rewards[:, 0] = torch.tensor([1.0, 2.0, 3.0])
    ro.values[:, 0] = torch.tensor([0.5, 1.0, 1.5])
    ro.truncated[1, 0], ro.terminated[2, 0] = True, True
    ro.final_values[1, 0] = 4.0
    nv = ro.next_values(torch.tensor([9.0]))
    assert nv[:, 0].tolist() == [1.0, 4.0, 9.0]
    adv, ret = gae(ro.rewards, ro.values, nv, ro.terminated, ro.truncated, g, lam)
    d0, d1, d2 = 1 + g * 1.0 - 0.5, 2 + g * 4.0 - 1.0, 3 - 1.5  # TD errors by hand
    expected = [d0 + g * lam * d1, d1, d2]  # the recursion stops at the truncation and the termination
    assert adv[:, 0].tolist() == pytest.approx(expected)
    assert ret[:, 0].tolist() == pytest.approx([a + v for a, v in zip(expected, [0.5, 1.0, 1.5])])
    # Without episode ends it is the plain lambda-return recursion.
    adv2, _ = gae(ro.rewards, ro.values, torch.tensor([[1.0], [1.5], [9.0]]), torch.zeros(3, 1, dtype=torch.bool),
                  torch.zeros(3, 1, dtype=torch.bool), g, lam)
    e2 = 3 + g * 9.0 - 1.5
    e1 = 2 + g * 1.5 - 1.0 + g * lam * e2
    assert adv2[:, 0].tolist() == pytest.approx([d0 + g * lam * e1, e1, e2])


class _Constant(torch.nn.Module):
    """A policy whose log-probability of every action, or a critic whose value of every state, is
    one parameter: the update's losses then have gradients by hand."""

    def __init__(self, value: float):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(value))

    def evaluate(self, x, a):
        return self.w.expand(len(x)), torch.zeros(len(x))

    def forward(self, x):
        return self.w.expand(len(x))


def _one_step_update(logp: float, old_logp: float, reward: float, v: float, old_v: float,
                     **cfg) -> tuple[PPO, dict]:
    """One PPO update on a one-step rollout of two alike environments (one minibatch) whose advantage
    is ``reward - old_v`` (gamma 0, the advantage not normalised), with the policy's log-probability
    ``logp`` and the critic's value ``v``."""
    ac = ActorCritic(RunningNorm(1), _Constant(logp), _Constant(v))
    ppo = PPO(ac, PPOConfig(epochs=1, minibatch_size=2, gamma=0.0, norm_adv=False, max_grad_norm=1e9, **cfg), 1)
    ro = Rollout(1, 2, 1, (1,))
    ro.logp[:], ro.rewards[:], ro.values[:] = old_logp, reward, old_v
    return ppo, ppo.update(ro, torch.zeros(2), 0)


@pytest.mark.parametrize("ratio,adv,zero", [(1.5, 1.0, True), (0.5, -1.0, True), (1.1, 1.0, False),
                                            (0.5, 1.0, False), (1.5, -1.0, False), (0.9, -1.0, False)])
def test_clipped_objective_gradient_is_zero_outside_the_clip_range(ratio, adv, zero):
    old = 0.3
    ppo, st = _one_step_update(old + math.log(ratio), old, adv, 0.0, 0.0, clip=0.2)
    grad = ppo.ac.policy.w.grad.item()
    if zero:  # left the trust region in the direction the advantage favours: no more push
        assert grad == 0.0
        assert st["policy_loss"] == pytest.approx(-adv * (1.2 if adv > 0 else 0.8))
    else:  # d(-rho A)/d logp = -rho A
        assert grad == pytest.approx(-ratio * adv, rel=1e-5)
    assert st["clip_frac"] == float(abs(ratio - 1) > 0.2)
    assert st["approx_kl"] == pytest.approx((ratio - 1) - math.log(ratio), rel=1e-4, abs=1e-7)


def test_value_loss_clipping_and_lr_schedules():
    # V = 2 against a return of 3, where the rollout's value was 1: 0.5 unclipped; clipped to
    # 1 + 0.2, the pessimistic of the two
    assert _one_step_update(0.0, 0.0, 3.0, 2.0, 1.0)[1]["value_loss"] == pytest.approx(0.5)
    clipped = _one_step_update(0.0, 0.0, 3.0, 2.0, 1.0, clip_value=True, value_clip=0.2)[1]["value_loss"]
    assert clipped == pytest.approx(0.5 * (3.0 - 1.2) ** 2)
    c = PPOConfig(lr=1.0, lr_min=0.1)
    assert learning_rate(c, 5, 10) == 1.0
    c.lr_schedule = "linear"
    assert learning_rate(c, 0, 10) == 1.0 and learning_rate(c, 5, 10) == pytest.approx(0.55)
    c.lr_schedule = "cosine"
    assert learning_rate(c, 5, 10) == pytest.approx(0.55) and learning_rate(c, 10, 10) == pytest.approx(0.1)
    with pytest.raises(ValueError):
        learning_rate(PPOConfig(lr_schedule="step"), 0, 1)


def test_the_kl_warning_reads_the_median_of_the_window():
    assert kl_warning([]) is None
    assert kl_warning([0.03, 0.05, 0.04], threshold=0.3) is None
    assert kl_warning([0.03, 5.0, 0.04], threshold=0.3) is None  # one wild update is not a trend
    msg = kl_warning([0.5, 0.03, 0.8], threshold=0.3)
    assert "median 0.5 nats" in msg and "last 3 iterations" in msg and "ppo.lr" in msg


def test_running_norm_matches_batch_statistics_and_is_saved():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, size=(1000, 4))
    n = RunningNorm(4, clip=100.0)
    for chunk in np.array_split(x, 7):
        n.update(torch.from_numpy(chunk))
    assert n.mean.numpy() == pytest.approx(x.mean(0)) and n.var.numpy() == pytest.approx(x.var(0))
    y = n(torch.from_numpy(x))
    assert y.mean(0).abs().max() < 1e-6 and (y.std(0) - 1).abs().max() < 1e-2
    assert {"mean", "var", "count"} <= set(n.state_dict())


def test_encoder_decoder_policy_shapes_and_std():
    p = EncoderDecoderPolicy(5, 7, 3, latent_dim=4, encoder=(8,), decoder=(8,), log_std=-1.0, learn_log_std=False)
    x = torch.randn(6, 12)
    assert p.encode(x).shape == (6, 4) and p.mean(x).shape == (6, 3)
    assert torch.allclose(p.dist(x).stddev, torch.full((6, 3), math.exp(-1.0)))
    assert "log_std" not in dict(p.named_parameters())  # fixed std: a buffer, not trained
    # The decoder sees s and the latent only: changing the goal changes actions through z alone.
    assert p.decoder[0].in_features == 5 + 4


def test_gradient_penalty_of_a_linear_discriminator():
    w, b = torch.tensor([1.0, -2.0, 3.0]), 0.5
    x = torch.randn(16, 3)
    gp = gradient_penalty(lambda z: z @ w + b, x)
    assert gp.item() == pytest.approx(float(w @ w))  # grad of w.x + b is w everywhere
    # Quadratic f = |x|^2: gradient 2x, penalty mean 4|x|^2.
    quad = gradient_penalty(lambda z: (z**2).sum(-1), x).item()
    assert quad == pytest.approx(float((4 * (x**2).sum(-1)).mean()), rel=1e-5)


def test_style_reward_convention():
    # D = sigmoid(logit) = 1 for reference data: r = -5 log(1 - D).
    r = style_reward(torch.tensor([0.0, 2.0, -2.0, 50.0]), 5.0)
    d = torch.sigmoid(torch.tensor([0.0, 2.0, -2.0]))
    assert r[:3].tolist() == pytest.approx((-5 * torch.log(1 - d)).tolist(), rel=1e-5)
    assert r[0].item() == pytest.approx(5 * math.log(2))
    assert r[3].item() == pytest.approx(-5 * math.log(1e-4))  # floored: a confident D gives a bounded reward


def test_discriminator_learns_reference_is_one_and_replay_buffer_wraps():
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    ref = rng.normal(size=(400, 6)).cumsum(0) * 0.05  # smooth "clips": consecutive frames are close
    amp = AMP(AMPConfig(hidden=[32, 32], batch_size=64, updates=20, lr=3e-3, replay_size=100), ref,
              np.array([0, 200, 400]))
    assert 199 not in amp.ref_idx and 399 not in amp.ref_idx  # no transition spans two clips
    s = torch.from_numpy(rng.normal(size=(300, 6))).float()
    s2 = s + torch.from_numpy(rng.normal(size=(300, 6))).float()  # jerky transitions: unlike the data
    amp.update(s, s2, rng)
    rs, rs2 = amp.reference_batch(200, rng)
    assert amp.reward(rs, rs2).mean() > amp.reward(s, s2).mean() + 0.5
    st = amp.update(s, s2, rng)
    assert st["disc_ref"] > 0.5 > st["disc_pol"]
    assert amp.replay.size == 100  # 600 added into 100 slots
    buf = ReplayBuffer(4, 1)
    buf.add(torch.arange(6.0)[:, None], torch.arange(6.0)[:, None])
    assert sorted(buf.data[:, 0, 0].tolist()) == [2.0, 3.0, 4.0, 5.0] and buf.pos == 2


class InvertedPointMass:
    """The smallest 'stand still' task: a point on an unstable slope (acceleration +9 x) must be
    held at 0 by a force; r = exp(-x^2) per step, terminated beyond |x| = 1, truncated after 40
    steps. Zero force falls off within about 15 steps; a = -k x - c v stands forever."""

    def __init__(self, n, seed=0):
        self.n, self.rng, self.dt = n, np.random.default_rng(seed), 0.05
        self.x, self.v, self.t = np.zeros(n), np.zeros(n), np.zeros(n, dtype=int)

    def reset(self, ids):
        self.x[ids], self.v[ids], self.t[ids] = self.rng.uniform(-0.2, 0.2, len(ids)), 0.0, 0

    def obs(self):
        return np.stack([self.x, self.v], 1)

    def step(self, a):
        self.v += self.dt * (9.0 * self.x + 3.0 * np.clip(a[:, 0], -3, 3))
        self.x += self.dt * self.v
        self.t += 1
        term = np.abs(self.x) > 1.0
        return np.exp(-self.x**2), term, (self.t >= 40) & ~term


def test_short_ppo_run_raises_the_return_of_a_stand_still_task():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny networks: extra threads only fight the other jobs
    try:
        _stand_still()
    finally:
        torch.set_num_threads(threads)


def _stand_still():
    from motok.control.rl.networks import ActorCritic, ValueNet
    from motok.control.rl.policies import MLPPolicy
    from motok.control.rl.ppo import PPO

    torch.manual_seed(0)
    N, T = 16, 40
    env = InvertedPointMass(N)
    env.reset(np.arange(N))
    ac = ActorCritic(RunningNorm(2), MLPPolicy(2, 1, (32, 32), log_std=-0.5, learn_log_std=True), ValueNet(2, (32, 32)))
    ppo = PPO(ac, PPOConfig(horizon=T, lr=3e-3, epochs=4, minibatch_size=160), 20)
    lengths, ep = [], np.zeros(N)
    for it in range(20):
        ro, done_len = Rollout(T, N, 2, (1,)), []
        for t in range(T):
            x = torch.as_tensor(env.obs(), dtype=torch.float32)
            ac.norm.update(x)
            ro.x[t], ro.actions[t], ro.logp[t], ro.values[t] = ac.act(x)
            r, term, trunc = env.step(ro.actions[t].numpy())
            ro.rewards[t] = torch.from_numpy(r).float()
            ro.terminated[t], ro.truncated[t] = torch.from_numpy(term), torch.from_numpy(trunc)
            if trunc.any():  # bootstrap from the final observation, before the reset
                with torch.no_grad():
                    final = torch.as_tensor(env.obs()[trunc]).float()
                    ro.final_values[t, torch.from_numpy(trunc)] = ac.value(ac.norm(final))
            ep += 1
            done = term | trunc
            done_len += ep[done].tolist()
            ep[done] = 0
            env.reset(np.flatnonzero(done))
        with torch.no_grad():
            last = ac.value(ac.norm(torch.as_tensor(env.obs(), dtype=torch.float32)))
        ppo.update(ro, last, it)
        lengths.append(np.mean(done_len) if done_len else T)
    assert np.mean(lengths[-5:]) > 1.5 * np.mean(lengths[:5]), np.round(lengths, 1)
