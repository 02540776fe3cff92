"""The latent priors (motok.control.priors.model) and their online distillation (motok.control.priors.distill,
motok.control.priors.dagger): where the gradients go, quantizer dropout and decoding from codes, the
Gaussian KL, the label conversion between action bases, learning, exact resume, the command."""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from motok.config import load_config
from motok.control.priors.dagger import expert_labels
from motok.control.priors.distill import DistillTrainer, distill_loss, expert_path, latent_change, train
from motok.control.priors.model import DistillConfig, WeightSchedule, load_prior
from motok.control.expert.model import ExpertConfig, load_expert
from motok.control.expert.train import imitation_mdp
from motok.control.expert.train import train as train_expert
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.priors.model import KINDS, LatentPrior, PriorConfig, gaussian_kl
from motok.errors import UserError
from motok.sim.env import SimConfig
from motok.sim.reference import load_library

pytestmark = pytest.mark.usefixtures("one_thread")
RECIPES = Path(__file__).resolve().parent.parent / "recipes" / "control"
QUANTIZED = ("discrete", "discrete+", "hybrid", "hybrid-vq")


def small_prior(kind: str, **kw) -> PriorConfig:
    c = PriorConfig(kind=kind, latent_dim=8, posterior_hidden=[32], prior_hidden=[32], decoder_hidden=[32],
                    num_codebooks=4, codebook_size=16, vq_codebook_size=32)
    return replace(c, **kw)


def random_model(kind: str, **kw) -> tuple[LatentPrior, torch.Tensor]:
    torch.manual_seed(0)
    model = LatentPrior(small_prior(kind, **kw), obs_dim=10, goal_dim=6, action_dim=4)
    return model, torch.randn(64, 16)


@pytest.fixture(scope="module")
def walk_lib(hum, small_dataset, tmp_path_factory):
    return load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp("prior-ref"))


@pytest.fixture(scope="module")
def tiny_expert(hum, walk_lib, tmp_path_factory) -> Path:
    """A barely trained expert (2 PPO iterations) on the reference base, as the recipes train it:
    the student must still learn its labels, ``reference base + a_e - q``, which change with
    every state."""
    cfg = ExpertConfig(seed=0, iterations=2, save_every=1000)
    cfg.env.num_envs, cfg.env.nthread, cfg.ppo.horizon, cfg.ppo.minibatch_size = 8, 1, 16, 64
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [64, 64]
    cfg.net.latent_dim = 16
    cfg.amp.enabled = False
    cfg.action.base, cfg.task.termination = "reference", "mean"
    run = tmp_path_factory.mktemp("tiny-expert") / "expert"
    train_expert(cfg, run, hum, walk_lib)
    return run


def distill_cfg(kind: str, **kw) -> DistillConfig:
    cfg = DistillConfig(seed=0, iterations=30, save_every=1000, horizon=16, epochs=4, minibatch_size=128,
                        action_noise=0.0)
    cfg.env.num_envs, cfg.env.nthread = 16, 1
    cfg.task.termination = "mean"
    cfg.prior = replace(small_prior(kind), latent_dim=16, posterior_hidden=[64, 64], prior_hidden=[64, 64],
                        decoder_hidden=[64, 64])
    return replace(cfg, **kw)


# ---------------------------------------------------------------------- the models

def test_gaussian_kl_against_the_closed_form():
    # KL(N(1, 2^2) || N(0, 1)) = log(1 / 2) + (4 + 1) / 2 - 1/2
    kl = gaussian_kl(torch.tensor(1.0), torch.tensor(math.log(2.0)), torch.tensor(0.0), torch.tensor(0.0))
    assert float(kl) == pytest.approx(math.log(0.5) + 2.0, rel=1e-6)
    g = torch.Generator().manual_seed(0)
    mq, lq, mp, lp = (torch.randn(5, 3, generator=g) for _ in range(4))
    ref = torch.distributions.kl_divergence(torch.distributions.Normal(mq, lq.exp()), torch.distributions.Normal(mp, lp.exp()))
    assert torch.allclose(gaussian_kl(mq, lq, mp, lp), ref, atol=1e-5)
    assert float(gaussian_kl(mq, lq, mq, lq).abs().max()) < 1e-6  # zero between equal Gaussians


