"""The levers against sliding feet that are options of the expert (docs/sim.md "Feet"): the
action-rate term, the discriminator seeing the soles, and a higher control rate."""

from __future__ import annotations

import json
import re
from functools import partial

import numpy as np
import pytest
import torch

from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.rewards import action_rate
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.imitation import ImitationTask, ImitationTaskConfig
from motok.sim.env import HumanoidEnv, SimConfig

pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------- action rate


def test_action_rate_is_the_mean_squared_change_and_nothing_on_an_episodes_first_step():
    a_prev = np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 0.5], [0.2, 0.2, 0.2]])
    a = np.array([[0.3, 0.0, -0.3], [1.0, -1.0, 0.5], [0.0, 0.0, 0.0]])
    e = action_rate(a, a_prev, np.array([False, False, True]))
    np.testing.assert_allclose(e, [(0.09 + 0.09) / 3, 0.0, 0.0])  # the third env starts an episode
    bad = a.copy()
    bad[1, 2] = np.nan
    assert action_rate(bad, a_prev, np.zeros(3, bool))[1] == 0.0  # an invalid action: no NaN in the return
    t = action_rate(torch.tensor(a), torch.tensor(a_prev), torch.tensor([False, False, True]))
    np.testing.assert_allclose(t.numpy(), [0.06, 0.0, 0.0])


class Scripted:
    """An actor-critic whose action at step ``t`` is ``level[t] * (1 + j / A)`` on joint ``j`` (plus
    ``0.01 n`` for environment ``n``), with a real normaliser: the collector's reward is then known."""

    def __init__(self, ac, level):
        self.norm, self.policy, self.level, self.t = ac.norm, ac.policy, level, 0

    def act(self, x):
        N, A = len(x), self.policy.action_shape[0]
        a = self.level[self.t] * (1 + torch.arange(A) / A)[None] + 0.01 * torch.arange(N)[:, None]
        self.t += 1
        return self.norm(x), a.float(), torch.zeros(N), torch.zeros(N)

    def value(self, x):
        return torch.zeros(len(x))


def test_the_collector_adds_the_action_rate_term_and_forgets_the_last_episodes_action(hum, lib):
    """Episodes of 2 control steps (``max_episode_seconds`` 2/30): the term is 0 on every episode's
    first step, even where the scripted action jumps across the reset, and
    ``-mean_j (a_t - a_(t-1))^2`` inside an episode; the rollout's reward is the same run's without
    it, minus ``w_action_rate`` times it, on the same physics."""
    from motok.control.expert.model import NetConfig, build_actor_critic
    from motok.control.rl.rollout import Collector

    level = [0.0, 0.1, 0.5, 0.2, -0.1, 0.3]
    out = {}
    for w in (0.0, 2.0):
        env = HumanoidEnv(hum, SimConfig(num_envs=3))
        task = ImitationTask(ImitationTaskConfig(max_episode_seconds=2 / 30, early_termination=False), env, lib,
                             np.random.default_rng(3))
        mdp = TaskEnv(env, task, partial(pd_targets, ActionConfig(base="reference", scale=0.05)))
        torch.manual_seed(0)
        ac = Scripted(build_actor_critic(NetConfig(encoder=[8], decoder=[8], value=[8]), mdp.obs_dim, mdp.goal_dim,
                                         mdp.action_dim), level)
        col = Collector(mdp, ac, len(level), task_weight=0.5, action_rate=w)
        col.start()
        out[w] = col.collect()
    (ro, _, stats), (ro0, _, stats0) = out[2.0], out[0.0]
    done = (ro.terminated | ro.truncated).numpy()
    assert done[1].all() and done[3].all() and not done[2].any()  # episodes of exactly two steps
    A = hum.model.nu
    shape = 1 + np.arange(A) / A
    want = np.zeros((len(level), 3))
    for t in range(1, len(level)):
        if not done[t - 1, 0]:
            want[t] = np.mean(((level[t] - level[t - 1]) * shape) ** 2)
    assert want[1, 0] > 0 and want[2, 0] == 0  # a jump of 0.4 across the reset costs nothing
    np.testing.assert_allclose(ro.rewards.numpy(), ro0.rewards.numpy() - 2.0 * want, rtol=1e-5, atol=1e-6)
    assert stats["r_action_rate"] == pytest.approx(-want.mean(), rel=1e-5)
    assert "r_action_rate" not in stats0  # off by default: the paper's reward, unchanged


