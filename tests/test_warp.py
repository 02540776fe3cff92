"""The MuJoCo Warp stepper (motok/sim/warp_stepper.py) on Warp's CPU device, against the MuJoCo
stepper from the same states and controls: standing, PD tracking of walks, resets, divergence,
NaN containment, and a short expert training through ``env.backend: warp``.

MuJoCo Warp is optional (``pip install motok[gpu]``); without it every test here but the one
that checks the error message is skipped. The first run compiles Warp's kernels for the CPU (about
a minute, cached in Warp's kernel cache for the next runs)."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import numpy as np
import pytest

from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.steppers import make_stepper
from conftest import require_module

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def warp():
    require_module("mujoco_warp", "MuJoCo Warp is not installed (pip install 'motok[gpu]'; .ci/run installs it)")
    return "warp"


def pair(hum, n):
    """A MuJoCo (batch) and a Warp stepper of ``n`` environments."""
    return make_stepper("batch", hum, n, hum.substeps, 1), make_stepper("auto", hum, n, hum.substeps, 1, backend="warp")


def tracking_targets(hum, lib, rows):
    """Plain PD tracking with the velocity lead (action base ``reference``, zero residual)."""
    m = hum.model
    lead = -m.actuator_biasprm[:, 2] / m.actuator_gainprm[:, 0]
    q = lib.qpos[rows][:, hum.hinge_qpos_adr] + lead * lib.qvel[rows][:, m.jnt_dofadr[m.actuator_trnid[:, 0]]]
    return np.clip(q, m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1])


def test_standing_agrees_with_mujoco(hum, warp):
    """The rest pose held by PD targets 0 for 30 control steps (1 s): float32 against float64
    agree to micrometres (measured 3 um), since nothing chaotic happens; 0.5 mm is the bound."""
    a, w = pair(hum, 2)
    ctrl = np.zeros((2, hum.model.nu))
    for t in range(30):
        assert not a.step(ctrl).any() and not w.step(ctrl).any()
        ba, bw = a.bodies(), w.bodies()
        assert np.abs(ba.pos - bw.pos).max() < 5e-4, t
    assert np.abs(ba.vel - bw.vel).max() < 5e-3 and np.abs(ba.rot - bw.rot).max() < 1e-3
    assert np.abs(a.qpos - w.qpos).max() < 1e-3 and w.overflows == 0


def test_walk_tracking_agrees_with_mujoco(hum, lib, warp):
    """PD tracking from frame 0 of every walk clip for 30 control steps (1 s; the character falls
    after about 0.4 s, docs/sim.md). The two engines agree to float32 round-off (micrometres) until
    a contact event that float32 and the two collision codes decide differently: MuJoCo's box-box
    collider returns up to 8 points where MJWarp's convex one returns fewer (a foot stepping on the
    other foot's toes: 5 against 2), and a contact that appears a substep earlier in one engine.
    From then on the difference grows as chaotically as between two timesteps (docs/sim.md).
    Stated bounds (measured on the 24 walks: 23 below 1 mm for 10 steps, the median of the largest
    body difference 0.2 mm at step 30): for the first 10 steps (0.33 s, before the falls) the mean
    body difference is below 1 mm in three clips of four and below 5 cm in all; over the 30 steps
    the median over clips of the largest body difference stays below 5 mm. Float32 itself costs
    about 1e-7 relative (0.1 um on a 1 m position) per operation; the bounds are set by the
    contact events above, not by round-off."""
    n = len(lib.names)
    rows = lib.frame_index(np.arange(n), np.zeros(n, dtype=int))
    a, w = pair(hum, n)
    ids = np.arange(n)
    for s in (a, w):
        s.set_state(ids, lib.qpos[rows], lib.qvel[rows])
    assert np.abs(a.bodies().pos - w.bodies().pos).max() < 1e-6  # float32 kinematics of the same state
    worst = np.zeros((30, n))
    mean = np.zeros((30, n))
    for t in range(30):
        ctrl = tracking_targets(hum, lib, lib.frame_index(ids, np.full(n, t + 1)))
        assert not a.step(ctrl).any() and not w.step(ctrl).any()
        err = np.linalg.norm(a.bodies().pos - w.bodies().pos, axis=-1)
        worst[t], mean[t] = err.max(1), err.mean(1)
    print("median over clips of the largest body difference (mm) per step:", np.round(np.median(worst, 1) * 1e3, 3))
    print("clips with mean < 1 mm over the first 10 steps:", (mean[:10].max(0) < 1e-3).sum(), "of", n)
    assert (mean[:10].max(0) < 1e-3).mean() >= 0.75 and mean[:10].max() < 0.05
    assert np.median(worst, 1).max() < 5e-3 and w.overflows == 0


def test_resets_divergence_and_nans_behave_as_with_mujoco(hum, lib, warp):
    """set_state of a subset leaves the others alone and gives the same body states as MuJoCo;
    a blown-up world is reported diverged by both and comes back at qpos0, the others stepping as
    if nothing happened; a NaN state is reset by both."""
    g = np.array([10, 500, 2000, 3000])
    a, w = pair(hum, 4)
    for s in (a, w):
        s.set_state(np.arange(4), lib.qpos[g], lib.qvel[g])
    ctrl = tracking_targets(hum, lib, g + 1)
    a.step(ctrl), w.step(ctrl)
    kept = w.qpos[[0, 2, 3]].copy()
    for s in (a, w):  # a reset of one environment
        s.set_state([1], lib.qpos[g[1] + 7:g[1] + 8], lib.qvel[g[1] + 7:g[1] + 8])
    assert np.array_equal(w.qpos[[0, 2, 3]], kept) and np.abs(w.qpos[1] - lib.qpos[g[1] + 7]).max() < 1e-6
    ba, bw = a.bodies([1]), w.bodies([1])
    assert np.abs(ba.pos - bw.pos).max() < 1e-5 and np.abs(ba.vel - bw.vel).max() < 1e-4
    assert np.abs(w.bodies().pos[[0, 2, 3]] - w.bodies([0, 2, 3]).pos).max() == 0.0
    # Worlds spun at 1e6 and 1e9 rad/s: both engines blow up in the first substep, reset the world
    # to qpos0 at rest and report it; the healthy worlds step as they would without them.
    v = lib.qvel[g[:2]].copy()
    v[:, 10] = [1e6, 1e9]
    for s in (a, w):
        s.set_state([2, 3], lib.qpos[g[:2]], v)
    ref = make_stepper("auto", hum, 4, hum.substeps, 1, backend="warp")  # the same worlds without the bad two
    ref.set_state(np.arange(4), w.qpos, w.qvel)
    ref.set_state([2, 3], lib.qpos[g[:2]], lib.qvel[g[:2]])
    da, dw, dr = a.step(ctrl), w.step(ctrl), ref.step(ctrl)
    assert da.tolist() == dw.tolist() == [False, False, True, True] and not dr.any()
    assert np.isfinite(w.qpos).all() and np.abs(w.qpos[2:, :3] - hum.model.qpos0[:3]).max() < 0.01  # root at rest
    # the same restart at rest and unactuated; C MuJoCo resets before integrating its first substep,
    # Warp after it, so Warp's reset worlds run one substep less (4 mm on a hinge, 0.1 mm at the root)
    assert np.abs(a.qpos[2:] - w.qpos[2:]).max() < 1e-2 and np.abs(a.qpos[2:, :3] - w.qpos[2:, :3]).max() < 1e-3
    assert np.abs(w.qpos[:2] - ref.qpos[:2]).max() < 1e-5  # the healthy worlds stepped as without them
    # A NaN state (a caller's bug): mujoco.batch resets it to qpos0 in set_state without a report; so does Warp.
    q = lib.qpos[g[:1]].copy()
    q[0, 9] = np.nan
    for s in (a, w):
        s.set_state([3], q, lib.qvel[g[:1]])
    assert np.isfinite(w.qpos).all() and np.abs(w.qpos[3] - a.qpos[3]).max() < 1e-6
    da, dw = a.step(ctrl), w.step(ctrl)
    assert not da.any() and not dw.any() and np.abs(a.qpos[3] - w.qpos[3]).max() < 1e-3
    assert not w.step(ctrl)[2:].any()  # the reset worlds step normally again


def test_env_backend_selection_and_nan_actions(hum, lib, warp):
    env = HumanoidEnv(hum, SimConfig(num_envs=3, backend="warp", nan_actions="terminate"))
    assert type(env.stepper).__name__ == "WarpStepper" and env.obs_dim == 102
    ref = HumanoidEnv(hum, SimConfig(num_envs=3, backend="warp"))
    g = np.array([10, 500, 2000])
    for e in (env, ref):
        e.set_state(np.arange(3), lib.qpos[g], lib.qvel[g])
    bad = lib.qpos[g + 1][:, env.hinge_adr].copy()
    held = env.qpos[2, env.hinge_adr].copy()
    good = bad.copy()
    bad[2, 0] = np.nan
    diverged, invalid = env.step(bad)
    ref.step(good)
    assert invalid.tolist() == [False, False, True] and not diverged.any() and np.isfinite(env.qpos).all()
    assert np.abs(env.qpos[2, env.hinge_adr] - held).max() < 0.2  # held its pose
    assert np.abs(env.observation()[:2] - ref.observation()[:2]).max() < 1e-5  # the others as without it
    with pytest.raises(ValueError, match="non-finite"):
        HumanoidEnv(hum, SimConfig(num_envs=3, backend="warp")).step(bad)
    with pytest.raises(UserError, match="device 'cuda'"):  # no GPU here
        HumanoidEnv(hum, SimConfig(num_envs=1, backend="warp", device="cuda"))


def test_the_on_device_path_steps_and_observes_without_the_host(hum, lib, warp):
    """step_tensor takes and returns device tensors; Eq. 7 (motok.sim.obs.observation, the same
    function as on the host) of bodies_tensor() equals the numpy observation of the same state
    (float32 arithmetic against float64: 1e-5)."""
    import torch

    from motok.sim.obs import observation

    g = np.array([10, 500, 2000])
    w = make_stepper("auto", hum, 3, hum.substeps, 1, backend="warp")
    w.set_state(np.arange(3), lib.qpos[g], lib.qvel[g])
    ctrl = torch.as_tensor(tracking_targets(hum, lib, g + 1), dtype=torch.float32)
    bad = w.step_tensor(ctrl)
    assert isinstance(bad, torch.Tensor) and bad.dtype == torch.bool and not bad.any()
    ee = list(hum.skeleton.end_effectors)
    b = w.bodies_tensor()
    assert b.pos.dtype == torch.float32 and b.rot.shape == (3, len(hum.body_ids), 3, 3)
    mine = observation(w.qpos_t, w.qvel_t, b, ee)
    assert isinstance(mine, torch.Tensor)
    w._sync()  # the host mirrors, for the numpy reference only
    ref = observation(w.qpos, w.qvel, w.bodies(), ee)
    assert mine.shape == ref.shape == (3, 102) and np.abs(mine.numpy() - ref).max() < 1e-5


def device_pair(hum, lib, n, target_filter=1.0):
    """The imitation MDP of ``n`` environments on Warp twice: host arrays, and on the device."""
    from motok.control.expert.train import imitation_mdp
    from motok.control.mdp.actions import ActionConfig
    from motok.control.tasks.imitation import ImitationTaskConfig

    tc, ac = ImitationTaskConfig(termination="mean"), ActionConfig(base="reference")
    sim = SimConfig(num_envs=n, nthread=1, backend="warp", target_filter=target_filter)
    return (imitation_mdp(hum, lib, sim, tc, ac, 0),
            imitation_mdp(hum, lib, replace(sim, on_device=True), tc, ac, 0))


@pytest.mark.parametrize("target_filter", [1.0, 0.5])
def test_the_on_device_imitation_mdp_equals_the_host_one(hum, lib, warp, target_filter):
    """env.on_device: state, observation (Eq. 7), goal (Eq. 9), action map, reward (Eq. 10) and
    termination computed in torch where the state lives give the host path's numbers from the same
    starts and actions: the two differ by float32 against float64 arithmetic on the same float32
    physics (measured 1e-5 after 20 steps; bounds 1e-3 and 1e-4), and the same steps end; the PD
    target filter too."""
    import torch

    host, dev = device_pair(hum, lib, 3, target_filter)
    starts = dict(clips=[0, 1, 2], frames=[0, 5, 30])
    (oh, gh), (od, gd) = host.reset(**starts), dev.reset(**starts)
    assert isinstance(od, torch.Tensor) and od.dtype == torch.float32 and np.abs(od.numpy() - oh).max() < 1e-5
    rng = np.random.default_rng(0)
    for t in range(20):
        a = rng.normal(0.0, 0.05, (3, host.action_dim))
        oh, gh, rh, th, trh, ih = host.step(a)
        od, gd, rd, td, trd, id_ = dev.step(torch.as_tensor(a, dtype=torch.float32))
        assert all(isinstance(x, torch.Tensor) for x in (od, gd, rd["r_im"], td, trd, id_["max_body_error"]))
        assert np.abs(od.numpy() - oh).max() < 1e-3 and np.abs(gd.numpy() - gh).max() < 1e-3, t
        assert np.abs(rd["r_im"].numpy() - rh["r_im"]).max() < 1e-4, t
        assert np.array_equal(td.numpy(), th) and np.array_equal(trd.numpy(), trh), t
        assert np.array_equal(id_["frame"].numpy(), ih["frame"])
        if (th | trh).any():
            break
    assert t >= 5  # the comparison covered several steps of tracking


def test_on_device_starts_are_drawn_on_the_device(hum, lib, warp):
    """Random starts come from the task's torch.Generator: reproducible from its seed, every frame
    leaves the goal's frames ahead, and difficulty probabilities (clip_p) are obeyed."""
    import torch

    _, dev = device_pair(hum, lib, 64)
    dev.reset()
    t = dev.task
    first = (t.clip.clone(), t.frame.clone())
    assert t.clip.device == t.frame.device == dev.env.qpos.device
    L = t._host_lengths
    c, f = t.clip.numpy(), t.frame.numpy()
    assert (f >= 0).all() and (f + t.cfg.goal_frames + 2 <= L[c]).all() and len(set(c.tolist())) > 3
    assert (t.limit.numpy() == np.minimum(t.max_steps, L[c] - 1 - f - t.cfg.goal_frames)).all()
    _, again = device_pair(hum, lib, 64)
    again.reset()
    assert torch.equal(again.task.clip, first[0]) and torch.equal(again.task.frame, first[1])
    p = np.zeros(len(lib))
    p[3] = 1.0
    t.clip_p = p
    dev.reset(torch.arange(10))
    assert (t.clip[:10] == 3).all() and torch.equal(t.clip[10:], first[0][10:])
    obs = dev.env.observation()
    assert torch.isfinite(obs).all() and obs.shape == (64, dev.obs_dim)