@pytest.mark.parametrize("kind", [k for k, c in KINDS.items() if c.quantizer != "fsq"])  # FSQ: tests/test_beyond_priors.py
def test_the_posterior_receives_the_straight_through_gradient_of_z(kind):
    model, x = random_model(kind)
    out = model(x)
    out.z.retain_grad()
    w = torch.randn_like(out.z_bar)
    (out.z_bar * w).sum().backward()
    assert torch.equal(out.z.grad, w)  # d z_bar / d z = identity, through the quantizer and the margin
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.posterior.parameters())


@pytest.mark.parametrize("kind", ["hybrid", "hybrid-vq"])
def test_the_prior_learns_from_l_mm_and_l_reg_only(kind):
    model, x = random_model(kind)
    def grads(term: str) -> tuple[float, float]:
        model.zero_grad(set_to_none=True)
        out = model(x)
        _, terms = distill_loss(out, torch.randn(64, 4), 8, torch.zeros(8, 8, dtype=torch.bool),
                           {"action": 10.0, "reg": 0.05, "commit": 1.0, "mm": 1.0, "kl": 0.0})
        terms[term].backward()
        norm = lambda ps: sum(float(p.grad.abs().sum()) for p in ps if p.grad is not None)  # noqa: E731
        return norm(model.prior.parameters()), norm(model.posterior.parameters())

    prior, post = grads("action_loss")
    assert prior == 0.0 and post > 0  # z_p enters the decoder behind a stop-gradient
    assert grads("commit_loss")[0] == 0.0  # the margin quantized is z - sg(z_p)
    assert grads("mm_loss")[0] > 0 and grads("reg_loss")[0] > 0


def test_the_continuous_prior_learns_from_the_kl_not_the_action():
    model, x = random_model("continuous")
    out = model(x)
    (out.action ** 2).sum().backward()
    assert all(p.grad is None for p in model.prior.parameters())
    model.zero_grad(set_to_none=True)
    model(x).losses["kl"].backward()
    assert sum(float(p.grad.abs().sum()) for p in model.prior.parameters()) > 0
    s = x[:, :10]  # x plays the normalised input
    u = torch.randn(64, 8)
    assert torch.allclose(model.offset_to_latent(s, u), model.prior_latent(s)[0] + u)  # z = mu_p + u
    raw = 3 * torch.randn(64, 16) + 1
    model.norm.update(raw)  # task learning normalises s alone, with the statistics of [s, s~]
    assert torch.allclose(model.norm_obs(raw[:, :10]), model.norm(raw)[:, :10])


@pytest.mark.parametrize("kind", ["hybrid", "discrete+"])
def test_quantizer_dropout_limits_decoding_to_the_first_m_codebooks(kind):
    model, x = random_model(kind, quantizer_dropout=1.0)
    seen = set()
    for _ in range(30):
        out = model(x)  # training mode: each batch draws M ~ U{1..4}
        m = out.stats["num_active_codebooks"]
        seen.add(m)
        assert (out.indices[:, m:] == -1).all() and (out.indices[:, :m] >= 0).all()
    assert seen == {1, 2, 3, 4}
    model.eval()
    s = x[:, :10]  # x plays the normalised input
    full = model(x).indices
    books = model.codebooks()
    z_p = model.prior_latent(s)[0] if kind == "hybrid" else torch.zeros(64, 8)
    for m in range(1, 5):
        out = model(x, num_codebooks=m)
        codes = sum(books[i][out.indices[:, i]] for i in range(m))
        assert torch.allclose(out.z_bar, z_p + codes, atol=1e-6)  # z_bar = z_p + sum of the selected codes
        assert torch.equal(model.codes_to_latent(s, out.indices, m), out.z_bar)
        # given all N columns, decoding with the first M reads those only: the residual prefix
        assert torch.equal(model.codes_to_latent(s, full, m), out.z_bar)
        assert torch.equal(model.decode(s, model.codes_to_latent(s, out.indices, m)), out.action)