def test_in_a_trainer_with_two_groups_each_environment_keeps_its_own_last_action_across_iterations(hum, lib):
    """The expert with both options and two environment groups taking turns: the collector's
    ``e_rate`` equals the one recomputed from the stored actions and episode ends, the last action
    of one iteration carried into the next; the discriminator's transitions (Eq. 7 and the soles)
    chain, each state the next transition's start, except where an episode restarted."""
    from motok.control.expert.model import ExpertConfig
    from motok.control.expert.train import ExpertTrainer

    cfg = ExpertConfig(seed=0, save_every=1000, w_action_rate=1.0)
    cfg.env.num_envs, cfg.env.groups, cfg.ppo.horizon, cfg.ppo.minibatch_size = 8, 2, 12, 32
    cfg.task.max_episode_seconds = 0.2  # 6 steps: every environment restarts within an iteration
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [16]
    cfg.amp.hidden, cfg.amp.batch_size, cfg.amp.updates, cfg.amp.feet = [16], 16, 1, True
    tr = ExpertTrainer(cfg, hum, lib)
    tr.start_segment()
    col, prev = tr.collector, None
    for _ in range(2):
        ro, _, stats = col.collect()
        s, s2 = (x.view(cfg.ppo.horizon, 8, -1) for x in col._transitions)
        a, done = ro.actions.numpy().astype(np.float64), (ro.terminated | ro.truncated).numpy()
        before = np.concatenate([prev[0][None], a[:-1]]) if prev else np.concatenate([a[:1], a[:-1]])
        fresh = np.concatenate([prev[1][None], done[:-1]]) if prev else np.concatenate([np.ones((1, 8), bool), done[:-1]])
        want = np.where(fresh, 0.0, ((a - before) ** 2).mean(-1))
        np.testing.assert_allclose(col.rate.numpy(), want, rtol=1e-5, atol=1e-9)
        assert stats["r_action_rate"] == pytest.approx(-want.mean(), rel=1e-5) and (want > 0).any()
        assert done.any() and s.shape[-1] == tr.mdp.obs_dim + 4
        same = ~done[:-1]
        np.testing.assert_array_equal(s[1:].numpy()[same], s2[:-1].numpy()[same])
        D = tr.mdp.obs_dim  # a restarted row starts from its new episode's state, Eq. 7 and soles alike
        assert (s[1:].numpy()[~same][:, :D] != s2[:-1].numpy()[~same][:, :D]).any(-1).all()
        # and an episode's last transition ends at its own final soles, taken before the restart
        assert (s[1:].numpy()[~same][:, D:] != s2[:-1].numpy()[~same][:, D:]).any(-1).all()
        col.update_hooks()
        prev = (a[-1], done[-1])


def test_an_expert_with_both_options_resumes_exactly(hum, lib, tmp_path):
    """Interrupted and resumed at a checkpoint, the expert with the action-rate term and the
    soles' discriminator ends with the weights and metrics of one trained straight through (every
    segment starts fresh episodes, and so no last action, in both)."""
    from safetensors.torch import load_file

    from motok.control.expert.model import ExpertConfig
    from motok.control.expert.train import train

    cfg = ExpertConfig(seed=0, iterations=4, save_every=2, w_action_rate=1.0)
    cfg.env.num_envs, cfg.ppo.horizon, cfg.ppo.minibatch_size = 4, 8, 16
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [16]
    cfg.amp.hidden, cfg.amp.batch_size, cfg.amp.updates, cfg.amp.feet = [16], 16, 1, True
    train(cfg, tmp_path / "straight", hum, lib)
    train(cfg, tmp_path / "split", hum, lib, until=2)
    train(cfg, tmp_path / "split", hum, lib, resume=True)
    a, b = (load_file(tmp_path / r / "model.safetensors") for r in ("straight", "split"))
    extra = json.loads((tmp_path / "split" / "bundle.json").read_text())["extra"]
    assert a["disc.mean"].shape[0] == extra["amp_obs_dim"] == extra["obs_dim"] + 4  # Eq. 7 and the soles
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    rows = [[json.loads(x) for x in (tmp_path / r / "metrics.jsonl").read_text().splitlines()] for r in ("straight", "split")]
    assert [r["r_action_rate"] for r in rows[0]] == [r["r_action_rate"] for r in rows[1]]