def device_expert_cfg(iterations: int = 4):
    from motok.control.expert.model import ExpertConfig

    cfg = ExpertConfig(seed=0, iterations=iterations, save_every=2)
    cfg.env.num_envs, cfg.env.nthread, cfg.env.backend, cfg.env.on_device = 4, 1, "warp", True
    cfg.ppo.horizon, cfg.ppo.minibatch_size = 8, 32
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [16]
    cfg.net.latent_dim = 8
    cfg.amp.hidden, cfg.amp.batch_size, cfg.amp.updates = [16], 32, 1
    cfg.action.base, cfg.task.termination = "reference", "mean"
    cfg.sampling.hard_fraction, cfg.sampling.every, cfg.sampling.eval_batch = 0.5, 2, 4
    return cfg


def metric_rows(run, keys):
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    return [[r.get(k) for k in keys] for r in rows]


@pytest.fixture(scope="module")
def device_expert(hum, lib, small_dataset, tmp_path_factory, warp):
    """An expert trained 4 iterations with env.on_device (PPO + AMP, difficulty sampling)."""
    from motok.control.expert.train import train

    run = tmp_path_factory.mktemp("device-expert") / "a"
    out = train(device_expert_cfg(), run, hum, lib, data=small_dataset)
    assert out["iterations"] == 4 and out["samples"] == 4 * 4 * 8
    return run


