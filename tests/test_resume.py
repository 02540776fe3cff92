"""Identity checks and exact resume: a resumed run continues on the inputs it was trained on (data
set, expert, prior, warm start, clips; the humanoid: tests/test_feet.py) and with the settings
it was trained with, or refuses with what differs; a flag that cannot apply exactly says so."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from motok.cli.main import app
from motok.config import ConfigError
from motok.errors import MotokError, UserError

from tiny_runs import small_prior_config, tree  # noqa: F401  (a fixture)

pytestmark = pytest.mark.usefixtures("one_thread")


def expert_cfg(seed: int = 0, **kw):
    from motok.control.expert.model import ExpertConfig

    cfg = ExpertConfig(seed=seed, iterations=1, save_every=1000)
    cfg.env.num_envs, cfg.env.nthread, cfg.ppo.horizon, cfg.ppo.minibatch_size = 4, 1, 8, 32
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [16]
    cfg.net.latent_dim = 8
    cfg.amp.enabled = False
    cfg.action.base, cfg.task.termination = "reference", "mean"
    return replace(cfg, **kw)


def distill_cfg(seed: int = 0, **kw):
    from motok.control.priors.model import DistillConfig

    cfg = DistillConfig(seed=seed, iterations=4, save_every=2, horizon=8, epochs=1, minibatch_size=32)
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.task.termination = "mean"
    cfg.prior = small_prior_config("hybrid")
    return replace(cfg, **kw)


def task_cfg():
    from motok.control.highlevel.policy import HighLevelNetConfig, TaskTrainConfig

    cfg = TaskTrainConfig(seed=0, iterations=2, save_every=1, task="navigation")
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.ppo = replace(cfg.ppo, horizon=8, epochs=1, minibatch_size=32)
    cfg.net = HighLevelNetConfig(policy=[16], value=[16])
    return cfg


@pytest.fixture(scope="module")
def runs(hum, small_dataset, tmp_path_factory):
    """Two 1-iteration experts (seeds 0 and 1), two hybrid priors distilled from the first (P
    stopped at iteration 2 of 4, Q finished) and a task policy over P (stopped at 1 of 2)."""
    from motok.control.expert.train import train as train_expert
    from motok.control.highlevel.train import train_from_prior
    from motok.control.priors.distill import train as distill
    from motok.sim.reference import load_library

    root = tmp_path_factory.mktemp("resume-runs")
    lib = load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=root / "cache")
    for name, seed in (("expertA", 0), ("expertB", 1)):
        train_expert(expert_cfg(seed), root / name, hum, lib, data=small_dataset)
    distill(distill_cfg(), root / "P", root / "expertA", lib, data=small_dataset, until=2)
    distill(distill_cfg(1, iterations=2), root / "Q", root / "expertA", lib, data=small_dataset)
    train_from_prior(task_cfg(), root / "P", root / "T", codebooks=2, until=1)
    return root, lib


def _unchanged(run: Path):
    return (run / "bundle.json").read_bytes(), (run / "model.safetensors").read_bytes()


# --------------------------------------------------------------------------- identity

def test_distill_resumed_with_another_expert_is_refused(runs, small_dataset):
    from motok.control.priors.distill import train as distill

    root, lib = runs
    before = _unchanged(root / "P")
    with pytest.raises(UserError, match=r"--expert .*expertB: .* was made from another expert, .*expertA"):
        distill(distill_cfg(), root / "P", root / "expertB", lib, data=small_dataset, resume=True)
    assert _unchanged(root / "P") == before  # the teacher's record is not overwritten


def test_task_policy_resumed_over_another_prior_is_refused(runs):
    from motok.control.highlevel.train import train_from_prior

    root, _ = runs
    before = _unchanged(root / "T")
    with pytest.raises(UserError, match=r"--prior .*Q: .* was made from another prior, .*P \(weights"):
        train_from_prior(task_cfg(), root / "Q", root / "T", codebooks=2, resume=True)
    assert _unchanged(root / "T") == before


def test_a_resume_on_another_data_set_with_the_same_name_is_refused(runs, hum, small_dataset, tmp_path):
    from motok.control.expert.train import train as train_expert

    root, lib = runs
    other = tmp_path / Path(small_dataset).name  # the same name, other content
    shutil.copyfile(small_dataset, other)
    with h5py.File(other, "r+") as f:
        f.attrs["fps"] = 30.0
    with pytest.raises(UserError, match="was trained on another data set"):
        train_expert(expert_cfg(), root / "expertA", hum, lib, data=other, resume=True)


def test_a_resume_on_other_clips_is_refused(runs, hum, small_dataset):
    from motok.control.expert.train import train as train_expert
    from motok.sim.reference import load_library

    root, _ = runs
    fewer = load_library(hum, small_dataset, clips=[0, 1], cache_dir=root / "cache")
    with pytest.raises(UserError, match="was trained on 3 clips, this command selects 2"):
        train_expert(expert_cfg(), root / "expertA", hum, fewer, data=small_dataset, resume=True)


def test_a_warm_start_is_kept_on_resume_and_another_is_refused(runs, hum, tmp_path, small_dataset):
    import json

    from motok.control.expert.train import train as train_expert

    root, lib = runs
    cfg = expert_cfg(iterations=2, save_every=1)
    train_expert(cfg, tmp_path / "warm", hum, lib, data=small_dataset, init=root / "expertA", until=1)
    train_expert(cfg, tmp_path / "warm", hum, lib, data=small_dataset, resume=True)  # --init left out
    meta = json.loads((tmp_path / "warm" / "bundle.json").read_text())
    assert meta["extra"]["iteration"] == 2 and meta["extra"]["init_info"]["absolute"] == str(root / "expertA")
    with pytest.raises(UserError, match="--init .*expertB: .* was made from another init"):
        train_expert(cfg, tmp_path / "warm", hum, lib, data=small_dataset, init=root / "expertB", resume=True)


def test_a_gpt_resumed_on_other_tokens_is_refused(tree, tmp_path):
    from motok.gpt.train import resolve_config, train

    other = tmp_path / "tokens.h5"
    shutil.copyfile(tree / "tokens.h5", other)
    with h5py.File(other, "r+") as f:
        f.attrs["note"] = "another tokens artifact"
    before = _unchanged(tree / "gpt")
    with pytest.raises(MotokError, match="is not the tokens artifact .* was trained on"):
        train(resolve_config(None, [], tree / "gpt", resume=True), other, tree / "gpt", resume=True)
    assert _unchanged(tree / "gpt") == before


# --------------------------------------------------------------------------- settings

def test_a_changed_setting_on_resume_is_refused_with_what_differs(runs, hum, small_dataset):
    from motok.control.expert.model import KIND, ExpertConfig
    from motok.control.expert.train import train as train_expert
    from motok.resume import resolve_config

    root, lib = runs
    with pytest.raises(ConfigError, match=r"this would change ppo.lr 0.0003 -> 1e-05"):
        resolve_config(ExpertConfig, None, ["ppo.lr=1e-5"], root / "expertA", KIND, True)
    with pytest.raises(ConfigError, match="env.num_envs 4 -> 8"):  # a trainer called from code too
        train_expert(expert_cfg(env=replace(expert_cfg().env, num_envs=8)), root / "expertA", hum, lib,
                     data=small_dataset, resume=True)
    # no recipe: the saved config, not the defaults; the length may change under a constant schedule...
    assert resolve_config(ExpertConfig, None, [], root / "expertA", KIND, True) == expert_cfg()
    assert resolve_config(ExpertConfig, None, ["iterations=3"], root / "expertA", KIND, True).iterations == 3
    # ...but not where the learning rate's schedule spans it
    assert expert_cfg(ppo=replace(expert_cfg().ppo, lr_schedule="linear")).resume_may_change() == set()


def test_a_changed_set_on_resume_is_one_line_on_the_command_line(tree, small_dataset):
    r = CliRunner().invoke(app, ["tokenize", "train", "-d", str(small_dataset), "-o", str(tree / "tok"), "--resume",
                                 "--set", "optim.lr=0.5"])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and "--resume continues" in lines[0] and "optim.lr 0.0002 -> 0.5" in lines[0], r.output
    r = CliRunner().invoke(app, ["gpt", "train", "-d", str(tree / "tokens.h5"), "-o", str(tree / "gpt"), "--resume",
                                 "--set", "model.dim=64", "--set", "iterations=3"])
    assert r.exit_code == 2 and "model.dim 32 -> 64" in r.output and "iterations 2 -> 3" not in r.output, r.output


def test_until_past_the_iterations_is_refused(runs, hum, small_dataset, tmp_path):
    from motok.control.expert.train import train as train_expert

    _, lib = runs
    with pytest.raises(UserError, match="--until 5 is past the run's 1 iterations"):
        train_expert(expert_cfg(), tmp_path / "new", hum, lib, data=small_dataset, until=5)
    assert not (tmp_path / "new").exists()


def test_a_stop_between_checkpoints_says_resuming_is_not_exact(runs, hum, small_dataset, tmp_path, capsys):
    from motok.control.expert.train import train as train_expert

    _, lib = runs
    cfg = expert_cfg(iterations=4, save_every=2)

    def said():
        return " ".join(capsys.readouterr().err.split())  # the console wraps long notes
    train_expert(cfg, tmp_path / "r", hum, lib, data=small_dataset, until=1)
    assert "--until 1 is between checkpoints (save_every 2)" in said()
    train_expert(cfg, tmp_path / "r", hum, lib, data=small_dataset, resume=True, until=2)
    assert "stopped at iteration 1, between checkpoints" in said()
    train_expert(cfg, tmp_path / "r", hum, lib, data=small_dataset, resume=True, until=2)
    assert "already at iteration 2: nothing to train" in said()