# ---------------------------------------------------------------------- the discriminator sees the soles


def test_the_soles_of_a_reference_frame_survive_the_round_trip_through_mujoco(hum, lib):
    """Reference frames put into MuJoCo as qpos/qvel: the discriminator's whole observation of the
    simulated state (Eq. 7 and the soles) equals the one computed from the library's frame."""
    from motok.control.rl.amp import SoleObservation, reference_observations

    sole = SoleObservation(hum)
    g = np.array([lib.starts[0] + 10, lib.starts[0] + 40, lib.starts[1] + 7, lib.starts[2] + 25])
    env = HumanoidEnv(hum, SimConfig(num_envs=len(g)))
    env.set_state(np.arange(len(g)), lib.qpos[g], lib.qvel[g])
    ref = reference_observations(lib, env.end_effectors, sole)
    sim = sole.of(env.observation(), env.bodies)
    assert ref.shape[1] == env.obs_dim + 4 and sim.shape == (len(g), env.obs_dim + 4)
    np.testing.assert_allclose(sim, ref[g], atol=1e-6)
    feet = ref[:, -4:]
    assert feet[:, [1, 3]].max() > 0.5 and feet[:, [0, 2]].min() < 0.02  # walking: a swinging foot, a planted one


def test_a_foot_sliding_at_a_known_speed_gives_that_speed(hum, lib):
    """A real standing frame in MuJoCo moving as a rigid body: translating at (0.3, 0.4) m/s every
    sole slides at 0.5 m/s; turning about the vertical at 2 rad/s each foot's lowest corner moves at
    2 rad/s times its horizontal distance from the root. Heights are the lowest corners' (computed
    here from the body quaternions, another path)."""
    from motok.sim.soles import foot_corners, reference_corners, sole_state, soles

    sole = soles(hum)
    feet = foot_corners(sole, hum.skeleton)
    q = lib.qpos[lib.starts[0]][None].copy()
    env = HumanoidEnv(hum, SimConfig(num_envs=1))
    qv = np.zeros((1, hum.nv))
    qv[0, :3] = [0.3, 0.4, 0.0]
    env.set_state([0], q, qv)
    b = env.bodies
    f = sole_state(sole, feet, b.pos, b.rot, b.vel, b.angvel)[0]
    corners = reference_corners(sole, b.pos, b.quat)[0]
    np.testing.assert_allclose(f[[0, 2]], [corners[feet[0], 2].min(), corners[feet[1], 2].min()], atol=1e-9)
    np.testing.assert_allclose(f[[1, 3]], [0.5, 0.5], atol=1e-9)

    t = sole_state(sole, feet, *(torch.as_tensor(np.ascontiguousarray(x)) for x in (b.pos, b.rot, b.vel, b.angvel)))
    np.testing.assert_allclose(t.numpy()[0], f, atol=1e-12)  # the same numbers on tensors (a device rollout)

    R = b.rot[0, 0]  # the free joint's angular velocity is in the root's frame
    qv[0, :3], qv[0, 3:6] = 0.0, R.T @ [0.0, 0.0, 2.0]
    env.set_state([0], q, qv)
    b = env.bodies
    f = sole_state(sole, feet, b.pos, b.rot, b.vel, b.angvel)[0]
    for k, idx in enumerate(feet):
        low = corners[idx[np.argmin(corners[idx, 2])]]
        assert f[2 * k + 1] == pytest.approx(2.0 * np.hypot(*(low[:2] - b.pos[0, 0, :2])), rel=1e-6)