def test_expert_trains_on_the_device_and_resumes_exactly(hum, lib, small_dataset, tmp_path, device_expert):
    """PPO + AMP with env.on_device: rollout buffers, networks, AMP's replay and reference
    transitions on the physics device (here Warp's CPU device); a run stopped at iteration 2 and
    resumed logs the same metrics as an uninterrupted one (the task's torch.Generator, the
    difficulty sampler and the replay buffer are saved with it)."""
    from motok.control.expert.train import train

    cfg = device_expert_cfg()
    train(cfg, tmp_path / "b", hum, lib, data=small_dataset, until=2)
    train(cfg, tmp_path / "b", hum, lib, data=small_dataset, resume=True)
    keys = ("r_im", "r_style", "policy_loss", "disc_loss", "hard_clips", "episode_return")
    rows = metric_rows(device_expert, keys)
    assert rows == metric_rows(tmp_path / "b", keys)
    assert all(np.isfinite(r[0]) and 0.0 <= r[0] <= 1.0 for r in rows)
    assert rows[1][4] is not None  # the difficulty evaluation ran (on the host) at iteration 2


def test_distillation_runs_on_the_device_and_resumes_exactly(hum, lib, tmp_path, device_expert):
    """Online distillation (DAgger) of a hybrid prior with env.on_device: the student, the frozen
    expert, the batch and the expert's labels on the physics device; resumed exactly; the bundle
    loads on the host like any prior."""
    from motok.control.priors.distill import train
    from motok.control.priors.model import DistillConfig, PriorConfig, load_prior

    cfg = DistillConfig(seed=0, iterations=4, save_every=2, horizon=8, epochs=2, minibatch_size=32, action_noise=0.05)
    cfg.env = replace(cfg.env, num_envs=4, nthread=1, backend="warp", on_device=True)
    cfg.task.termination = "mean"
    cfg.prior = PriorConfig(kind="hybrid", latent_dim=8, num_codebooks=2, codebook_size=16, posterior_hidden=[16],
                            prior_hidden=[16], decoder_hidden=[16])
    train(cfg, tmp_path / "a", device_expert, lib)
    train(cfg, tmp_path / "b", device_expert, lib, until=2)
    train(cfg, tmp_path / "b", device_expert, lib, resume=True)
    keys = ("action_loss", "commit_loss", "mm_loss", "rollout_action_err", "code_usage", "r_im")
    rows = metric_rows(tmp_path / "a", keys)
    assert rows == metric_rows(tmp_path / "b", keys) and all(v is not None and np.isfinite(v) for v in rows[-1])
    _, _, model, _ = load_prior(tmp_path / "b")
    assert next(model.parameters()).device.type == "cpu"