@pytest.mark.parametrize("kind", ["discrete", "hybrid-vq"])
def test_single_codebook_kinds_decode_from_their_code(kind):
    model, x = random_model(kind)
    model.eval()
    out = model(x)
    s = x[:, :10]  # x plays the normalised input
    code = model.codebooks()[0][out.indices[:, 0]]
    expected = code + model.prior_latent(s)[0] if kind == "hybrid-vq" else code
    assert torch.allclose(model.codes_to_latent(s, out.indices), expected) and torch.equal(out.z_bar, expected)


def set_head(head: torch.nn.Sequential, value: list[float]) -> None:
    """Make a network output ``value`` whatever its input (last layer: zero weights, bias = value)."""
    with torch.no_grad():
        head[-1].weight.zero_()
        head[-1].bias.copy_(torch.tensor(value))


def test_the_kinds_table():
    """Each kind's row and what follows from it: the losses distillation logs, the ramped weight,
    the default alpha of Eq. 6, and what the model builds (prior network, quantizer)."""
    rows = {  # quantized, margin, residual, losses, schedule, alpha
        "continuous": (False, False, False, ("kl_loss",), "kl", 0.005),
        "discrete": (True, False, False, ("commit_loss",), None, 0.05),
        "discrete+": (True, False, True, ("commit_loss",), None, 0.05),
        "hybrid": (True, True, True, ("commit_loss", "mm_loss"), "mm", 0.05),
        "hybrid-vq": (True, True, False, ("commit_loss", "mm_loss"), "mm", 0.05),
        # the paper's future work: FSQ has no commitment term; the part-wise prior adds L_part
        "hybrid-fsq": (True, True, True, ("mm_loss",), "mm", 0.05),
        "hybrid-grvq": (True, True, True, ("commit_loss", "mm_loss"), "mm", 0.05),
        "hybrid-parts": (True, True, True, ("commit_loss", "mm_loss", "part_loss"), "mm", 0.05),
    }
    assert list(KINDS) == list(rows)
    for kind, row in rows.items():
        k = KINDS[kind]
        assert (k.quantized, k.margin, k.residual, k.losses, k.schedule, k.reg) == row, kind
        model, _ = random_model(kind)
        assert (model.prior is not None) == (kind != "discrete" and kind != "discrete+")
        assert (model.quantizer is None) == (kind == "continuous")


def test_prior_config_check():
    PriorConfig(kind="continuous", log_std_min=-1.0, log_std_max=-1.0).check()  # a fixed std is allowed
    with pytest.raises(UserError, match="^prior.log_std_min must not exceed prior.log_std_max$"):
        PriorConfig(kind="continuous", log_std_min=0.5, log_std_max=0.0).check()
    with pytest.raises(UserError, match=r"^prior kind must be one of continuous, discrete, discrete\+, hybrid, "
                                        r"hybrid-vq, hybrid-fsq, hybrid-grvq, hybrid-parts, not 'vae'$"):
        PriorConfig(kind="vae").check()


def test_every_network_uses_the_configured_activation():
    model, x = random_model("hybrid", activation="tanh")  # one hidden layer each: Linear, tanh, Linear
    for net, inp in ((model.posterior, x), (model.prior, x[:, :10]), (model.decoder, torch.randn(64, 18))):
        assert torch.allclose(net(inp), net[-1](torch.tanh(net[0](inp))), atol=1e-6)