def test_amp_feet_is_recorded_and_a_resume_with_the_other_setting_is_refused(small_dataset, tmp_path):
    from typer.testing import CliRunner

    from motok.cli.main import app
    from motok.config import from_dict, to_dict
    from motok.control.expert.model import ExpertConfig

    run = tmp_path / "expert"
    args = ["--quiet", "control", "expert", "train", "-d", str(small_dataset), "--clips", "dataset-2_walk_normal_001",
            "--set", "env.num_envs=4", "--set", "ppo.horizon=4", "--set", "ppo.minibatch_size=16",
            "--set", "amp.batch_size=8", "--set", "iterations=2", "-o", str(run)]
    r = CliRunner().invoke(app, [*args, "--set", "amp.feet=true", "--set", "w_action_rate=1.0", "--until", "1"])
    assert r.exit_code == 0, r.output
    meta = json.loads((run / "bundle.json").read_text())
    assert meta["config"]["amp"]["feet"] is True and meta["extra"]["amp_obs_dim"] == meta["extra"]["obs_dim"] + 4
    r = CliRunner().invoke(app, [*args, "--set", "amp.feet=false", "--resume"])
    assert r.exit_code == 2 and "amp.feet True -> False" in r.output, r.output
    r = CliRunner().invoke(app, [*args, "--resume"])  # the run's own settings: goes on
    assert r.exit_code == 0 and json.loads((run / "bundle.json").read_text())["extra"]["iteration"] == 2
    new = [*args[:-1], str(tmp_path / "warm")]  # a warm start whose discriminator saw another input
    r = CliRunner().invoke(app, [*new, "--init", str(run), "--until", "1"])
    assert r.exit_code == 2 and "amp.feet=true, this recipe has amp.feet=false" in r.output, r.output
    r = CliRunner().invoke(app, [*args[:-1], str(tmp_path / "nostyle"), "--init", str(run), "--set", "w_style=0",
                                 "--until", "1"])  # no discriminator here: nothing of the other one is loaded
    assert r.exit_code == 0, r.output
    # a config saved before these options existed loads as what it did: both off
    old = to_dict(ExpertConfig())
    del old["w_action_rate"], old["amp"]["feet"]
    cfg = from_dict(ExpertConfig, old)
    assert cfg.w_action_rate == 0.0 and cfg.amp.feet is False


# ---------------------------------------------------------------------- 60 Hz


def test_a_student_or_a_task_policy_acts_at_its_parents_control_rate():
    """A prior distilled from a 60 Hz expert steps at 60 Hz unless its recipe says otherwise, and a
    recipe asking for another rate is refused, naming both."""
    from motok.errors import UserError

    parent = SimConfig(control_hz=60.0, target_filter=0.5)
    child = SimConfig().same_world(parent, "the expert E")
    assert (child.control_hz, child.target_filter) == (60.0, 0.5)
    with pytest.raises(UserError, match="env.control_hz=30 but the expert E acts at env.control_hz=60"):
        SimConfig(control_hz=30.0).same_world(parent, "the expert E")
    assert SimConfig().same_world(SimConfig(), "the expert E").control_hz is None  # both at the humanoid's


def test_a_rate_set_against_a_parent_at_the_humanoids_rate_is_refused():
    """A parent that left its rate unset acts at its humanoid's: a child asking for another is refused,
    naming both; one asking for the humanoid's own goes on, and an unset one stays unset (a saved
    recipe does not change)."""
    from motok.errors import UserError

    with pytest.raises(UserError, match="env.control_hz=60 but the prior P acts at its humanoid's rate, 30:"):
        SimConfig(control_hz=60.0).same_world(SimConfig(), "the prior P", 30.0)
    assert SimConfig(control_hz=30.0).same_world(SimConfig(), "the prior P", 30.0).control_hz == 30.0
    assert SimConfig().same_world(SimConfig(), "the prior P", 30.0).control_hz is None


