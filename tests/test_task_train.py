"""Task learning over a frozen prior (motok.control.highlevel.policy, motok.control.highlevel.train, `motok
control train` / `motok control eval --task T --run`): the action map decodes exactly what the
prior would, PPO trains the high-level policy and nothing of the prior, it learns, training
resumes exactly, and the bundle evaluates and renders."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.checkpoint import CheckpointError
from motok.control.priors.model import DistillConfig, load_prior
from motok.control.highlevel.policy import HighLevelNetConfig, LatentActionMap, build_high_level, task_codebooks
from motok.control.mdp.resets import reference_state
from motok.control.rl.policies import MLPPolicy, MultiCategoricalPolicy
from motok.control.priors.model import LatentPrior
from motok.control.highlevel.policy import TaskTrainConfig, load_task_run
from motok.control.highlevel.evaluate import evaluate_run
from motok.control.highlevel.train import TaskTrainer, ppo_config, train_from_prior
from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.reference import load_library
from tiny_runs import small_prior_config, tiny_prior_bundle

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def walk_lib(hum, small_dataset, tmp_path_factory):
    return load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp("task-ref"))


@pytest.fixture(scope="module")
def tiny_prior(hum, walk_lib, small_dataset, tmp_path_factory):
    return tiny_prior_bundle(tmp_path_factory.mktemp("task-runs"), hum, walk_lib, small_dataset)


def standing_env(hum, lib, n=4) -> HumanoidEnv:
    env = HumanoidEnv(hum, SimConfig(num_envs=n, nthread=1))
    env.set_state(np.arange(n), *reference_state(lib, np.arange(n) % len(lib), np.arange(n) * 3))
    return env


def random_prior(kind: str, env: HumanoidEnv, seed=0) -> LatentPrior:
    torch.manual_seed(seed)
    model = LatentPrior(small_prior_config(kind), env.obs_dim, 7, env.action_dim).eval()
    with torch.no_grad():  # statistics that are not the identity, so a missing normalisation shows
        model.norm.mean.normal_(0, 0.3)
        model.norm.var.uniform_(0.5, 2.0)
    return model


# ---------------------------------------------------------------------- the action map

@pytest.mark.parametrize("kind,m", [("hybrid", 2), ("discrete+", 3), ("discrete", 1)])
def test_the_action_map_decodes_the_chosen_codes(hum, walk_lib, kind, m):
    env = standing_env(hum, walk_lib)
    model = random_prior(kind, env)
    idx = torch.randint(0, model.quantizer.codebook_size, (env.num_envs, m))
    targets = LatentActionMap(model, m, 0.7)(idx.numpy(), env, None)
    # By hand: z_bar = [z_p(s) +] sum of the chosen codes of the first m codebooks.
    s = torch.as_tensor(env.observation(), dtype=torch.float32)
    n = model.norm
    sn = ((s - n.mean[:env.obs_dim].float()) / torch.sqrt(n.var[:env.obs_dim].float() + n.eps)).clamp(-5, 5)
    books = model.codebooks()
    z = sum(books[j][idx[:, j]] for j in range(m))
    if model.prior is not None:
        z = z + model.prior(sn)
    a = model.decoder(torch.cat([sn, z], -1)).detach().numpy()
    np.testing.assert_allclose(targets, env.qpos[:, env.hinge_adr] + 0.7 * a, rtol=1e-5, atol=1e-6)
    other = idx.clone()
    other[:, m - 1] = (other[:, m - 1] + 1) % model.quantizer.codebook_size
    assert not np.allclose(LatentActionMap(model, m, 0.7)(other.numpy(), env, None), targets)


def test_the_continuous_map_offsets_the_prior_mean(hum, walk_lib):
    env = standing_env(hum, walk_lib)
    model = random_prior("continuous", env)
    amap = LatentActionMap(model, 0, 1.0)
    u = np.random.default_rng(0).normal(size=(env.num_envs, model.cfg.latent_dim)).astype(np.float32)
    sn = model.norm_obs(torch.as_tensor(env.observation(), dtype=torch.float32))
    mu_p = model.prior_latent(sn)[0]
    a = model.decode(sn, mu_p + torch.as_tensor(u)).detach().numpy()
    np.testing.assert_allclose(amap(u, env, None), env.qpos[:, env.hinge_adr] + a, rtol=1e-5, atol=1e-6)


def test_the_high_level_action_space_follows_the_prior(hum, walk_lib):
    env = standing_env(hum, walk_lib, 1)
    net = HighLevelNetConfig(policy=[16], value=[16], std=0.3)
    ac = build_high_level(net, random_prior("discrete+", env), env.obs_dim, 2, 3)
    assert isinstance(ac.policy, MultiCategoricalPolicy) and (ac.policy.heads, ac.policy.classes) == (3, 16)
    assert build_high_level(net, random_prior("hybrid", env), env.obs_dim, 2, None).policy.heads == 4
    assert build_high_level(net, random_prior("discrete", env), env.obs_dim, 2, None).policy.classes == 32
    cont = build_high_level(net, random_prior("continuous", env), env.obs_dim, 2, None).policy
    assert isinstance(cont, MLPPolicy) and torch.allclose(cont.log_std.exp(), torch.tensor(0.3))
    with pytest.raises(UserError, match="1..4"):
        build_high_level(net, random_prior("hybrid", env), env.obs_dim, 2, 5)
    with pytest.raises(UserError, match="no codebooks"):
        build_high_level(net, random_prior("continuous", env), env.obs_dim, 2, 1)


def test_each_task_learns_over_its_papers_active_codebooks(hum, walk_lib, tiny_prior, tmp_path):
    """Tables 6-8: in-betweening over 1 active codebook, head tracking over 2, navigation over 1. A
    recipe's ``codebooks: null`` is the task's default (at most the prior's; all for a task the
    paper does not have), an explicit number wins, and the default reaches the policy's action
    space: a new run saves it resolved and resumes with it."""
    env = standing_env(hum, walk_lib, 1)
    hybrid = random_prior("hybrid", env)  # 4 codebooks
    assert [task_codebooks(hybrid, t, None) for t in ("inbetween", "hmd", "navigation", "steering")] == [1, 2, 1, 4]
    assert task_codebooks(hybrid, "hmd", 3) == 3
    assert task_codebooks(random_prior("continuous", env), "hmd", None) is None
    assert task_codebooks(random_prior("discrete", env), "hmd", None) == 1  # one codebook: all it has
    net = HighLevelNetConfig(policy=[16], value=[16])
    assert build_high_level(net, hybrid, env.obs_dim, 2, task_codebooks(hybrid, "hmd", None)).policy.heads == 2
    # the continuous prior's own learning rate; the categorical policies keep ppo.lr
    lrs = TaskTrainConfig(continuous_lr=5e-5)
    assert ppo_config(lrs, random_prior("continuous", env)).lr == 5e-5 and ppo_config(lrs, hybrid).lr == lrs.ppo.lr
    cfg = small_cfg(iterations=2, save_every=1, task="hmd")
    cfg.env.num_envs, cfg.tasks.hmd.episode_seconds = 4, 1.0
    cfg.ppo = replace(cfg.ppo, horizon=4, minibatch_size=16, epochs=1)
    assert cfg.codebooks is None
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "hmd", until=1)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "hmd", resume=True)  # the recipe's null again
    saved, _, ac, model, _, meta = load_task_run(tmp_path / "hmd")
    rows = [json.loads(x) for x in (tmp_path / "hmd" / "metrics.jsonl").read_text().splitlines()]
    assert model.num_codebooks == 4 and saved.codebooks == 2 and [r["iteration"] for r in rows] == [1, 2]
    assert meta["extra"]["high_level_action"]["codebooks"] == 2 and ac.policy.heads == 2


def test_configs_saved_before_the_papers_protocol_keep_what_they_did():
    """A run saved before a protocol setting existed resumes and evaluates as it trained: the keys
    it lacks take the values it ran with, not the paper's new defaults; a new config has the paper's."""
    from motok.config import from_dict, to_dict

    old = to_dict(TaskTrainConfig())
    del old["continuous_lr"], old["tasks"]["inbetween"]["keyframe_selection"]
    del old["tasks"]["navigation"]["full_reward_on_arrival"]
    was, now = from_dict(TaskTrainConfig, old), TaskTrainConfig()
    assert (was.continuous_lr, was.tasks.inbetween.keyframe_selection, was.tasks.navigation.full_reward_on_arrival) \
        == (None, "uniform", False)
    assert (now.continuous_lr, now.tasks.inbetween.keyframe_selection, now.tasks.navigation.full_reward_on_arrival) \
        == (None, "still", True)


# ---------------------------------------------------------------------- PPO over the prior

def small_cfg(**kw) -> TaskTrainConfig:
    cfg = TaskTrainConfig(seed=0, iterations=40, save_every=1000, task="navigation")
    cfg.env.num_envs, cfg.env.nthread = 16, 1
    cfg.ppo = replace(cfg.ppo, horizon=16, epochs=4, minibatch_size=128, lr=3e-3, clip=0.2, entropy_coef=0.0)
    cfg.net = HighLevelNetConfig(policy=[32], value=[32])
    return replace(cfg, **kw)


class CodeToPose(torch.nn.Module):
    """A decoder ``pi_low(s, z)`` for the learning test: code k asks for the standing pose plus
    offset k, ``a = q_stand + offset_k - q`` (``q``: the hinge angles inside Eq. 7's ``s``, read
    through an identity normaliser)."""

    def __init__(self, obs_dim: int, codes: torch.Tensor, q_stand: torch.Tensor, offsets: torch.Tensor):
        super().__init__()
        self.obs_dim, self.codes, self.q_stand, self.offsets = obs_dim, codes, q_stand, offsets

    def forward(self, x):
        s, z = x[..., :self.obs_dim], x[..., self.obs_dim:]
        k = torch.cdist(z, self.codes).argmin(-1)
        q = s[..., 13:13 + len(self.q_stand)]  # Eq. 7: height (1), root 6-d (6), velocities (3 + 3), hinges
        return self.q_stand + self.offsets[k] - q


# navigation: targets 5-10 m away (the authors' code's draw), where standing pays the same small
# reward everywhere: the paper's targets within 10 m pay up to 1 a step near the start, a return
# noise that hides the codes' difference in 40 iterations of 256 samples
SHORT_TASKS = {"navigation": {"episode_seconds": 2.0, "min_distance": 5.0},
               "inbetween": {"window_seconds": 2.0, "num_keyframes": 3, "eval_keyframes": 3},
               "hmd": {"episode_seconds": 2.0}}


@pytest.mark.parametrize("task", list(SHORT_TASKS))
def test_ppo_learns_which_codes_keep_the_character_up_and_never_touches_the_prior(hum, labelled_dataset,
                                                                                  tmp_path, task):
    """A discrete prior of 4 codes: code 0 holds a standing pose, the others hold it with offsets
    of up to +-1 rad on every hinge, which topple the character. Episodes start from standing
    gesture clips; every task pays while the character stays up (navigation: its velocity term is
    > 0 standing still; in-betweening and head tracking: the gesture's reference stays near a
    standing pose) and ends when it falls (the head below 0.5 m, the bodies or the head far from
    the reference), so PPO must learn to pick code 0: episodes and returns grow. The prior's
    weights stay bit-identical."""
    from motok.data.dataset import select_clips

    lib = load_library(hum, labelled_dataset, clips=select_clips(labelled_dataset, "dataset-2_raise-up-both-hands_*"),
                       cache_dir=tmp_path)
    env = standing_env(hum, lib, 1)
    torch.manual_seed(0)
    model = LatentPrior(replace(small_prior_config("discrete"), vq_codebook_size=4), env.obs_dim, 7,
                        env.action_dim).eval()
    H = env.action_dim
    g = torch.Generator().manual_seed(1)
    codes = torch.randn(4, model.cfg.latent_dim, generator=g)
    offsets = 2.0 * (torch.rand(4, H, generator=g) - 0.5)
    offsets[0] = 0.0
    with torch.no_grad():
        model.quantizer.embed.copy_(codes)
    q_stand = torch.as_tensor(lib.qpos[lib.starts[0], 7:], dtype=torch.float32)
    model.decoder = CodeToPose(env.obs_dim, codes, q_stand, offsets)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    cfg = small_cfg(task=task)
    setattr(cfg.tasks, task, replace(getattr(cfg.tasks, task), **SHORT_TASKS[task]))
    tr = TaskTrainer(cfg, hum, lib, DistillConfig(), model)
    assert not ({id(p) for p in tr.ppo.params} & {id(p) for p in model.parameters()})
    tr.start_segment()
    stats = [tr.step() for _ in range(40)]
    lens = [x["episode_seconds"] for x in stats if "episode_seconds" in x]
    rets = [x["episode_return"] for x in stats if "episode_return" in x]
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert np.mean(lens[-6:]) > 1.5 * np.mean(lens[:6]), lens
    assert np.mean(rets[-6:]) > 1.5 * np.mean(rets[:6]), rets
    x = torch.as_tensor(np.concatenate([tr.mdp.env.observation(), tr.mdp.task.goal()], 1), dtype=torch.float32)
    p0 = tr.ac.policy.log_probs(tr.ac.norm(x))[..., 0, 0].exp().mean()
    assert p0 > 0.5, float(p0)  # from 1/4 at the start (0.999 here; PPO settles on code 0 between iterations 30 and 40)


# ---------------------------------------------------------------------- the bundle

def test_train_resume_eval_and_the_command(hum, walk_lib, tiny_prior, tmp_path, script):
    cfg = small_cfg(iterations=4, save_every=2, eval_every=2, eval_episodes=4)
    cfg.env.num_envs = 4
    cfg.ppo = replace(cfg.ppo, horizon=8, minibatch_size=16, epochs=1)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "straight", codebooks=2)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "split", codebooks=2, until=2)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "split", codebooks=2, resume=True)
    a, b = load_task_run(tmp_path / "straight"), load_task_run(tmp_path / "split")
    sa, sb = a[2].state_dict(), b[2].state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    rows = [json.loads(x) for x in (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4] and "eval_reached_share" in rows[1]
    cfg_, _, ac, model, _, meta = a
    assert meta["extra"]["task"] == "navigation" and meta["extra"]["high_level_action"]["codebooks"] == 2
    assert ac.policy.heads == 2 and model.kind == "hybrid"
    res = evaluate_run(tmp_path / "straight", episodes=4, render=tmp_path / "nav.gif")
    assert res["episodes"] == 4 and 0 <= res["reached_share"] <= 1 and (tmp_path / "nav.gif").stat().st_size > 0
    # the idle phase's motion matching is reported (NaN, with no transitions, where no stay lasted)
    assert res["idle_transitions"] == res["idle_motion_matching"]["transitions"] and "idle_bodies" not in res
    again = evaluate_run(tmp_path / "straight", episodes=4)
    assert again["mean_reward"] == res["mean_reward"]  # a fixed seed: the same episodes
    written = json.loads((tmp_path / "straight" / "eval_navigation.json").read_text(),
                         parse_constant=lambda c: pytest.fail(f"eval_navigation.json holds {c}: not JSON"))
    assert written["checkpoint"]["iteration"] == 4
    # a number the evaluation could not take (no target reached, no idle stay) is null in the file
    for key in ("time_to_reach_mean_s", "idle_distance_mean"):
        assert (written[key] is None) == bool(np.isnan(again[key])), key
    with pytest.raises(CheckpointError):
        load_task_run(tiny_prior)
    with pytest.raises(UserError, match="navigation"):
        train_from_prior(replace(cfg), tiny_prior, tmp_path / "bad", task="jump")

    from motok.cli.main import app
    r = CliRunner().invoke(app, ["control", "eval", "--task", "navigation", "--policy", str(tmp_path / "straight"),
                                 "-n", "2", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["episodes"] == 2
    r = CliRunner().invoke(app, ["control", "eval", "--task", "navigation", "--prior", str(tiny_prior)])
    assert r.exit_code == 2 and "--policy" in r.output
    # the wrong task for the run: one line before any episode is played or any file written
    stamp = (tmp_path / "straight" / "eval_navigation.json").stat().st_mtime_ns
    r = CliRunner().invoke(app, ["control", "eval", "--task", "hmd", "--policy", str(tmp_path / "straight"), "-n", "2"])
    assert r.exit_code != 0 and "is a 'navigation' policy, not 'hmd'" in r.output
    assert not (tmp_path / "straight" / "eval_hmd.json").exists()
    assert (tmp_path / "straight" / "eval_navigation.json").stat().st_mtime_ns == stamp
    _ = load_prior  # the prior still loads on its own after all this

    # scripts/codebook_entropy.py: one entropy per active codebook, each within [0, ln K]
    h, top = script("codebook_entropy").codebook_entropy(tmp_path / "straight", episodes=2)
    assert len(h) == 2 and top == pytest.approx(np.log(ac.policy.classes)) and all(0 <= x <= top + 1e-5 for x in h)

    # Thrown balls at the trained policy, zero-shot, on the run's humanoid with a pool of balls.
    from motok.control.highlevel.perturb import perturb_run
    pr = perturb_run(tmp_path / "straight", episodes=2, render=tmp_path / "balls.gif")
    assert pr["launched"] >= 1 and 0 <= pr["hits"] <= pr["launched"] and pr["episodes"] == 2
    assert (tmp_path / "straight" / "perturb.json").exists() and (tmp_path / "balls.gif").stat().st_size > 0
    from motok.control.highlevel.perturb import PerturbConfig
    before = (tmp_path / "straight" / "perturb.json").read_text()
    slow = perturb_run(tmp_path / "straight", episodes=1, cfg=PerturbConfig(period=0.6))
    assert slow["written"].endswith("perturb_period0.6.json") and slow["config"]["period"] == 0.6
    assert (tmp_path / "straight" / "perturb.json").read_text() == before  # the paper's result stays


def test_the_world_of_the_expert_is_the_world_of_its_prior_and_tasks(hum, walk_lib, small_dataset, tmp_path):
    """A PD-target filter an expert was trained through is its students' and their task policies'
    world: inherited when the recipe leaves it unset (and played so by the evaluations, which read
    the saved config), refused when the recipe sets another."""
    from motok.control.priors.model import DistillConfig, load_prior
    from motok.control.priors.distill import train as distill
    from motok.errors import UserError
    prior = tiny_prior_bundle(tmp_path, hum, walk_lib, small_dataset, target_filter=0.5)
    assert load_prior(prior)[0].env.target_filter == 0.5
    cfg = small_cfg(iterations=1, save_every=1000, eval_every=0)
    cfg.env.num_envs = 4
    cfg.ppo = replace(cfg.ppo, horizon=8, minibatch_size=16, epochs=1)
    train_from_prior(replace(cfg), prior, tmp_path / "nav", codebooks=2)
    assert load_task_run(tmp_path / "nav")[0].env.target_filter == 0.5
    cfg.env.target_filter = 1.0
    with pytest.raises(UserError, match=r"target_filter=1 but the prior .* acts through env.target_filter=0.5"):
        train_from_prior(replace(cfg), prior, tmp_path / "nav-other", codebooks=2)
    dcfg = DistillConfig(seed=0, iterations=1, save_every=1000, horizon=8, epochs=1, minibatch_size=32)
    dcfg.env.num_envs, dcfg.env.nthread, dcfg.env.target_filter = 4, 1, 0.8
    dcfg.prior = small_prior_config("hybrid")
    with pytest.raises(UserError, match=r"target_filter=0.8 but the expert"):
        distill(dcfg, tmp_path / "prior-other", tmp_path / "expert", walk_lib, data=small_dataset)


def test_in_betweening_is_evaluated_on_the_clips_of_another_split(tiny_prior, small_dataset, tmp_path):
    """Tables 2-3 read the test clips of a policy trained on others: `--data --split` gives the
    windows, and the result is written as eval_TASK_SPLIT.json with the split in its provenance."""
    from motok.data.dataset import MotionFile

    with MotionFile(small_dataset) as mf:
        test = [mf.names[i] for i in mf.split_indices("test")]
    assert test  # the slice has test clips
    cfg = small_cfg(task="inbetween", iterations=1)
    cfg.tasks.inbetween = replace(cfg.tasks.inbetween, window_seconds=1.0, num_keyframes=3, eval_keyframes=4,
                                  min_keyframe_gap_seconds=0.2)
    cfg.env.num_envs = 4
    cfg.ppo = replace(cfg.ppo, horizon=4, minibatch_size=16, epochs=1)
    train_from_prior(cfg, tiny_prior, tmp_path / "ib")
    res = evaluate_run(tmp_path / "ib", episodes=3, data=small_dataset, split="test", render=tmp_path / "ib.gif")
    assert res["written"].endswith("eval_inbetween_test.json") and res["episodes"] == 3
    assert res["keyframes_per_window"] == 4 and len(res["per_episode"]["success"]) == 3
    saved = json.loads((tmp_path / "ib" / "eval_inbetween_test.json").read_text())
    assert saved["provenance"]["config"]["split"] == "test" and (tmp_path / "ib.gif").stat().st_size > 0


def test_the_command_line_knows_every_task():
    from motok.cli.priors import EVAL_TASKS
    from motok.control.tasks import registry
    assert set(EVAL_TASKS) == {"imitation", *registry.names()}


def test_updates_that_leave_the_trust_region_are_reported_once(hum, walk_lib, small_dataset, tmp_path, capsys,
                                                                monkeypatch):
    """The continuous prior's Gaussian at too large an lr moved nats of KL per update and diverged
    while the curves looked like training (docs/results.md); the run now says so, once, and a run
    whose updates stay small says nothing."""
    from motok.control.rl import runner
    from motok.control.rl.ppo import KL_WARN

    prior = tiny_prior_bundle(tmp_path, hum, walk_lib, small_dataset, kind="continuous")
    monkeypatch.setattr(runner, "KL_WINDOW", 3)
    cfg = small_cfg(iterations=6)
    cfg.env.num_envs = 8
    cfg.ppo = replace(cfg.ppo, horizon=8, minibatch_size=16, epochs=4, clip=0.1, lr=1e-1)
    cfg.net = HighLevelNetConfig(policy=[32], value=[32], std=0.02)
    capsys.readouterr()
    train_from_prior(replace(cfg), prior, tmp_path / "wild")
    rows = [json.loads(x) for x in (tmp_path / "wild" / "metrics.jsonl").read_text().splitlines()]
    said = " ".join(capsys.readouterr().err.split())
    assert sorted(r["approx_kl"] for r in rows)[len(rows) // 2] > KL_WARN  # the run the warning is for
    assert said.count("left the trust region") == 1 and "ppo.lr" in said
    cfg.ppo = replace(cfg.ppo, lr=1e-7)
    train_from_prior(replace(cfg), prior, tmp_path / "tame")
    rows = [json.loads(x) for x in (tmp_path / "tame" / "metrics.jsonl").read_text().splitlines()]
    assert max(r["approx_kl"] for r in rows) < KL_WARN
    assert "trust region" not in capsys.readouterr().err