def test_each_kind_builds_its_bottleneck_from_the_config():
    """Codebook sizes per kind (N x K: residual kinds num_codebooks x codebook_size, single
    codebooks 1 x vq_codebook_size) and every quantizer setting passed on unchanged."""
    kw = dict(quantizer="ema", decay=0.9, reset_threshold=3.0, quantizer_dropout=0.25, kmeans_init=False)
    for kind in QUANTIZED:
        model, x = random_model(kind, **kw)
        residual = KINDS[kind].residual
        N, K = (4, 16) if residual else (1, 32)
        assert model.codebooks().shape == (N, K, 8) and model.num_codebooks == N
        qc = model.quantizer.cfg
        assert (qc.kind, qc.rvq_base, qc.num_codebooks, qc.codebook_size) == ("rvq" if residual else "ema", "ema", N, K)
        assert (qc.dim, qc.decay, qc.reset_threshold, qc.quantizer_dropout, qc.kmeans_init) == (8, 0.9, 3.0, 0.25, False)
        assert model.spec() == {"kind": kind, "latent_dim": 8, "has_prior": KINDS[kind].prior_network,
                                "num_codebooks": N, "codebook_size": K, "quantizer": KINDS[kind].quantizer,
                                "index_columns": N, "posterior_hidden": [32],
                                "prior_hidden": [32], "decoder_hidden": [32]}
        with pytest.raises(UserError, match=f"^offset_to_latent is for the continuous prior, not '{re.escape(kind)}'$"):
            model.offset_to_latent(x[:, :10], torch.zeros(64, 8))
        if not KINDS[kind].prior_network:
            with pytest.raises(UserError, match=f"^the {re.escape(kind)} prior has no prior network$"):
                model.prior_latent(x[:, :10])
    model, x = random_model("continuous")
    assert model.quantizer is None and model.num_codebooks == 0 and model.spec()["codebook_size"] == 0
    with pytest.raises(UserError, match="^the continuous prior has no codebooks$"):
        model.codebooks()
    with pytest.raises(UserError, match="^the continuous prior has no codes: use offset_to_latent$"):
        model.codes_to_latent(x[:, :10], torch.zeros(64, 1, dtype=torch.long))


def test_norm_obs_on_hand_values():
    """(s - mean) / sqrt(var + eps) on the observation's entries of the [s, s~] statistics,
    clipped to [-5, 5]: mean k, var 4 (var 0 on entry 3, where eps alone divides)."""
    model, _ = random_model("hybrid")
    n = model.norm
    with torch.no_grad():
        n.mean.copy_(torch.arange(16.0))
        n.var.fill_(4.0)
        n.var[3] = 0.0
    s = torch.arange(10.0) + torch.tensor([2.0, -2.0, 40.0, 2**-10, 0.0, 0.0, -40.0, 0.0, 0.0, 1.0])
    expect = torch.tensor([1.0, -1.0, 5.0, 2**-10 / math.sqrt(n.eps), 0.0, 0.0, -5.0, 0.0, 0.0, 0.5])
    assert torch.allclose(model.norm_obs(s[None].expand(3, 10)), expect.expand(3, 10), atol=1e-6)
    assert torch.allclose(model.norm_obs(s), expect, atol=1e-6)  # one observation, no batch axis


@pytest.mark.parametrize("kind", ["continuous", "hybrid"])
def test_one_observation_without_a_batch_axis(kind):
    model, x = random_model(kind)
    s, z = x[0, :10], torch.randn(8)
    for one, batch in zip(model.prior_latent(s), model.prior_latent(s[None])):
        assert (one is None and batch is None) or torch.allclose(one, batch[0], atol=1e-6)
    assert torch.allclose(model.decode(s, z), model.decode(s[None], z[None])[0], atol=1e-6)


def test_the_continuous_heads_clamp_log_std_and_sample_by_reparameterisation():
    """Heads fixed to q = N((1, -0.5), exp(-10, 3)) and p = N((0, 1), exp(0.5, -7)): log-stds
    clamped to [-5, 1], so q's are (-5, 1) and p's (0.5, -5); z = mu_q + std_q * eps with eps the
    next normal draws, or mu_q itself without sampling; z_p is the prior mean; L_reg reads mu_q."""
    model, _ = random_model("continuous", latent_dim=2)
    set_head(model.posterior, [1.0, -0.5, -10.0, 3.0])
    set_head(model.prior, [0.0, 1.0, 0.5, -7.0])
    x = torch.randn(6, 16)
    mu_p, ls_p = model.prior_latent(x[:, :10])
    assert torch.equal(ls_p, torch.tensor([0.5, -5.0]).expand(6, 2)) and torch.equal(mu_p[0], torch.tensor([0.0, 1.0]))
    mq, lq, mp, lp = [1.0, -0.5], [-5.0, 1.0], [0.0, 1.0], [0.5, -5.0]
    kl = sum(lp[i] - lq[i] + (math.exp(2 * lq[i]) + (mq[i] - mp[i]) ** 2) / (2 * math.exp(2 * lp[i])) - 0.5
             for i in range(2)) / 2
    torch.manual_seed(7)
    out = model(x)
    torch.manual_seed(7)
    eps = torch.randn(6, 2)
    mu_q = torch.tensor(mq).expand(6, 2)
    assert torch.allclose(out.z, mu_q + torch.exp(torch.tensor(lq)) * eps, atol=1e-6)
    assert torch.equal(out.z_bar, out.z) and torch.equal(out.z_p, mu_p) and torch.equal(out.reg[0], mu_q)
    assert float(out.losses["kl"].detach()) == pytest.approx(kl, rel=1e-6)
    mean = model(x, sample=False)
    assert torch.equal(mean.z, mu_q) and float(mean.losses["kl"].detach()) == pytest.approx(kl, rel=1e-6)
    assert torch.allclose(mean.action, model.decode(x[:, :10], mu_q))


