"""Unconditional generation from a distilled prior (motok.control.priors.generate, `motok control
generate`): uniform codes from the first M codebooks only, prior draws for the continuous kind, a
motion artifact of the requested length and count that the other tools read, the same motion for
the same seed."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.control.priors.model import load_prior
from motok.control.priors.generate import generate, rollout, sample_latent
from motok.control.priors.load import check_codebooks
from motok.control.mdp.resets import reference_state
from motok.control.priors.model import LatentPrior
from motok.data.dataset import MotionFile
from motok.errors import UserError
from motok.sim.reference import load_library
from tiny_runs import small_prior_config, tiny_prior_bundle

pytestmark = pytest.mark.usefixtures("one_thread")


small = small_prior_config


@pytest.fixture(scope="module")
def walk_lib(hum, small_dataset, tmp_path_factory):
    return load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp("gen-ref"))


@pytest.fixture(scope="module")
def tiny_prior(hum, walk_lib, small_dataset, tmp_path_factory):
    """A hybrid prior with 4 codebooks: untrained, but a real bundle with every part generation reads."""
    return tiny_prior_bundle(tmp_path_factory.mktemp("gen-runs"), hum, walk_lib, small_dataset)


# ---------------------------------------------------------------------- the draws

@pytest.mark.parametrize("kind,m", [("hybrid", 2), ("discrete+", 3), ("discrete", 1), ("hybrid-vq", 1)])
def test_codes_are_uniform_over_the_first_m_codebooks_only(kind, m):
    torch.manual_seed(0)
    model = LatentPrior(small(kind), obs_dim=10, goal_dim=6, action_dim=4).eval()
    s = torch.randn(8000, 10)
    z, idx = sample_latent(model, s, m, torch.Generator().manual_seed(0))
    K = model.quantizer.codebook_size
    assert idx.shape == (8000, m) and idx.min() >= 0 and idx.max() < K
    for col in idx.T:  # every code of every sampled codebook, about equally often (8000 / K each)
        counts = torch.bincount(col, minlength=K).float()
        assert counts.min() > 0.6 * 8000 / K and counts.max() < 1.4 * 8000 / K
    books = model.codebooks()
    want = sum(books[j][idx[:, j]] for j in range(m))  # codebooks m+1.. contribute nothing
    if kind == "hybrid" or kind == "hybrid-vq":
        want = want + model.prior_latent(s)[0]
    assert torch.allclose(z, want, atol=1e-5)
    assert torch.allclose(z, model.codes_to_latent(s, idx, m), atol=1e-6)
    # independent across rows: no two neighbouring rows share all their codes more often than chance
    assert (idx[1:] == idx[:-1]).all(1).float().mean() < 0.1


def test_continuous_draws_come_from_the_prior_gaussian():
    torch.manual_seed(0)
    model = LatentPrior(small("continuous"), obs_dim=10, goal_dim=6, action_dim=4).eval()
    s = torch.randn(1, 10).expand(20000, 10)
    z, idx = sample_latent(model, s, 0, torch.Generator().manual_seed(0))
    with torch.no_grad():
        mu, log_std = model.prior_latent(s[:1])
    assert idx is None
    assert torch.allclose(z.mean(0), mu[0], atol=0.05 * float(log_std.exp().max()) + 1e-3)
    assert torch.allclose(z.std(0), log_std.exp()[0], rtol=0.05)


def test_the_number_of_codebooks_is_checked():
    hybrid = LatentPrior(small("hybrid"), obs_dim=10, goal_dim=6, action_dim=4)
    assert check_codebooks(hybrid, None) == 4 and check_codebooks(hybrid, 2) == 2
    with pytest.raises(UserError, match="1..4"):
        check_codebooks(hybrid, 5)
    with pytest.raises(UserError, match="no codebooks"):
        check_codebooks(LatentPrior(small("continuous"), obs_dim=10, goal_dim=6, action_dim=4), 1)
    assert check_codebooks(hybrid, 0) == 0  # the prior alone: only where there is a prior network
    with pytest.raises(UserError, match="must be in 1..") as e:
        check_codebooks(LatentPrior(small("discrete+"), obs_dim=10, goal_dim=6, action_dim=4), 0)
    assert "z_p alone" not in str(e.value)


@pytest.mark.parametrize("kind", ["hybrid", "hybrid-vq"])
def test_zero_codebooks_is_the_prior_alone(kind):
    torch.manual_seed(0)
    model = LatentPrior(small(kind), obs_dim=10, goal_dim=6, action_dim=4).eval()
    s = torch.randn(64, 10)
    z, idx = sample_latent(model, s, 0, torch.Generator().manual_seed(0))
    with torch.no_grad():
        z_p = model.prior_latent(s)[0]
    assert idx.shape == (64, 0) and torch.equal(z, z_p)
    assert not torch.allclose(z, sample_latent(model, s, 1, torch.Generator().manual_seed(0))[0])


# ---------------------------------------------------------------------- the motion

def test_rollout_draws_from_m_codebooks_and_stops_a_sample_at_its_fall(tiny_prior, walk_lib):
    cfg, hum, model, _ = load_prior(tiny_prior)
    qpos, qvel = reference_state(walk_lib, np.array([0, 1, 2]), np.array([0, 5, 10]))
    res = rollout(model, hum, cfg.env, cfg.action, qpos, qvel, 40, 2, torch.Generator().manual_seed(0))
    idx = res["indices"]
    steps = int(res["alive"].sum(1).max())  # the loop stops once every sample has ended
    assert idx.shape == (40, 3, 2) and (idx[:steps - 1] >= 0).all() and idx.max() < 16
    for k in range(3):
        alive = res["alive"][k]
        kept = int(alive.sum())
        assert alive[:kept].all() and not alive[kept:].any()  # a prefix
        head = res["pos"][k, :kept, hum.skeleton.head, 2]
        assert (head >= 0.5).all()  # every frame kept is upright
        if res["stop"][k] == "fall":
            assert res["stop_step"][k] == kept - 1 and res["pos"][k, kept, hum.skeleton.head, 2] < 0.5
        else:
            assert res["stop"][k] == "" and kept == 41


def test_generation_writes_the_requested_motion_and_repeats_with_its_seed(tiny_prior, small_dataset, tmp_path,
                                                                         monkeypatch):
    # falls off (the head never goes below -1 m), so every sample runs its whole length
    a = generate(tiny_prior, tmp_path / "a.h5", codebooks=2, seconds=1.5, num_samples=3, seed=7, fall_height=-1.0)
    generate(tiny_prior, tmp_path / "b.h5", codebooks=2, seconds=1.5, num_samples=3, seed=7, fall_height=-1.0)
    generate(tiny_prior, tmp_path / "c.h5", codebooks=2, seconds=1.5, num_samples=3, seed=8, fall_height=-1.0)
    assert a["written"] == 3 and a["fell"] == 0 and a["codebooks"] == 2
    with MotionFile(tmp_path / "a.h5", "motion") as fa, MotionFile(tmp_path / "b.h5", "motion") as fb, \
            MotionFile(tmp_path / "c.h5", "motion") as fc, MotionFile(small_dataset) as ref:
        assert len(fa) == 3 and fa.fps == ref.fps and fa.names == ["hybrid-m2-000", "hybrid-m2-001", "hybrid-m2-002"]
        for name in fa.names:
            clip = fa.clip(name)
            # 1.5 s at the dataset's rate (30 frames at 20 fps; features drop one frame)
            assert abs(clip.num_frames - 1.5 * fa.fps) <= 1 and clip.features.shape[1] == 12 * 21 - 1
            assert clip.labels["codebooks"] == 2 and clip.labels["seed"] == 7 and clip.split == "none"
            assert np.array_equal(clip.joints, fb.clip(name).joints)  # the same seed, the same motion
        assert not np.allclose(fa.clip(0).joints, fc.clip(0).joints)
        assert [fa.clip(i).labels["start_clip"] for i in range(3)] == [a["per_sample"][n]["start_clip"]
                                                                       for n in fa.names]
    # with the fall test, a fall ends a sample: its time is reported and the clip is shorter
    d = generate(tiny_prior, tmp_path / "d.h5", seconds=3.0, num_samples=4, seed=0)
    assert d["fell"] > 0  # an untrained decoder holds its start pose and tips over
    for name, r in d["per_sample"].items():
        if r["stopped"] == "fall":
            assert r["fell_at_s"] <= 3.0 and r["seconds"] == pytest.approx(r["fell_at_s"] - 1 / 30)
        else:
            assert r["stopped"] is None and r["seconds"] == pytest.approx(3.0)
    from motok.cli.main import app

    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    runner = CliRunner()
    for args in (["info", str(tmp_path / "a.h5")],
                 ["render", "-d", str(tmp_path / "a.h5"), "--clip", "hybrid-m2-001", "-o", str(tmp_path / "g.gif")]):
        r = runner.invoke(app, ["--quiet", *args])
        assert r.exit_code == 0, (args, r.output)
    assert (tmp_path / "g.gif").stat().st_size > 0


def test_control_generate_command(tiny_prior, tmp_path):
    from motok.cli.main import app

    runner = CliRunner()
    out = tmp_path / "gen.h5"
    base = ["--quiet", "control", "generate", "--prior", str(tiny_prior)]
    r = runner.invoke(app, [*base, "--codebooks", "1", "--seconds", "1", "-n", "2", "-o", str(out), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    assert res["output"] == str(out) and res["samples"] == 2 and len(res["per_sample"]) == 2 and out.exists()
    assert res["kind"] == "hybrid" and res["codebooks"] == 1
    r = runner.invoke(app, [*base, "--codebooks", "5", "-o", str(tmp_path / "x.h5")])
    assert r.exit_code == 2 and "--codebooks must be in 1..4" in r.output and len(r.output.strip().splitlines()) == 1
    r = runner.invoke(app, [*base, "-o", str(tmp_path / "x.gif")])
    assert r.exit_code == 2 and not (tmp_path / "x.gif").exists()