def host_and_device(hum, lib, task_cls, cfg, base: str, n: int = 3):
    """A task's MDP on Warp twice, with residual PD targets on ``base``: host arrays, and on the device."""
    import torch
    from functools import partial

    from motok.control.mdp.actions import ActionConfig, pd_targets
    from motok.control.mdp.task_env import TaskEnv

    out = []
    for on in (False, True):
        env = HumanoidEnv(hum, SimConfig(num_envs=n, nthread=1, backend="warp", on_device=on))
        lb, rng = (lib.to("cpu"), torch.Generator().manual_seed(0)) if on else (lib, np.random.default_rng(0))
        out.append(TaskEnv(env, task_cls(cfg, env, lb, rng), partial(pd_targets, ActionConfig(base))))
    return out


def test_on_device_navigation_equals_the_host_one(hum, lib, warp):
    """The navigation task (Eq. 15 goal, Eq. 16 reward, head-fall test, target clock) on device
    tensors gives the host numbers from the same starts, targets and actions; its target redraw
    keeps the new target only where one is due, without reading the mask on the host."""
    import torch

    from motok.control.tasks.navigation import NavigationTask, NavigationTaskConfig

    cfg = NavigationTaskConfig(retarget_seconds=0.4)  # 12 steps: the redraw happens within the test
    host, dev = host_and_device(hum, lib, NavigationTask, cfg, "current")
    for m in (host, dev):
        m.reset(clips=[0, 1, 2], frames=[0, 10, 20])
        m.task.set_targets([0, 1, 2], [[3.0, 0.0], [0.0, -4.0], [-2.0, 2.0]])
    assert np.abs(dev.task.goal().numpy() - host.task.goal()).max() < 1e-5
    rng = np.random.default_rng(1)
    for t in range(11):  # before the first redraw: the same targets on both
        a = rng.normal(0.0, 0.05, (3, host.action_dim))
        _, gh, rh, th, trh, ih = host.step(a)
        _, gd, rd, td, trd, id_ = dev.step(torch.as_tensor(a, dtype=torch.float32))
        assert np.abs(gd.numpy() - gh).max() < 1e-3 and np.abs(rd["r_task"].numpy() - rh["r_task"]).max() < 1e-4
        assert np.array_equal(td.numpy(), th) and np.array_equal(ih["target_ends"], id_["target_ends"].numpy())
    before = dev.task.target.clone()
    _, _, _, _, _, info = dev.step(torch.zeros(3, dev.action_dim))
    due = info["target_ends"] & ~(info["fell"] | info["diverged"])
    assert due.all() and not torch.equal(dev.task.target, before)  # every target was due: all redrawn
    d = torch.linalg.norm(dev.task.target - dev.env.bodies.pos[:, 0, :2], dim=-1)
    assert ((d >= cfg.min_distance - 1e-4) & (d <= cfg.max_distance + 1e-4)).all()
    assert (dev.task.target_steps == 0).all() and (dev.task.target_index == 1).all()