def test_latent_change_covers_neighbouring_steps_of_one_episode():
    T, n = 3, 2
    lat = torch.tensor([[0.0], [0.0], [1.0], [5.0], [3.0], [5.0]])  # rows step-major: (t, env)
    done = torch.tensor([[False, True], [False, False], [False, False]])
    # env 0: (0 -> 1) + (1 -> 3) = 1 + 4; env 1: its step 0 ended an episode, so only (5 -> 5) = 0
    assert float(latent_change([lat], T, done)) == pytest.approx((1 + 4 + 0) / 3)
    assert float(latent_change([lat, 2 * lat], T, done)) == pytest.approx(5 * 5 / 3)
    assert float(latent_change([lat], T, torch.ones(T, n, dtype=torch.bool))) == 0.0


def test_weight_schedules_ramp_linearly_then_hold():
    s = WeightSchedule(0.1, 1.0, ramp=0.125)
    assert s.at(0, 800) == pytest.approx(0.1) and s.at(50, 800) == pytest.approx(0.55)
    assert s.at(100, 800) == pytest.approx(1.0) and s.at(700, 800) == pytest.approx(1.0)
    assert WeightSchedule(0.1, 1.0, ramp=0.0).at(0, 10) == 1.0
    # a ramp shorter than one iteration (0.125 of 4: half an iteration) still starts at `start`
    assert s.at(0, 4) == pytest.approx(0.1) and s.at(1, 4) == pytest.approx(1.0)


def test_prior_recipes_load():
    margin = {}  # per quantized kind: a minibatch's rows per code over the reset threshold
    for path in sorted(RECIPES.glob("prior_*.yaml")):
        cfg = load_config(DistillConfig, path)
        kind = path.stem[len("prior_"):]
        assert cfg.action.base == "current"
        if kind in ("discrete", "hybrid-vq", "discrete+", "hybrid"):
            codes = cfg.prior.vq_codebook_size if kind in ("discrete", "hybrid-vq") else cfg.prior.codebook_size
            margin[kind] = cfg.minibatch_size / codes / cfg.prior.reset_threshold
        if kind == "paper":
            assert cfg.prior.kind == "" and cfg.prior.codebook_size == 1024 and cfg.prior.vq_codebook_size == 8192
            m = LatentPrior(replace(cfg.prior, kind="hybrid"), 102, 315, 37)
            assert m.codebooks().shape == (8, 1024, 64)
        else:
            assert cfg.prior.kind == kind, path
            LatentPrior(cfg.prior, 102, 315, 37)
    assert {p.stem for p in RECIPES.glob("prior_*.yaml")} == {f"prior_{k}" for k in (*KINDS, "paper")}
    # A single book and a residual book are compared on equal terms: every code of either sees as
    # many rows per update, relative to the usage below which it is reset (else the single book
    # would be replaced rather than learned)
    assert len(set(margin.values())) == 1 and len(margin) == 4, margin


# ---------------------------------------------------------------------- labels and distillation