def test_distilling_or_training_a_task_at_another_rate_than_the_parents_is_refused_before_the_library(
        hum, small_dataset, tmp_path_factory, monkeypatch):
    """``motok control distill`` from an expert at the humanoid's 30 Hz, and ``motok control train``
    over a prior at it, with ``env.control_hz: 60``: each refused naming the rate, before the
    reference library is built at the wrong one."""
    from motok.control import runs
    from motok.control.highlevel.policy import TaskTrainConfig
    from motok.control.highlevel.train import train_from_prior
    from motok.control.priors.distill import train_from_expert
    from motok.control.priors.model import DistillConfig
    from motok.errors import UserError
    from task_helpers import tiny_prior_on_three_clips

    prior = tiny_prior_on_three_clips(hum, small_dataset, tmp_path_factory, "rates")
    expert, out = prior.parent / "expert", tmp_path_factory.mktemp("refused")

    def built(*a, **k):
        raise AssertionError("the reference library was built before the rate was checked")

    monkeypatch.setattr(runs, "run_library", built)
    cfg = DistillConfig(seed=0, iterations=1, save_every=1000, horizon=8, epochs=1, minibatch_size=32)
    cfg.env.num_envs, cfg.env.nthread, cfg.env.control_hz = 4, 1, 60.0
    said = "env.control_hz=60 but the {} acts at its humanoid's rate, 30:"
    with pytest.raises(UserError, match=re.escape(said.format(f"expert {expert}"))):
        train_from_expert(cfg, expert, out / "prior", prior="hybrid")
    tcfg = TaskTrainConfig(seed=0, iterations=1, save_every=1000, task="navigation")
    tcfg.env.num_envs, tcfg.env.nthread, tcfg.env.control_hz = 4, 1, 60.0
    with pytest.raises(UserError, match=re.escape(said.format(f"prior {prior}"))):
        train_from_prior(tcfg, prior, out / "nav", codebooks=2)


@pytest.fixture(scope="module")
def expert60(hum, small_dataset, tmp_path_factory):
    """A 1-iteration expert at 60 Hz on the first clip (no AMP)."""
    from motok.control.expert.model import ExpertConfig
    from motok.control.expert.train import train as train_expert
    from motok.sim.reference import load_library

    root = tmp_path_factory.mktemp("expert60")
    lib = load_library(hum, small_dataset, control_hz=60.0, clips=[0], cache_dir=root / "cache")
    ecfg = ExpertConfig(seed=0, iterations=1, save_every=1000)
    ecfg.env.num_envs, ecfg.env.nthread, ecfg.env.control_hz = 4, 1, 60.0
    ecfg.ppo.horizon, ecfg.ppo.minibatch_size = 8, 32
    ecfg.net.encoder = ecfg.net.decoder = ecfg.net.value = [16]
    ecfg.amp.enabled = False
    train_expert(ecfg, root / "expert", hum, lib, data=small_dataset)
    return root / "expert"


def test_a_prior_of_a_60hz_expert_and_a_task_over_it_step_at_60hz(expert60, tmp_path):
    """Through the commands' entry points, with recipes that leave the rate unset: the prior takes
    its expert's 60 Hz (its recipe, its spec and the library it learnt on), and the task policy the
    prior's."""
    from motok.control.highlevel.train import train_from_prior
    from motok.control.priors.distill import train_from_expert
    from motok.control.priors.model import DistillConfig
    from task_helpers import tiny_task_config
    from tiny_runs import small_prior_config

    cfg = DistillConfig(seed=0, iterations=1, save_every=1000, horizon=8, epochs=1, minibatch_size=32)
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.prior = small_prior_config("hybrid")
    train_from_expert(cfg, expert60, tmp_path / "prior")
    prior = json.loads((tmp_path / "prior" / "bundle.json").read_text())
    assert prior["config"]["env"]["control_hz"] == prior["extra"]["control_hz"] == 60.0
    tcfg = tiny_task_config("navigation")
    tcfg.iterations = tcfg.save_every = tcfg.eval_every = 1
    train_from_prior(tcfg, tmp_path / "prior", tmp_path / "nav", codebooks=2)
    nav = json.loads((tmp_path / "nav" / "bundle.json").read_text())
    assert nav["config"]["env"]["control_hz"] == nav["extra"]["control_hz"] == 60.0


