"""The physics terms written once for numpy and torch (motok/arrays.py): given torch tensors each
term gives the numbers it gives on numpy arrays, so the on-device rollout (env.on_device) computes
what the host rollout computes. Runs without MuJoCo Warp: the tensors live on the CPU here."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from motok.arrays import copy, like, xp
from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.resets import reference_bodies, reference_state, sample_starts
from motok.control.mdp.rewards import ImitationConfig, imitation_errors, imitation_reward
from motok.control.mdp.terminations import body_distances, end_of_step, tracking_failure
from motok.sim.obs import Bodies, TreeKinematics, observation

pytestmark = pytest.mark.usefixtures("one_thread")


def tensors(b: Bodies) -> Bodies:
    f = lambda a: torch.as_tensor(a)  # noqa: E731  (float64: the comparison is of formulas, not precision)
    return Bodies(f(b.pos), f(b.vel), f(b.angvel), rot=f(b.rot), quat=f(b.quat))


@pytest.fixture(scope="module")
def states(hum, lib):
    """Simulated states: reference frames perturbed by noise (so goals and errors are not zero)
    through numpy forward kinematics, and their reference one frame ahead."""
    rng = np.random.default_rng(0)
    g = rng.integers(0, lib.starts[-1] - 2, 16)
    qpos, qvel = lib.qpos[g].copy(), lib.qvel[g].copy()
    qpos[:, 7:] += rng.normal(0, 0.1, qpos[:, 7:].shape)
    qpos[:, :3] += rng.normal(0, 0.05, (16, 3))
    qvel += rng.normal(0, 0.3, qvel.shape)
    return qpos, qvel, TreeKinematics(hum)(qpos, qvel), g + 1


def test_the_namespace_follows_the_inputs():
    a, t = np.ones(3), torch.ones(3, dtype=torch.float64)
    assert xp(a) is np and xp(t) is torch and xp(a, t) is torch
    c = copy(t)
    c[0] = 5.0
    assert t[0] == 1.0 and copy(a) is not a
    v = like(t.to(torch.float32), [1.5, 2.5])
    assert v.dtype == torch.float32 and v.device == t.device
    assert like(t, np.arange(3)).dtype == torch.int64 and like(a, [1, 2]).dtype.kind == "i"


def test_every_term_gives_the_numpy_numbers_on_tensors(hum, lib, states):
    qpos, qvel, sim, g = states
    ee = list(hum.skeleton.end_effectors)
    simt = tensors(sim)
    obs = observation(qpos, qvel, sim, ee)
    obs_t = observation(torch.as_tensor(qpos), torch.as_tensor(qvel), simt, ee)
    assert isinstance(obs_t, torch.Tensor) and np.allclose(obs_t.numpy(), obs, atol=1e-12)
    # Eq. 9 with K = 2 frames ahead, clamped at the end of the clip.
    clips = np.searchsorted(lib.starts, g, side="right") - 1
    frames = g - lib.starts[clips]
    ahead = frames[:, None] + np.arange(1, 3)
    ref = reference_bodies(lib, clips[:, None], ahead)
    libt = lib.to("cpu", torch.float64)
    ref_t = reference_bodies(libt, torch.as_tensor(clips)[:, None], torch.as_tensor(ahead))
    goal = imitation_goal(sim, ref)
    goal_t = imitation_goal(simt, ref_t)
    assert goal.shape == (16, 2 * len(hum.body_ids) * 15) and np.abs(goal).max() > 0.01
    assert np.allclose(goal_t.numpy(), goal, atol=1e-12)
    # Eq. 10 and the terminations against the frame reached.
    r0, r0t = ref.take((slice(None), 0)), ref_t.take((slice(None), 0))
    rows = lib.frame_index(clips, frames + 1)
    rows_t = libt.frame_index(torch.as_tensor(clips), torch.as_tensor(frames + 1))
    assert np.array_equal(rows_t.numpy(), rows)
    args = (sim.pos, r0.pos, qpos[:, 7:], lib.qpos[rows, 7:], qvel[:, 6:], lib.qvel[rows, 6:], ee)
    args_t = (simt.pos, r0t.pos, torch.as_tensor(qpos[:, 7:]), libt.qpos[rows_t, 7:], torch.as_tensor(qvel[:, 6:]),
              libt.qvel[rows_t, 6:], ee)
    rew, rew_t = imitation_reward(imitation_errors(*args), ImitationConfig()), \
        imitation_reward(imitation_errors(*args_t), ImitationConfig())
    assert set(rew) == set(rew_t) and all(np.allclose(rew_t[k].numpy(), rew[k], rtol=1e-10) for k in rew)
    assert 0.0 < rew["r_im"].max() < 1.0
    dist, dist_t = body_distances(sim, r0), body_distances(simt, r0t)
    assert np.allclose(dist_t.numpy(), dist, atol=1e-12)
    for mode, th in (("mean", np.median(dist.mean(-1))), ("any", np.median(dist.max(-1)))):
        fell, fell_t = tracking_failure(dist, mode, th), tracking_failure(dist_t, mode, th)
        assert np.array_equal(fell_t.numpy(), fell) and 0 < fell.sum() < 16  # the threshold splits the batch
    bad = np.arange(16) % 5 == 0
    steps, limit = np.arange(16), np.full(16, 8)
    out = end_of_step(rew, fell, bad, np.zeros(16, bool), steps, limit)
    out_t = end_of_step(rew_t, fell_t, torch.as_tensor(bad), torch.zeros(16, dtype=torch.bool),
                        torch.as_tensor(steps), torch.as_tensor(limit))
    assert (out_t[0]["r_im"].numpy()[bad] == 0).all()
    assert np.allclose(out_t[0]["r_im"].numpy(), out[0]["r_im"]) and np.array_equal(out_t[1].numpy(), out[1])
    assert np.array_equal(out_t[2].numpy(), out[2]) and out[2].any()


def test_reference_states_and_starts_on_tensors(lib):
    """Reset states equal on both; torch starts come from a torch.Generator, reproducibly, inside
    the usable frames, with clip probabilities obeyed."""
    libt = lib.to("cpu", torch.float64)
    assert np.array_equal(libt.lengths.numpy(), lib.lengths)
    clips, frames = np.array([0, 3, 5]), np.array([0, 10, 2])
    q, v = reference_state(lib, clips, frames)
    qt, vt = reference_state(libt, torch.as_tensor(clips), torch.as_tensor(frames))
    assert np.allclose(qt.numpy(), q) and np.allclose(vt.numpy(), v)
    assert (q[:, 2] >= lib.qpos[lib.starts[clips] + frames, 2]).all()
    draw = lambda seed, p=None: sample_starts(libt, 500, torch.Generator().manual_seed(seed), 3, p)  # noqa: E731
    c, f = draw(0)
    assert torch.equal(c, draw(0)[0]) and not torch.equal(c, draw(1)[0])
    assert (f >= 0).all() and (f < libt.lengths[c] - 3).all()
    # Length-proportional by default: 20,000 draws within 5 standard errors of the usable lengths' shares.
    many = sample_starts(libt, 20000, torch.Generator().manual_seed(2), 3)[0].numpy()
    share, p = np.bincount(many, minlength=len(lib)) / 20000, (lib.lengths - 3) / (lib.lengths - 3).sum()
    assert np.abs(share - p).max() < 5 * np.sqrt(p.max() / 20000)
    p = torch.zeros(len(lib))
    p[[2, 7]] = 0.5
    c, _ = draw(0, p)
    assert set(c.tolist()) == {2, 7}