@pytest.mark.parametrize("name", ["inbetween", "hmd"])
def test_on_device_reference_tasks_equal_the_host_ones(name, hum, lib, warp):
    """In-betweening (Eq. 12-14: keyframe goal with the time encoding, the reference reward, the
    keyframe clock) and head tracking (head goal, head reward, head-lost test) on device tensors
    give the host numbers from the same starts, keyframes and actions; their random windows drawn
    on the device are valid (keyframes increasing, min_gap apart, inside their clips)."""
    import torch

    from motok.control.tasks.hmd import HMDTask, HMDTaskConfig
    from motok.control.tasks.inbetween import InbetweenTask, InbetweenTaskConfig

    cls, cfg = (InbetweenTask, InbetweenTaskConfig(window_seconds=1.0, min_keyframe_gap_seconds=0.2)) \
        if name == "inbetween" else (HMDTask, HMDTaskConfig(episode_seconds=1.0))
    host, dev = host_and_device(hum, lib, cls, cfg, "reference")
    given = dict(clips=[0, 1, 2], frames=[0, 10, 20])
    if name == "inbetween":
        given["keyframes"] = [[0, 8, 16, 29]] * 3
    (_, gh), (_, gd) = host.reset(**given), dev.reset(**given)
    assert isinstance(gd, torch.Tensor) and np.abs(gd.numpy() - gh).max() < 1e-4
    rng = np.random.default_rng(1)
    hits = 0
    for t in range(12):
        a = rng.normal(0.0, 0.05, (3, host.action_dim))
        _, gh, rh, th, trh, ih = host.step(a)
        _, gd, rd, td, trd, id_ = dev.step(torch.as_tensor(a, dtype=torch.float32))
        assert np.abs(gd.numpy() - gh).max() < 1e-3 and np.abs(rd["r_task"].numpy() - rh["r_task"]).max() < 1e-4, t
        assert np.array_equal(td.numpy(), th) and np.array_equal(trd.numpy(), trh), t
        if name == "inbetween":
            assert np.array_equal(id_["keyframe_index"].numpy(), ih["keyframe_index"]), t
            hits += int((ih["keyframe_index"] == 1).sum())
    if name == "inbetween":
        assert hits == 3  # every window reached its keyframe at offset 8, on both paths
    dev.reset(torch.arange(3))
    task = dev.task
    lengths = task._host_lengths[task.clip.numpy()]
    if name == "inbetween":
        k = task.keyframes.numpy() - task.start.numpy()[:, None]
        assert (k[:, 0] == 0).all() and (k[:, -1] == task.window - 1).all() and (np.diff(k, 1) >= task.min_gap).all()
        assert (task.keyframes.numpy()[:, -1] <= lengths - 1).all()
    else:
        assert (task.frame.numpy() + task.limit.numpy() + cfg.goal_frames <= lengths - 1).all()