@pytest.fixture(scope="module")
def libs(hum, small_dataset):
    from motok.sim.reference import build_library

    clips = ["dataset-2_walk_normal_001"]
    return {hz: build_library(hum, small_dataset, hz, clips) for hz in (30.0, 60.0)}


def test_a_60hz_reference_is_the_clip_at_real_speed_interpolated_between_its_frames(hum, small_dataset, libs):
    """The library at 60 Hz holds the 30 Hz one's states at every other frame (the same instants),
    and its frames between are the source clip (20 fps) interpolated at their own time: the root
    linearly, its rotation along the great arc (its angle to each neighbour in proportion)."""
    from motok.data.dataset import MotionFile
    from motok.sim.humanoid import to_mj
    from motok.sim.retarget import solve_locals

    l30, l60 = libs[30.0], libs[60.0]
    n30 = l30.lengths[0]
    np.testing.assert_allclose(l60.body_pos[0:2 * n30 - 1:2], l30.body_pos[:n30], atol=1e-9)
    np.testing.assert_allclose(l60.qpos[0:2 * n30 - 1:2, :3], l30.qpos[:n30, :3], atol=1e-12)
    with MotionFile(small_dataset) as mf:
        fps, j = mf.fps, np.asarray(mf.frames("joints", mf.index("dataset-2_walk_normal_001")), np.float64)
    src_root, src_q = to_mj(j[:, 0]), solve_locals(to_mj(j), hum.layout)[:, 0]
    checked = 0
    for k in range(1, l60.lengths[0] - 1, 2):  # the frames the 30 Hz library has no counterpart of
        s = k / 60.0 * fps
        i, u = int(np.floor(s)), s - np.floor(s)
        if u < 1e-9:
            continue
        np.testing.assert_allclose(l60.qpos[k, :3], (1 - u) * src_root[i] + u * src_root[i + 1], atol=1e-12)
        ang = lambda a, b: 2 * np.arccos(min(1.0, abs(float(np.dot(a, b)))))  # noqa: E731
        q, qa, qb = l60.qpos[k, 3:7], src_q[i], src_q[i + 1]
        assert ang(q, qa) == pytest.approx(u * ang(qa, qb), abs=1e-6)
        assert ang(q, qb) == pytest.approx((1 - u) * ang(qa, qb), abs=1e-6)
        checked += 1
    assert checked > 20


def test_a_60hz_episode_covers_the_same_clip_seconds_as_a_30hz_one(hum, libs):
    """The same clip from frame 0 to its end at both rates: twice the steps at half the step, so the
    same seconds of the clip (up to the goal's one frame ahead at each rate), and the reference
    reached after 2k steps at 60 Hz is the one reached after k steps at 30 Hz."""
    seconds, refs = {}, {}
    for hz, lib in libs.items():
        env = HumanoidEnv(hum, SimConfig(num_envs=1, control_hz=hz))
        assert env.substeps == round(120 / hz)
        task = ImitationTask(ImitationTaskConfig(early_termination=False), env, lib, np.random.default_rng(0))
        mdp = TaskEnv(env, task, partial(pd_targets, ActionConfig(base="reference")))
        mdp.reset(clips=[0], frames=0)
        steps, pos = 0, [task.reference(task.clip[:, None], task.frame[:, None]).pos[0, 0]]
        while True:
            *_, term, trunc, _ = mdp.step(np.zeros((1, env.action_dim)))
            steps += 1
            pos.append(task.reference(task.clip[:, None], task.frame[:, None]).pos[0, 0])
            if term[0] or trunc[0]:
                break
        seconds[hz], refs[hz] = steps / hz, np.stack(pos)
    clip_seconds = (libs[30.0].lengths[0] - 1) / 30.0
    assert seconds[30.0] == pytest.approx(clip_seconds - 1 / 30)  # the goal looks K = 1 frame ahead
    assert abs(seconds[60.0] - seconds[30.0]) <= 1 / 30 + 1e-9
    n = len(refs[30.0])
    np.testing.assert_allclose(refs[60.0][0:2 * n - 1:2], refs[30.0], atol=1e-9)