def test_the_converted_label_reproduces_the_expert_pd_targets(hum, walk_lib, tiny_expert):
    ecfg, _, expert, _ = load_expert(tiny_expert)
    sim = SimConfig(num_envs=8, nthread=1)
    student = ActionConfig("current", scale=0.5)
    mdp_e = imitation_mdp(hum, walk_lib, sim, ecfg.task, ecfg.action, seed=3)  # the expert's own MDP
    mdp_s = imitation_mdp(hum, walk_lib, sim, ecfg.task, student, seed=3)  # the student's, same starts
    obs, goal = mdp_e.reset()
    assert np.array_equal(obs, mdp_s.reset()[0])
    for _ in range(10):
        x = torch.as_tensor(np.concatenate([obs, goal], 1), dtype=torch.float32)
        a_e = expert.act(x, deterministic=True)[1].numpy()
        env = mdp_s.env
        label = expert_labels(ecfg.action, a_e, env, mdp_s.task, student.scale)
        want = np.clip(pd_targets(ecfg.action, a_e, mdp_e.env, mdp_e.task), env.ctrl_low, env.ctrl_high)
        assert ecfg.action.base == "reference" and np.abs(label).max() > 0.05  # a real change of base
        assert np.abs(pd_targets(student, label, env, mdp_s.task) - want).max() < 1e-12
        as_f32 = label.astype(np.float32)  # what a float32 student outputs
        assert np.abs(pd_targets(student, as_f32, env, mdp_s.task) - want).max() < 1e-6
        obs, goal, _, term, trunc, _ = mdp_e.step(a_e)
        mdp_s.step(label)
        assert np.abs(mdp_e.env.qpos - mdp_s.env.qpos).max() < 1e-8  # the same motion
        if (term | trunc).any():
            break


@pytest.mark.parametrize("kind", KINDS)
def test_a_short_distillation_lowers_the_action_loss(kind, hum, walk_lib, tiny_expert):
    """30 iterations of 16 envs x 16 steps (7.7k samples) from the barely trained expert: the
    student's error on the states it visits next (measured before each update) falls."""
    ecfg, ehum, expert, _ = load_expert(tiny_expert)
    tr = DistillTrainer(distill_cfg(kind), ehum, walk_lib, ecfg, expert)
    tr.start_segment()
    rows = [tr.step() for _ in range(tr.cfg.iterations)]
    err = [r["rollout_action_err"] for r in rows]
    fit = [r["action_loss"] for r in rows]
    first, last = np.mean(err[:3]), np.mean(err[-3:])
    print(f"{kind}: rollout action error {first:.3f} -> {last:.3f}, fitted {np.mean(fit[:3]):.3f} -> "
          f"{np.mean(fit[-3:]):.3f}")
    assert last < 0.6 * first, np.round(err, 3)
    assert np.mean(fit[-3:]) < 0.6 * np.mean(fit[:3])
    if kind in QUANTIZED:
        assert all(0.0 < r["code_usage"] <= 1.0 for r in rows)