def test_task_learning_runs_on_the_device(hum, lib, small_dataset, tmp_path, warp):
    """PPO over a frozen prior on the navigation task with env.on_device (the prior, the
    high-level policy and the buffers on the physics device), resumed exactly; its evaluation
    runs on host arrays."""
    from tiny_runs import tiny_prior_bundle

    from motok.control.highlevel.policy import TaskTrainConfig
    from motok.control.highlevel.train import train

    prior = tiny_prior_bundle(tmp_path, hum, lib, small_dataset)
    cfg = TaskTrainConfig(seed=0, iterations=4, save_every=2, eval_every=4, eval_episodes=2)
    cfg.env = replace(cfg.env, num_envs=4, nthread=1, backend="warp", on_device=True)
    cfg.ppo.horizon, cfg.ppo.minibatch_size, cfg.ppo.epochs = 8, 16, 2
    cfg.net.policy = cfg.net.value = [16]
    train(cfg, tmp_path / "a", prior, lib)
    train(cfg, tmp_path / "b", prior, lib, until=2)
    train(cfg, tmp_path / "b", prior, lib, resume=True)
    keys = ("r_task", "policy_loss", "value_loss", "entropy", "episode_return")
    rows = metric_rows(tmp_path / "a", keys)
    assert rows == metric_rows(tmp_path / "b", keys) and all(np.isfinite(v) for v in rows[-1] if v is not None)
    last = json.loads((tmp_path / "a" / "metrics.jsonl").read_text().splitlines()[-1])
    assert any(k.startswith("eval_") for k in last)