# ---------------------------------------------------------------------- the ranking script


def test_every_lever_of_the_ranking_script_is_a_valid_change_of_the_recipe(script):
    """``scripts/foot_levers.py``'s levers load into the expert's and the humanoid's configs (a
    misspelt key would only fail hours into a ranking), and ``rate60s`` keeps per second what the
    30 Hz settings do per 1/30 s: discount, GAE lambda and the target filter's decay."""
    from pathlib import Path

    from motok.config import load_config
    from motok.control.expert.model import ExpertConfig
    from motok.sim.humanoid import HumanoidConfig

    fl = script("foot_levers")
    recipe = Path(__file__).parents[1] / "recipes/control/expert.yaml"
    cfgs = {n: load_config(ExpertConfig, recipe, fl.BASE_SETS + sets) for n, (_, sets) in fl.LEVERS.items()}
    for hum_sets, _ in fl.LEVERS.values():
        load_config(HumanoidConfig, None, hum_sets)
    base, r60, r60s = cfgs["base"], cfgs["rate60"], cfgs["rate60s"]
    assert (base.w_action_rate, base.amp.feet, base.env.control_hz) == (0.0, False, None)
    assert cfgs["action_rate"].w_action_rate > 0 and cfgs["amp_feet"].amp.feet is True
    assert r60.env.control_hz == 60 and r60.ppo.gamma == base.ppo.gamma
    assert r60s.ppo.gamma ** 2 == pytest.approx(base.ppo.gamma, abs=1e-4)
    assert r60s.ppo.lam ** 2 == pytest.approx(base.ppo.lam, abs=1e-3)
    assert (1 - r60s.env.target_filter) ** 2 == pytest.approx(1 - base.env.target_filter, abs=1e-3)
    # on the chosen world the 30 Hz filter is 0.3, and every set2 lever keeps it per second
    set2 = cfgs["filter0.3+ankle0.5"]
    assert (1 - cfgs["set2+rate60s"].env.target_filter) ** 2 == pytest.approx(1 - set2.env.target_filter, abs=1e-3)
    assert cfgs["set2+action_rate"].env.target_filter == cfgs["set2+amp_feet"].env.target_filter == 0.3
    assert fl.LEVERS["set2+rate60s"][0] == fl.LEVERS["filter0.3+ankle0.5"][0]


def test_the_feet_videos_take_one_to_three_experts_and_one_label_each(script, tmp_path):
    """``scripts/feet_videos.py`` refuses, before any clip is played, a panel count it cannot lay out
    and labels that do not pair with the experts, naming what it expected."""
    fv = script("feet_videos")
    run = str(tmp_path / "run")
    common = ["-d", str(tmp_path / "data.h5"), "--clip", "x", "-o", str(tmp_path / "v.mp4")]
    with pytest.raises(SystemExit, match="1 to 3 times \\(got 4\\)"):
        fv.main([*["--expert", run] * 4, *common])
    with pytest.raises(SystemExit, match="--label once per --expert"):
        fv.main(["--expert", run, "--expert", run, "--label", "only one", *common])


def test_the_feet_videos_refuse_experts_at_two_control_rates(script, expert60, tmp_path):
    """Panels are joined frame by frame, so a 60 Hz expert beside a 30 Hz one would play at twice
    its speed: refused before any clip is played, naming both rates."""
    import shutil

    fv = script("feet_videos")
    other = tmp_path / "expert30"
    shutil.copytree(expert60, other)
    meta = json.loads((other / "bundle.json").read_text())
    meta["extra"]["control_hz"] = 30.0
    (other / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(SystemExit, match="the experts act at 60 Hz, 30 Hz; side by side they must share one"):
        fv.main(["--expert", str(expert60), "--expert", str(other), "-d", str(tmp_path / "absent.h5"), "--clip", "x",
                 "-o", str(tmp_path / "v.mp4")])