@pytest.mark.parametrize("kind", ["hybrid", "continuous"])
def test_distillation_resumes_exactly(kind, hum, walk_lib, tiny_expert, tmp_path):
    cfg = distill_cfg(kind, iterations=4, save_every=2)
    cfg.env.num_envs, cfg.horizon, cfg.minibatch_size, cfg.action_noise = 8, 8, 32, 0.05
    train(replace(cfg, eval_every=2), tmp_path / "straight", tiny_expert, walk_lib)
    train(cfg, tmp_path / "split", tiny_expert, walk_lib, until=2)
    train(cfg, tmp_path / "split", tiny_expert, walk_lib, resume=True)
    a, b = load_file(tmp_path / "straight" / "model.safetensors"), load_file(tmp_path / "split" / "model.safetensors")
    assert a.keys() == b.keys() and "model.norm.mean" in a
    for k in a:
        assert torch.equal(a[k], b[k]), k  # and the evaluations in between changed nothing
    strip = lambda s: {k: v for k, v in json.loads(s).items() if not k.endswith("_s") and not k.startswith("eval_")}  # noqa: E731
    la = (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()
    lb = (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()
    assert [strip(x) for x in la] == [strip(x) for x in lb]
    assert ["eval_success" in json.loads(x) for x in la] == [False, True, False, True]
    # the bundle: kind, the expert (relative path resolving from the bundle), sizes, the MJCF
    meta = json.loads((tmp_path / "split" / "bundle.json").read_text())
    ex = meta["extra"]
    assert meta["kind"] == "control-prior" and ex["prior"]["kind"] == kind and ex["action"]["base"] == "current"
    assert expert_path(tmp_path / "split", meta).resolve() == tiny_expert.resolve()
    moved = tmp_path / "elsewhere" / "deeper" / "prior"
    shutil.copytree(tmp_path / "split", moved)  # the relative path breaks; the absolute one still holds
    assert expert_path(moved, meta).resolve() == tiny_expert.resolve()
    assert not Path(ex["expert"]).is_absolute() and "expert" in meta["refs"]
    assert ex["expert_info"]["absolute"] == str(tiny_expert.resolve()) and ex["expert_info"]["action"]["base"] == "reference"
    assert ex["prior"]["num_codebooks"] == (4 if kind == "hybrid" else 0)
    _, phum, model, _ = load_prior(tmp_path / "split")
    assert len(ex["mjcf_sha256"]) == 64 and Path(phum.path).name == "humanoid.xml"
    x = torch.randn(5, ex["obs_dim"] + ex["goal_dim"])
    assert model(model.norm(x), sample=False).action.shape == (5, 37)


def test_control_distill_command(small_dataset, tiny_expert, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from motok.cli.main import app

    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    recipe = tmp_path / "r.yaml"
    recipe.write_text("iterations: 3\nhorizon: 8\nminibatch_size: 32\nenv: {num_envs: 4, nthread: 1}\n"
                      "task: {termination: mean}\n"
                      "prior: {kind: hybrid, latent_dim: 8, posterior_hidden: [16], prior_hidden: [16], "
                      "decoder_hidden: [16], num_codebooks: 2, codebook_size: 8}\n")
    out = tmp_path / "prior"
    base = ["--quiet", "control", "distill", "--expert", str(tiny_expert), "--data", str(small_dataset),
            "--recipe", str(recipe), "-o", str(out)]
    r = CliRunner().invoke(app, [*base, "--kind", "hybrid", "--until", "1", "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    assert summary["iterations"] == 1 and summary["action_loss"] > 0 and 0 < summary["code_usage"] <= 1
    meta = json.loads((out / "bundle.json").read_text())
    assert meta["extra"]["iteration"] == 1 and meta["config"]["iterations"] == 3 and (out / "humanoid.xml").exists()
    for args, says in ((["--kind", "vq-vae"], "--kind must be one of"),
                       (["--kind", "discrete"], "the recipe is for a 'hybrid' prior")):
        r = CliRunner().invoke(app, [*base[:-1], str(tmp_path / "other"), *args])  # -o: a new folder
        assert r.exit_code == 2 and says in r.output and len(r.output.strip().splitlines()) == 1, r.output
        assert not (tmp_path / "other").exists()
    # the distilled policy on the imitation task, with the first codebook only
    ev = ["--quiet", "control", "eval", "--task", "imitation", "--prior", str(out), "--data", str(small_dataset),
          "--clips", "dataset-2_walk_normal_00[12]"]
    r = CliRunner().invoke(app, [*ev, "--codebooks", "1", "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads((out / "eval_m1.json").read_text())
    o = res["overall"]
    assert res["kind"] == "control-prior-eval" and o["clips"] == 2
    # two clips, one episode each: the overall rate is the share of the clips that succeeded
    assert o["success_rate"] == np.mean([bool(v["success"]) for v in res["clips"].values()])
    assert all(v["seconds"] > 0 for v in res["clips"].values()) and res["checkpoint"]["codebooks"] == 1
    assert res["checkpoint"]["prior"]["kind"] == "hybrid" and o["g_mpjpe_mm"] > 0
    for args, says in ((["--task", "no-such-task"], "--task must be one of"), (["--codebooks", "3"], "--codebooks must be in 1..2")):
        r = CliRunner().invoke(app, [*ev, *args])
        assert r.exit_code == 2 and says in r.output and len(r.output.strip().splitlines()) == 1, r.output
    # the distilled policy as the controller of `motok control track`
    tr = ["--quiet", "control", "track", "-d", str(small_dataset), "--clips", "dataset-2_walk_normal_001"]
    r = CliRunner().invoke(app, [*tr, "--prior", str(out), "-o", str(tmp_path / "sim.h5"), "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["written"] == 1, r.output
    r = CliRunner().invoke(app, [*tr, "-o", str(tmp_path / "none.h5")])
    assert r.exit_code == 2 and "one controller" in r.output