def test_backend_errors_name_the_fix(hum, monkeypatch):
    """Runs with or without MuJoCo Warp: C MuJoCo refuses a GPU device, unknown backends are named,
    and a missing MuJoCo Warp says what to install."""
    with pytest.raises(UserError, match="needs backend 'warp'"):
        HumanoidEnv(hum, SimConfig(num_envs=1, device="cuda"))
    with pytest.raises(UserError, match="unknown backend 'jax'"):
        HumanoidEnv(hum, SimConfig(num_envs=1, backend="jax"))
    # C MuJoCo's state is host memory: on_device leaves its rollout where it is.
    env = HumanoidEnv(hum, SimConfig(num_envs=1, on_device=True))
    assert not env.on_device and isinstance(env.observation(), np.ndarray)

    monkeypatch.setitem(sys.modules, "mujoco_warp", None)  # as on a CPU-only install
    with pytest.raises(UserError, match=r"motok\[gpu\]"):
        HumanoidEnv(hum, SimConfig(num_envs=1, backend="warp"))


def test_expert_trains_through_the_warp_backend(hum, lib, small_dataset, tmp_path, warp):
    """Two PPO + AMP iterations of 4 environments on Warp's CPU device, then an evaluation through
    Warp: the recipe key reaches the stepper and is kept in the checkpoint, and a loaded run starts
    from C MuJoCo on the CPU whatever it was trained on (its evaluation's --device chooses)."""
    from motok.control.expert.model import ExpertConfig
    from motok.control.expert.evaluate import evaluate_run
    from motok.control.expert.train import train

    cfg = ExpertConfig(seed=0, iterations=2, save_every=1000)
    cfg.env.num_envs, cfg.env.nthread, cfg.env.backend = 4, 1, "warp"
    cfg.ppo.horizon, cfg.ppo.minibatch_size = 8, 32
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [16]
    cfg.net.latent_dim = 8
    cfg.amp.hidden, cfg.amp.batch_size, cfg.amp.updates = [16], 32, 1
    cfg.action.base, cfg.task.termination = "reference", "mean"
    cfg.eval_per_group = 0
    out = train(cfg, tmp_path / "run", hum, lib, data=small_dataset)
    assert out["iterations"] == 2 and out["samples"] == 2 * 4 * 8
    meta = json.loads((tmp_path / "run" / "bundle.json").read_text())
    assert meta["config"]["env"]["backend"] == "warp" and meta["config"]["env"]["device"] == "cpu"
    rows = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["r_im"]) and 0.0 < r["r_im"] <= 1.0 for r in rows)
    from motok.control.tasks.imitation import evaluate
    from motok.control.expert.model import load_expert

    loaded, _, ac, _ = load_expert(tmp_path / "run")
    assert (loaded.env.backend, loaded.env.device) == ("mujoco", "cpu")  # a loaded run: C MuJoCo unless told
    sim = replace(loaded.env, backend="warp", num_envs=2)
    res = evaluate(hum, ac, lib, sim, cfg.task, cfg.action, clips=np.array([0, 1]))
    assert res["overall"]["clips"] == 2 and all(v["seconds"] > 0 for v in res["clips"].values())
    res = evaluate_run(tmp_path / "run", clips="dataset-2_walk_normal_00[12]", device="cpu")  # C MuJoCo
    assert res["overall"]["clips"] == 2


