"""The physics expert (motok.control.expert.train): Eq. 10 product reward, learning on a trivial task,
exact resume, and the `motok control expert` commands."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from motok.control.expert.model import ExpertConfig
from motok.control.expert.train import ExpertTrainer, imitation_mdp, train
from motok.control.mdp.actions import ActionConfig
from motok.control.mdp.rewards import ImitationConfig, imitation_errors, imitation_reward
from motok.errors import UserError
from motok.control.tasks.imitation import ImitationTaskConfig
from motok.sim.env import SimConfig
from motok.sim.kinematics import body_states
from motok.sim.reference import ReferenceLibrary, load_library


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def walk_lib(hum, small_dataset, tmp_path_factory):
    return load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp("expert-ref"))


def standing_library(hum, seconds: float = 6.0) -> ReferenceLibrary:
    """A still standing pose: the reference of the trivial 'stand still' task. The rest pose is a
    T-pose whose arms sag under the weak shoulder gains, so the reference is where PD targets 0
    let it settle (arms lowered): exactly holdable with targets 0, i.e. residual actions a = -q."""
    import mujoco

    m, d = hum.model, mujoco.MjData(hum.model)
    for _ in range(int(2.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    T = int(seconds * hum.control_hz)
    qpos = np.repeat(d.qpos[None], T, 0)
    qvel = np.zeros((T, hum.model.nv))
    st = body_states(hum, qpos, qvel)
    return ReferenceLibrary(names=["stand"], fps=float(hum.control_hz), starts=np.array([0, T]), qpos=qpos,
                            qvel=qvel, joints=st["body_pos"].copy(), **st)


def small_cfg(**kw) -> ExpertConfig:
    cfg = ExpertConfig(seed=0, save_every=1000)
    cfg.env.num_envs, cfg.ppo.horizon, cfg.ppo.minibatch_size = 8, 16, 64
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [64, 64]
    cfg.net.latent_dim = 16
    cfg.amp.hidden, cfg.amp.batch_size, cfg.amp.updates = [32, 32], 64, 2
    for k, v in kw.items():
        setattr(cfg, k, v)
    return cfg


def test_imitation_reward_terms_against_hand_values():
    J = 4
    pos, ref = np.zeros((1, J, 3)), np.zeros((1, J, 3))
    pos[0, 0] = [0.1, 0.0, 0.0]  # root off by 10 cm, which moves every root-relative effector...
    pos[0, 1:] = pos[0, 0]
    pos[0, 2] += [0.0, 0.05, 0.0]  # ...except the one also off by 5 cm relative to the root
    q, q_ref = np.array([[0.1, -0.2, 0.0]]), np.zeros((1, 3))
    qd, qd_ref = np.array([[1.0, 2.0, 3.0]]), np.zeros((1, 3))
    err = imitation_errors(pos, ref, q, q_ref, qd, qd_ref, [1, 2])
    assert err["root"][0] == pytest.approx(0.01)
    assert err["q"][0] == pytest.approx(0.05)  # sum over hinges
    assert err["alpha"][0] == pytest.approx(14 / 3)  # mean over hinges
    assert err["ee"][0] == pytest.approx(0.0025)  # root-relative, summed over effectors
    r = imitation_reward(err, ImitationConfig())
    hand = {"r_root": math.exp(-10 * 0.01), "r_q": math.exp(-2 * 0.05), "r_alpha": math.exp(-0.5 * 14 / 3),
            "r_ee": math.exp(-40 * 0.0025)}
    for k, v in hand.items():
        assert r[k][0] == pytest.approx(v)
    assert r["r_im"][0] == pytest.approx(math.prod(hand.values()))  # Eq. 10 is a product


def test_imitation_reward_is_one_on_the_reference(hum, walk_lib):
    """Eq. 10 after one step of PD tracking (zero residual on the reference) is close to 1."""
    mdp = imitation_mdp(hum, walk_lib, SimConfig(num_envs=16), ImitationTaskConfig(), ActionConfig("reference"), 0)
    mdp.reset(clips=[0, 1, 2] * 5 + [0], frames=[3] * 16)
    t = mdp.task
    L = walk_lib
    g = L.frame_index(t.clip, t.frame)
    env = mdp.env
    err = imitation_errors(env.bodies.pos, L.body_pos[g], env.qpos[:, 7:], L.qpos[g, 7:], env.qvel[:, 6:],
                           L.qvel[g, 6:], env.end_effectors)
    assert imitation_reward(err, ImitationConfig())["r_im"].min() > 0.99  # only the root, lifted on reset, is off
    _, _, r, term, _, _ = mdp.step(np.zeros((16, env.action_dim)))
    assert r["r_im"].min() > 0.5 and not term.any()


def test_short_ppo_run_raises_the_return_of_standing_still(hum):
    """The issue's trivial task: hold a standing reference, r = r_im (Eq. 10). A fresh policy
    already stands (zero action = PD on the reference), so it starts miscalibrated: constant
    offsets of up to 0.3 rad on every hinge, which topple it within a second. PPO must learn to
    cancel them. 48 iterations of 16 envs x 32 steps (25k samples): the mean episode return of
    the last 5 iterations is 2.1x the first 5 (at 32 iterations: 1.4x-2.8x over seeds 0-4)."""
    cfg = small_cfg(iterations=48, w_im=1.0, w_style=0.0)
    cfg.env.num_envs, cfg.task.max_episode_seconds, cfg.env.nthread = 16, 3.0, 1
    cfg.action.base, cfg.task.termination = "reference", "mean"
    cfg.ppo.horizon, cfg.ppo.minibatch_size, cfg.ppo.lr = 32, 128, 3e-4
    cfg.net.log_std, cfg.amp.enabled = math.log(0.055), False
    tr = ExpertTrainer(cfg, hum, standing_library(hum))
    bias = tr.ac.policy.decoder[-1].bias
    with torch.no_grad():
        bias.copy_((torch.rand(bias.shape, generator=torch.Generator().manual_seed(0)) * 2 - 1) * 0.3)
    offsets = bias.detach().clone()
    tr.start_segment()
    rows = [tr.step() for _ in range(cfg.iterations)]
    ret = [r["episode_return"] for r in rows if "episode_return" in r]
    assert len(ret) >= 40 and np.mean(ret[-5:]) > 1.4 * np.mean(ret[:5]), np.round(ret, 2)
    assert np.mean([r["r_im"] for r in rows[-5:]]) > 1.1 * np.mean([r["r_im"] for r in rows[:5]])
    # the learning went where it should: the decoder's output offsets shrank towards zero
    assert bias.detach().abs().mean() < offsets.abs().mean()


def test_expert_loop_on_a_standing_reference_logs_its_metrics(hum, tmp_path):
    # The loop without AMP, and its log (learning: the test above and test_ppo.py).
    cfg = small_cfg(iterations=3, w_im=1.0, w_style=0.0, eval_every=2)
    cfg.task.max_episode_seconds, cfg.ppo.horizon = 0.5, 15
    out = train(cfg, tmp_path / "run", hum, standing_library(hum))
    assert out["iterations"] == 3 and out["samples"] == 3 * 8 * 15
    rows = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3]
    assert ["eval_success" in r for r in rows] == [False, True, False]  # eval_every=2
    assert 0.0 <= rows[1]["eval_success_any_body"] <= rows[1]["eval_success"] <= 1.0 and rows[1]["eval_seconds"] > 0
    # the feet during training, beside the clips' own: a standing reference's soles do not move
    assert rows[1]["eval_ref_sole_slip_cm_s"] == 0 and rows[1]["eval_sole_slip_cm_s"] >= 0
    assert {"eval_skate_cm_s", "eval_jitter_m_s3", "eval_ref_jitter_m_s3"} <= rows[1].keys()
    for r in rows:
        assert 0.0 < r["r_im"] <= 1.0 and "r_style" not in r and r["samples_per_s"] > 0  # no AMP hook
    done = [r for r in rows if "success" in r]
    assert done and all(0.0 <= r["success"] <= 1.0 and 0.0 < r["episode_seconds"] <= 0.5 for r in done)
    meta = json.loads((tmp_path / "run" / "bundle.json").read_text())
    assert not any(k.startswith("disc.") for k in load_file(tmp_path / "run" / "model.safetensors"))
    assert meta["extra"]["normaliser"] == ["ac.norm.mean", "ac.norm.var", "ac.norm.count"]


def test_a_warm_start_begins_from_the_other_runs_weights_and_not_its_counters(hum, walk_lib, tmp_path):
    cfg = small_cfg(iterations=4, save_every=2)
    train(cfg, tmp_path / "first", hum, walk_lib, until=2)
    train(cfg, tmp_path / "warm", hum, walk_lib, init=tmp_path / "first", until=0)
    a, b = load_file(tmp_path / "first" / "model.safetensors"), load_file(tmp_path / "warm" / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)  # policy, critic, normaliser, disc
    meta = json.loads((tmp_path / "warm" / "bundle.json").read_text())
    assert meta["extra"]["iteration"] == 0 and meta["extra"]["init_info"]["iteration"] == 2
    out = train(cfg, tmp_path / "warm", hum, walk_lib, resume=True, until=2)
    assert out["iterations"] == 2 and out["samples"] == 2 * 8 * cfg.ppo.horizon
    c = load_file(tmp_path / "warm" / "model.safetensors")
    assert not torch.equal(a["ac.norm.count"], c["ac.norm.count"])  # it trained on from there
    wide = replace(cfg, net=replace(cfg.net, encoder=[32, 32]))
    with pytest.raises(UserError, match="do not fit"):
        train(wide, tmp_path / "bad", hum, walk_lib, init=tmp_path / "first", until=0)


def test_sigterm_stops_a_training_at_its_next_checkpoint_and_it_resumes_exactly(hum, walk_lib, tmp_path, monkeypatch,
                                                                                 capsys):
    import signal
    import sys

    from motok.control.rl import runner
    from motok.control.expert.model import KIND

    cfg = small_cfg(iterations=6, save_every=2)
    before = signal.getsignal(signal.SIGTERM)

    def make(d):
        tr = ExpertTrainer(cfg, hum, walk_lib, d)
        step = tr.step

        def step_and_signal():
            out = step()
            if tr.iteration == 3:  # a SIGTERM mid-segment: the run goes on to iteration 4, saves, stops
                signal.raise_signal(signal.SIGTERM)
            return out
        tr.step = step_and_signal
        return tr

    argv = ["motok", "control", "expert", "train", "-d", "walk.h5", "-o", str(tmp_path / "stopped"), "--force"]
    monkeypatch.setattr(sys, "argv", argv)
    out = runner.train(make, cfg, tmp_path / "stopped", hum, kind=KIND)
    assert out["iterations"] == 4 and signal.getsignal(signal.SIGTERM) is before
    # it says where it stopped and the exact command that continues it, as Ctrl-C does
    said = " ".join(capsys.readouterr().err.split())
    assert f"stopped at iteration 4 on request (SIGTERM); last checkpoint: iteration 4 in {tmp_path / 'stopped'}" in said
    assert (f"continue exactly from there with: motok control expert train -d walk.h5 -o {tmp_path / 'stopped'} "
            f"--resume") in said, said
    assert json.loads((tmp_path / "stopped" / "bundle.json").read_text())["extra"]["iteration"] == 4
    train(cfg, tmp_path / "stopped", hum, walk_lib, resume=True)
    train(cfg, tmp_path / "straight", hum, walk_lib)
    a, b = load_file(tmp_path / "straight" / "model.safetensors"), load_file(tmp_path / "stopped" / "model.safetensors")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_expert_training_resumes_exactly(hum, walk_lib, tmp_path):
    cfg = small_cfg(iterations=4, save_every=2)
    train(cfg, tmp_path / "straight", hum, walk_lib)
    train(cfg, tmp_path / "split", hum, walk_lib, until=2)
    assert json.loads((tmp_path / "split" / "bundle.json").read_text())["extra"]["iteration"] == 2
    train(cfg, tmp_path / "split", hum, walk_lib, resume=True)
    a, b = load_file(tmp_path / "straight" / "model.safetensors"), load_file(tmp_path / "split" / "model.safetensors")
    assert a.keys() == b.keys() and any(k.startswith("disc.") for k in a) and "ac.norm.mean" in a
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # with difficulty sampling every iteration: its failures survive the resume
    hard = replace(cfg, sampling=replace(cfg.sampling, hard_fraction=0.7, every=1, eval_batch=2))
    train(hard, tmp_path / "hard", hum, walk_lib)
    train(hard, tmp_path / "hard_split", hum, walk_lib, until=2)
    train(hard, tmp_path / "hard_split", hum, walk_lib, resume=True)
    h, hs = load_file(tmp_path / "hard" / "model.safetensors"), load_file(tmp_path / "hard_split" / "model.safetensors")
    assert all(torch.equal(h[k], hs[k]) for k in h)
    from motok.checkpoint import load_bundle
    sampler = load_bundle(tmp_path / "hard_split", "control-expert", with_train_state=True)[2]["shared"]["sampler"]
    assert sampler["measured_at"] == 4 and sampler["failure"].shape == (3,)
    rows = [json.loads(x) for x in (tmp_path / "hard_split" / "metrics.jsonl").read_text().splitlines()]
    assert all("train_success" in r and "hard_share" in r for r in rows) and len(rows) == 4
    # evaluation passes in between change nothing of the training (no RNG drawn, no state touched)
    train(replace(cfg, eval_every=1), tmp_path / "evaluated", hum, walk_lib)
    c = load_file(tmp_path / "evaluated" / "model.safetensors")
    assert all(torch.equal(a[k], c[k]) for k in a)
    la = (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()
    lb = (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()
    strip = lambda s: {k: v for k, v in json.loads(s).items() if not k.endswith("_s")}  # noqa: E731 (timings differ)
    assert [strip(x) for x in la] == [strip(x) for x in lb]


def test_control_expert_commands(small_dataset, hum, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from motok.cli.main import app

    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    recipe = tmp_path / "r.yaml"
    recipe.write_text("iterations: 3\nenv: {num_envs: 4}\nppo: {horizon: 8, minibatch_size: 32}\n"
                      "net: {encoder: [32], decoder: [32], value: [32]}\n"
                      "amp: {hidden: [16], batch_size: 32, updates: 1}\n")
    run = tmp_path / "run"
    runner = CliRunner()
    r = runner.invoke(app, ["--quiet", "control", "expert", "train", "--data", str(small_dataset), "--clips",
                            "dataset-2_walk_normal_*", "--recipe", str(recipe), "--humanoid", str(hum.path),
                            "-o", str(run), "--until", "1", "--json"])
    assert r.exit_code == 0, r.output
    meta = json.loads((run / "bundle.json").read_text())
    assert meta["extra"]["iteration"] == 1 and meta["config"]["iterations"] == 3  # stopped early, schedule kept
    assert meta["kind"] == "control-expert" and meta["extra"]["obs_dim"] == 102 and meta["extra"]["action_dim"] == 37
    assert len(meta["extra"]["mjcf_sha256"]) == 64 and (run / "humanoid.xml").exists()
    r = runner.invoke(app, ["--quiet", "control", "expert", "eval", "--run", str(run), "--clips",
                            "dataset-2_walk_normal_00[12]", "--render", str(tmp_path / "e.gif"), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads((run / "eval.json").read_text())
    o = res["overall"]
    assert o["clips"] == 2 and 0.0 <= o["success_rate"] <= 1.0
    # the overall errors are the clips' errors weighted by the time each was played
    w = np.array([v["seconds"] for v in res["clips"].values()])
    for k in ("mpjpe_mm", "g_mpjpe_mm"):
        per = np.array([v[k] for v in res["clips"].values()])
        assert (per > 0).all() and o[k] == pytest.approx(float((per * w).sum() / w.sum()), rel=1e-9)
    assert all(v["seconds"] > 0 for v in res["clips"].values()) and (tmp_path / "e.gif").exists()
    assert o["success_rate_any_body"] <= o["success_rate"] and o["termination"] == "any body error > 0.5 m"
    # what was measured: the checkpoint's iteration and hash, and the data's hash
    assert res["checkpoint"]["iteration"] == 1 and res["checkpoint"]["mjcf_sha256"] == meta["extra"]["mjcf_sha256"]
    assert res["provenance"]["inputs"][str(small_dataset)] == meta["provenance"]["inputs"][str(small_dataset)]
    r = runner.invoke(app, ["--quiet", "control", "expert", "eval", "--run", str(run), "--clips",
                            "dataset-2_walk_normal_00[12]", "--termination", "mean", "--distance", "0.02", "--json"])
    strict = json.loads(r.output)  # any body > 0.5 m implies a mean > 0.5 / 21 > 0.02 m: no clip lasts longer
    assert r.exit_code == 0 and strict["overall"]["termination"] == "mean body error > 0.02 m"
    assert all(v["seconds"] <= res["clips"][k]["seconds"] for k, v in strict["clips"].items())
    monkeypatch.setenv("COLUMNS", "80")  # the table fits a standard terminal: no header or number is cut
    r = runner.invoke(app, ["control", "expert", "eval", "--run", str(run), "--clips", "dataset-2_walk_normal_00[12]"])
    assert r.exit_code == 0 and "dataset-2_walk_normal_*" in r.output and "…" not in r.output, r.output
    rows = [line.split("│")[1:-1] for line in r.output.splitlines() if line.startswith("│")]
    assert [c.strip() for c in rows[0][:1] + rows[1][:1]] == ["001", "002"] and rows[2][0].strip() == "overall"
    assert float(rows[0][3]) == pytest.approx(res["clips"]["dataset-2_walk_normal_001"]["mpjpe_mm"], abs=0.05)
    r = runner.invoke(app, ["--quiet", "control", "expert", "eval", "--run", str(run), "--split", "test", "--json"])
    assert r.exit_code == 0, r.output
    test = json.loads((run / "eval_test.json").read_text())
    from motok.data.dataset import select_clips
    names = select_clips(small_dataset, None, "test")
    assert sorted(test["clips"]) == sorted(names) and test["groups"]["content"]["walk"]["clips"] == len(names)
    assert test["groups"]["style"]["normal"]["success_rate"] == test["overall"]["success_rate"]
    r = runner.invoke(app, ["control", "expert", "train", "--data", str(small_dataset), "--clips", "nope*",
                            "-o", str(tmp_path / "x")])
    assert r.exit_code == 2 and "nope" in r.output
    r = runner.invoke(app, ["control", "expert", "eval", "--run", str(run), "--split", "tets"])
    assert r.exit_code == 2 and "no split 'tets'" in r.output


def test_torchrun_two_ranks_keep_identical_weights(small_dataset, hum, tmp_path):
    """Each rank steps its own environments (its own task and AMP streams); gradients, the KL
    early stop and the normaliser are averaged, so both ranks hold the same weights throughout."""
    import os
    import socket
    import subprocess
    import sys

    from motok.checkpoint import load_bundle

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    recipe = tmp_path / "r.yaml"
    recipe.write_text("iterations: 3\nsave_every: 2\nenv: {num_envs: 4, nthread: 1}\nppo: {horizon: 8, minibatch_size: 16}\n"
                      "net: {encoder: [32], decoder: [32], value: [32]}\n"
                      "amp: {hidden: [16], batch_size: 16, updates: 1, replay_size: 64}\n")
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr", "127.0.0.1",
           "--master_port", str(port), "-m", "motok.cli.main", "-q", "control", "expert", "train",
           "--data", str(small_dataset), "--clips", "dataset-2_walk_normal_00[1-4]", "--recipe", str(recipe),
           "--humanoid", str(hum.path), "-o", str(run)]
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1", "OMP_NUM_THREADS": "1", "MOTOK_CACHE": str(tmp_path / "cache")}
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-4000:]
    meta, state, ts = load_bundle(run, "control-expert", with_train_state=True)
    hashes = meta["extra"]["rank_state_sha256"]
    assert len(hashes) == 2 and hashes[0] == hashes[1] == meta["model_sha256"]
    assert meta["extra"]["world_size"] == 2 and ts["world_size"] == 2 and ts["shared"]["iteration"] == 3
    assert meta["extra"]["samples"] == 3 * 2 * 4 * 8  # both ranks' samples
    a, b = ts["ranks"]
    assert a["task_rng"] != b["task_rng"] and not torch.equal(a["replay"]["data"], b["replay"]["data"])
    assert [json.loads(x)["iteration"] for x in (run / "metrics.jsonl").read_text().splitlines()] == [1, 2, 3]


def test_control_recipes_load_with_their_measured_choices():
    from pathlib import Path

    from motok.config import load_config
    root = Path(__file__).resolve().parent.parent / "recipes" / "control"
    small, paper, set2 = (load_config(ExpertConfig, root / f"{n}.yaml") for n in ("expert", "expert_paper", "expert_set2"))
    for cfg in (paper, set2):  # whole-dataset recipes: difficulty sampling and a stratified eval subset
        assert cfg.sampling.hard_fraction == 0.5 and cfg.sampling.every > 0 and cfg.eval_per_group == 2
    assert small.sampling.hard_fraction == 0.0 and set2.update_threads == 2
    # the same physics settings but for the feet levers the whole-dataset recipe trains through
    # (docs/sim.md "Feet"): the PD-target filter at 0.3 and ankles at half stiffness
    assert set2.env.target_filter == 0.3 and replace(set2.env, target_filter=None) == small.env
    assert set2.humanoid.ankle_stiffness_scale == 0.5 and small.humanoid == paper.humanoid == type(small.humanoid)()
    for cfg in (small, paper, set2):
        assert cfg.action.base == "reference" and cfg.task.termination == "mean" and cfg.eval_every > 0
        assert (cfg.w_im, cfg.w_style) == (0.5, 0.5) and cfg.ppo.gamma == 0.99 and cfg.ppo.lam == 0.95
    assert paper.env.num_envs >= 4096 > small.env.num_envs


def test_overlapped_groups_give_the_same_transitions_as_the_sequential_schedule(hum, walk_lib):
    """Two environment groups taking turns (one's physics on a worker thread while the policy runs
    on the other) collect exactly what the same schedule collects without threads."""
    def rollout(threaded: bool):
        cfg = small_cfg()
        cfg.env.groups = 2
        tr = ExpertTrainer(cfg, hum, walk_lib)
        tr.collector.threaded = threaded
        tr.start_segment()
        out = [tr.collector.collect() for _ in range(3)]
        return out, tr

    (a, ta), (b, tb) = rollout(True), rollout(False)
    assert ta.collector.threaded and not tb.collector.threaded and ta.collector.num_envs == 8
    for (ra, va, sa), (rb, vb, sb) in zip(a, b):
        for k in ("x", "actions", "logp", "values", "rewards", "final_values", "terminated", "truncated"):
            assert torch.equal(getattr(ra, k), getattr(rb, k)), k
        assert torch.equal(va, vb) and sa == sb
    with pytest.raises(ValueError, match="groups must divide"):
        cfg = small_cfg()
        cfg.env.groups = 3
        ExpertTrainer(cfg, hum, walk_lib)