def test_device_option_of_the_commands(small_dataset, hum, tmp_path, monkeypatch):
    """``--device`` on training and evaluation: cuda means MuJoCo Warp, refused here (no GPU, or no
    MuJoCo Warp) with the reason; anything else is named; cpu with env.backend=warp trains through
    it (when installed) and the run's eval takes it too."""
    from typer.testing import CliRunner

    from motok.cli.main import app

    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    recipe = tmp_path / "r.yaml"
    recipe.write_text("iterations: 1\nenv: {num_envs: 2, nthread: 1}\nppo: {horizon: 4, minibatch_size: 8}\n"
                      "net: {encoder: [8], decoder: [8], value: [8], latent_dim: 4}\namp: {enabled: false}\n"
                      "eval_per_group: 0\n")
    base = ["--quiet", "control", "expert", "train", "--data", str(small_dataset), "--clips",
            "dataset-2_walk_normal_00[12]", "--recipe", str(recipe), "--humanoid", str(hum.path)]
    runner = CliRunner()
    r = runner.invoke(app, base + ["-o", str(tmp_path / "gpu"), "--device", "cuda"])
    assert r.exit_code == 2 and ("no CUDA driver" in r.output or "motok[gpu]" in r.output), r.output
    r = runner.invoke(app, base + ["-o", str(tmp_path / "tpu"), "--device", "tpu"])
    assert r.exit_code == 2 and "use cpu or cuda" in r.output, r.output
    require_module("mujoco_warp", "MuJoCo Warp is not installed (pip install 'motok[gpu]'; .ci/run installs it)")
    run = tmp_path / "run"
    r = runner.invoke(app, base + ["-o", str(run), "--device", "cpu", "--set", "env.backend=warp", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads((run / "bundle.json").read_text())["config"]["env"]["backend"] == "warp"
    r = runner.invoke(app, ["--quiet", "control", "expert", "eval", "--expert", str(run), "--clips",
                            "dataset-2_walk_normal_001", "--device", "cpu", "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["overall"]["clips"] == 1, r.output
