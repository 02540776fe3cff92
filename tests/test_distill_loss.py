"""Eq. 6 of the hybrid-latent paper as the distillation computes it (motok.control.priors.distill.distill_loss
on motok.control.priors.model.LatentPrior): every term recomputed by hand from the model's outputs, the
total and its gradient against the weighted hand sum, which parameters each term reaches, the update's
training mode (quantizer dropout, EMA codebooks), the KL's direction and the commitment loss's sign.

A short distillation still learns when any of these is wrong, so each is pinned here on hand values."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from motok.control.priors.dagger import DaggerBatch
from motok.control.priors.distill import DistillTrainer, distill_loss
from motok.control.priors.model import DistillConfig, LatentPrior, PriorConfig
from motok.quantize.base import QuantizerConfig
from motok.quantize.registry import build_quantizer

pytestmark = pytest.mark.usefixtures("one_thread")

T, NCOL = 4, 8  # horizon and environment columns of the hand batch: rows are step-major, t * NCOL + j
W = {"action": 10.0, "reg": 0.05, "commit": 1.0, "mm": 0.3, "kl": 0.7}  # distinct, so a dropped term shows


def small_model(kind: str, **kw) -> LatentPrior:
    torch.manual_seed(0)
    cfg = PriorConfig(kind=kind, latent_dim=8, posterior_hidden=[32], prior_hidden=[32], decoder_hidden=[32],
                      num_codebooks=4, codebook_size=16, vq_codebook_size=32)
    return LatentPrior(replace(cfg, **kw), obs_dim=10, goal_dim=6, action_dim=4)


def hand_batch() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    done = torch.zeros(T, NCOL, dtype=torch.bool)
    done[1, 2] = done[0, 5] = done[2, 5] = True  # episode ends: pairs (t, t+1) of those columns do not count
    return torch.randn(T * NCOL, 16, generator=g), torch.randn(T * NCOL, 4, generator=g), done


def hand_reg(latents: list[torch.Tensor], done: torch.Tensor) -> torch.Tensor:
    """L_reg written with loops: mean over kept neighbouring pairs of ||l_{t+1} - l_t||^2, summed over latents."""
    total = torch.zeros(())
    for lat in latents:
        pairs = [((lat[(t + 1) * NCOL + j] - lat[t * NCOL + j]) ** 2).sum()
                 for t in range(T - 1) for j in range(NCOL) if not done[t, j]]
        total = total + torch.stack(pairs).mean()
    return total


def groups(model: LatentPrior) -> dict[str, list[torch.nn.Parameter]]:
    g = {"posterior": list(model.posterior.parameters()), "decoder": list(model.decoder.parameters())}
    if model.prior is not None:
        g["prior"] = list(model.prior.parameters())
    if model.quantizer is not None and list(model.quantizer.parameters()):
        g["codebook"] = list(model.quantizer.parameters())
    return g


def reached(model: LatentPrior, loss: torch.Tensor) -> set[str]:
    """The parameter groups ``loss`` sends a non-zero gradient to."""
    out = set()
    for name, ps in groups(model).items():
        gs = torch.autograd.grad(loss, ps, retain_graph=True, allow_unused=True)
        if any(g is not None and float(g.abs().sum()) > 0 for g in gs):
            out.add(name)
    return out


def hybrid_forward(quantizer: str = "ema_reset"):
    """One training-mode forward of a hybrid after a first (k-means) one, with the hand terms of Eq. 6
    rebuilt from its outputs and the codebooks as they were when the batch read them."""
    model = small_model("hybrid", quantizer=quantizer, quantizer_dropout=0.0)
    x, labels, done = hand_batch()
    model.train()
    model(x)  # k-means start on the first batch, so the codes below are the ones the second forward reads
    codes = model.codebooks().clone()
    out = model(x)
    z, z_p = out.z, out.z_p
    # The margin y = z - sg(z_p) is quantized residual by residual with the codes as they were.
    y = z - z_p.detach()
    r, q_sum, commits = y, torch.zeros_like(y), []
    for i in range(model.num_codebooks):
        q = codes[i][out.indices[:, i]]
        commits.append(((r - q) ** 2).mean())  # q carries no gradient: a constant here
        r, q_sum = r - q, q_sum + q
    assert torch.allclose(out.z_bar, z_p + q_sum, atol=1e-5)  # z_bar = sg(z_p) + y_bar, y_bar = sum of codes
    y_bar = y + (q_sum - y).detach()  # straight-through: the value of the codes, the gradient of y
    z_bar = z_p.detach() + y_bar
    s = x[:, :10]
    hand = {"action_loss": ((model.decode(s, z_bar) - labels) ** 2).sum(-1).mean(),
            "commit_loss": torch.stack(commits).mean(),
            "mm_loss": ((z_bar - z_p) ** 2).sum(-1).mean(),
            "reg_loss": hand_reg([y_bar, z_p], done)}
    if quantizer == "vq":  # a gradient-learned codebook: its own loss pulls the codes (which are parameters)
        emb = [layer.embed for layer in model.quantizer.layers]
        r, cb = y.detach(), []
        for i in range(model.num_codebooks):
            q = emb[i][out.indices[:, i]]
            cb.append(((q - r) ** 2).mean())
            r = r - q.detach()
        hand["codebook"] = torch.stack(cb).mean()
    else:
        hand["codebook"] = torch.zeros(())
    total, terms = distill_loss(out, labels, T, done, W)
    return model, out, total, terms, hand


@pytest.mark.parametrize("quantizer", ["ema_reset", "vq"])
def test_the_hybrid_loss_and_its_gradient_are_the_weighted_hand_sum_of_eq_6(quantizer):
    model, out, total, terms, hand = hybrid_forward(quantizer)
    for k in ("action_loss", "commit_loss", "mm_loss", "reg_loss"):
        assert float(terms[k].detach()) == pytest.approx(float(hand[k].detach()), rel=1e-5), k
    hand_total = (W["action"] * hand["action_loss"] + W["reg"] * hand["reg_loss"] + W["commit"] * hand["commit_loss"]
                  + hand["codebook"] + W["mm"] * hand["mm_loss"])
    assert float(total.detach()) == pytest.approx(float(hand_total.detach()), rel=1e-5)
    # No term is negligible on this batch, so a dropped or re-signed one moves the total.
    for k, wk in (("reg_loss", "reg"), ("mm_loss", "mm"), ("commit_loss", "commit")):
        assert W[wk] * float(hand[k].detach()) > 1e-3 * float(total.detach()), k
    params = [p for ps in groups(model).values() for p in ps]
    g_code = torch.autograd.grad(total, params, retain_graph=True, allow_unused=True)
    g_hand = torch.autograd.grad(hand_total, params, allow_unused=True)
    for a, b in zip(g_code, g_hand):
        a = torch.zeros_like(b) if a is None else a
        b = torch.zeros_like(a) if b is None else b
        assert torch.allclose(a, b, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("quantizer", ["ema_reset", "vq"])
def test_each_hybrid_term_reaches_exactly_its_parameters(quantizer):
    """Algorithm 1's paths: the decoder reads z_bar = sg(z_p) + ST(y), y = z - sg(z_p); so the
    action loss trains decoder and posterior, never the prior; the commitment loss (on y, against
    detached codes) only the posterior; L_mm = ||z_bar - z_p||^2 both posterior (through the
    straight-through) and prior; L_reg (on y_bar and z_p) both, never the decoder. Codes are
    learned by the codebook loss only (gradient kind) or by EMA (buffers, no gradient at all)."""
    model, out, total, terms, hand = hybrid_forward(quantizer)
    learned = {"codebook"} if quantizer == "vq" else set()
    assert reached(model, terms["action_loss"]) == {"decoder", "posterior"}
    assert reached(model, terms["commit_loss"]) == {"posterior"}
    assert reached(model, terms["mm_loss"]) == {"posterior", "prior"}
    assert reached(model, terms["reg_loss"]) == {"posterior", "prior"}
    assert reached(model, total) == {"decoder", "posterior", "prior"} | learned
    if quantizer != "vq":
        assert not list(model.quantizer.parameters())  # EMA codebooks are buffers: nothing to pull on
    else:
        assert reached(model, out.losses["codebook"]) == {"codebook"}


def set_head(head: torch.nn.Sequential, value: list[float]) -> None:
    """Make a network output ``value`` whatever its input (last layer: zero weights, bias = value)."""
    last = head[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor(value))


def test_the_kl_is_posterior_to_prior_on_hand_gaussians():
    model = small_model("continuous", latent_dim=2)
    # q = N((1, -0.5), (0.5, 2)^2), p = N((0, 1), (1, 1.5)^2)
    mq, sq, mp, sp = [1.0, -0.5], [0.5, 2.0], [0.0, 1.0], [1.0, 1.5]
    set_head(model.posterior, mq + [math.log(s) for s in sq])
    set_head(model.prior, mp + [math.log(s) for s in sp])
    kl = lambda m1, s1, m2, s2: math.log(s2 / s1) + (s1 ** 2 + (m1 - m2) ** 2) / (2 * s2 ** 2) - 0.5  # noqa: E731
    forward = sum(kl(mq[i], sq[i], mp[i], sp[i]) for i in range(2)) / 2  # averaged over latent dimensions
    reverse = sum(kl(mp[i], sp[i], mq[i], sq[i]) for i in range(2)) / 2
    assert abs(forward - reverse) > 0.5  # the hand values tell the directions apart
    x, labels, done = hand_batch()
    out = model.train()(x)
    assert float(out.losses["kl"].detach()) == pytest.approx(forward, rel=1e-5)
    _, terms = distill_loss(out, labels, T, done, W)
    assert float(terms["kl_loss"].detach()) == pytest.approx(forward, rel=1e-5)


def test_the_continuous_loss_is_the_weighted_hand_sum():
    model = small_model("continuous")
    x, labels, done = hand_batch()
    torch.manual_seed(3)
    out = model.train()(x)
    total, terms = distill_loss(out, labels, T, done, W)
    mu_q, ls_q = model.posterior(x).chunk(2, -1)
    mu_p, ls_p = model.prior(x[:, :10]).chunk(2, -1)
    ls_q, ls_p = ls_q.clamp(-5, 1), ls_p.clamp(-5, 1)
    kl = (ls_p - ls_q + (torch.exp(2 * ls_q) + (mu_q - mu_p) ** 2) / (2 * torch.exp(2 * ls_p)) - 0.5).mean()
    z = out.z  # the reparameterised sample; its noise is (z - mu_q) / std_q
    eps = ((z - mu_q) / torch.exp(ls_q)).detach()
    z_h = mu_q + torch.exp(ls_q) * eps
    act = ((model.decode(x[:, :10], z_h) - labels) ** 2).sum(-1).mean()
    reg = hand_reg([mu_q], done)
    hand_total = W["action"] * act + W["reg"] * reg + W["kl"] * kl
    assert float(total.detach()) == pytest.approx(float(hand_total.detach()), rel=1e-5)
    params = [p for ps in groups(model).values() for p in ps]
    for a, b in zip(torch.autograd.grad(total, params, retain_graph=True), torch.autograd.grad(hand_total, params)):
        assert torch.allclose(a, b, atol=1e-6, rtol=1e-4)
    # The KL trains posterior and prior, the action loss decoder and posterior, L_reg (on mu_q) the posterior.
    assert reached(model, terms["kl_loss"]) == {"posterior", "prior"}
    assert reached(model, terms["action_loss"]) == {"decoder", "posterior"}
    assert reached(model, terms["reg_loss"]) == {"posterior"}


@pytest.mark.parametrize("kind", ["discrete", "discrete+"])
def test_the_discrete_loss_is_the_weighted_hand_sum(kind):
    """No prior network: z_bar = VQ(z) or RVQ(z), the sum of the codes read residual by residual,
    L_reg on z_bar, no L_mm and no KL; the action and L_reg reach decoder and posterior through the
    straight-through estimator, the commitment the posterior only."""
    model = small_model(kind, quantizer_dropout=0.0, vq_codebook_size=8)  # fewer codes than rows: commit > 0
    x, labels, done = hand_batch()
    model.train()
    model(x)  # k-means start
    codes = model.codebooks().clone()
    out = model(x)
    z = out.z
    r, q_sum, commits = z, torch.zeros_like(z), []
    for i in range(model.num_codebooks):
        q = codes[i][out.indices[:, i]]
        commits.append(((r - q) ** 2).mean())
        r, q_sum = r - q, q_sum + q
    assert torch.allclose(out.z_bar, q_sum, atol=1e-5) and out.z_p is None
    z_bar = z + (q_sum - z).detach()
    hand = {"action_loss": ((model.decode(x[:, :10], z_bar) - labels) ** 2).sum(-1).mean(),
            "commit_loss": torch.stack(commits).mean(), "reg_loss": hand_reg([z_bar], done)}
    total, terms = distill_loss(out, labels, T, done, W)
    for k, v in hand.items():
        assert float(terms[k].detach()) == pytest.approx(float(v.detach()), rel=1e-5), k
    assert float(terms["mm_loss"]) == 0.0 and float(terms["kl_loss"]) == 0.0
    hand_total = W["action"] * hand["action_loss"] + W["reg"] * hand["reg_loss"] + W["commit"] * hand["commit_loss"]
    assert float(total.detach()) == pytest.approx(float(hand_total.detach()), rel=1e-5)
    for k, wk in (("reg_loss", "reg"), ("commit_loss", "commit")):  # neither negligible on this batch
        assert W[wk] * float(hand[k].detach()) > 1e-3 * float(total.detach()), k
    params = [p for ps in groups(model).values() for p in ps]
    g_code = torch.autograd.grad(total, params, retain_graph=True)
    for a, b in zip(g_code, torch.autograd.grad(hand_total, params, retain_graph=True)):
        assert torch.allclose(a, b, atol=1e-6, rtol=1e-4)
    assert reached(model, terms["action_loss"]) == {"decoder", "posterior"}
    assert reached(model, terms["reg_loss"]) == {"posterior"}
    assert reached(model, terms["commit_loss"]) == {"posterior"}


def test_the_commitment_loss_falls_as_the_encoder_output_moves_toward_its_code():
    rvq = build_quantizer(QuantizerConfig(kind="rvq", rvq_base="ema_reset", num_codebooks=1, codebook_size=2,
                                          dim=2, quantizer_dropout=0.0)).eval()
    with torch.no_grad():
        rvq.layers[0].embed.copy_(torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
    losses = []
    for a in (0.5, 0.75, 0.9):  # (a, 0) is nearest (1, 0): commit = mean((a - 1)^2, 0) = (1 - a)^2 / 2
        out = rvq(torch.tensor([[a, 0.0]]))
        assert out.indices.tolist() == [[0]]
        losses.append(float(out.losses["commit"]))
        assert losses[-1] == pytest.approx((1 - a) ** 2 / 2)
    assert losses[0] > losses[1] > losses[2]
    # Through Eq. 6: a small gradient step on the encoder output lowers the weighted loss (points away from the code).
    z = torch.tensor([[0.5, 0.0]], requires_grad=True)
    out = rvq(z)
    lat = SimpleNamespace(action=torch.zeros(1, 1), reg=[torch.zeros(1, 1)], losses={"commit": out.losses["commit"],
                          "codebook": out.losses["codebook"], "mm": torch.zeros(()), "kl": torch.zeros(())})
    total, _ = distill_loss(lat, torch.zeros(1, 1), 1, torch.zeros(1, 1, dtype=torch.bool), W)
    (g,) = torch.autograd.grad(total, z)
    assert g[0, 0] < 0 and float(g[0, 1]) == 0.0  # descending moves z toward (1, 0)


# ---------------------------------------------------------------------- the update's training mode

def bare_trainer(model: LatentPrior, epochs: int) -> DistillTrainer:
    """DistillTrainer.update needs only the model, its optimiser and the config: no environments."""
    tr = object.__new__(DistillTrainer)
    cfg = DistillConfig(seed=0, iterations=10, horizon=T, epochs=epochs, minibatch_size=T)  # one column per step
    cfg.prior = model.cfg
    tr.cfg, tr.model, tr.iteration, tr.alpha = cfg, model, 0, 0.05
    tr.params = list(model.parameters())
    tr.opt = torch.optim.Adam(tr.params, lr=1e-3)
    return tr


def dagger_batch(ncols: int) -> DaggerBatch:
    g = torch.Generator().manual_seed(2)
    z = torch.zeros(T, ncols, dtype=torch.bool)
    return DaggerBatch(torch.randn(T, ncols, 16, generator=g), torch.randn(T, ncols, 4, generator=g),
                       torch.zeros(T, ncols), z, z.clone())


def test_the_update_trains_with_quantizer_dropout_at_its_configured_rate():
    """quantizer_dropout 0.5 over 4 codebooks: half the steps draw M ~ U{1..4}, so M < 4 on
    0.5 * 3/4 = 37.5% of the steps and each M < 4 on 12.5%; an eval-mode update always uses 4."""
    model = small_model("hybrid", quantizer_dropout=0.5)
    seen: list[int] = []
    model.quantizer.register_forward_hook(lambda mod, args, out: seen.append(out.stats["num_active_codebooks"]))
    stats = bare_trainer(model, epochs=10).update(dagger_batch(40))  # 10 epochs x 40 one-column minibatches
    assert len(seen) == 400
    share = sum(m < 4 for m in seen) / len(seen)
    assert abs(share - 0.375) < 0.08, share  # binomial std 0.024
    for m in (1, 2, 3):
        assert abs(seen.count(m) / len(seen) - 0.125) < 0.06, (m, seen.count(m))
    assert stats["active_codebooks"] == pytest.approx(sum(seen) / len(seen))
    assert stats["active_codebooks"] == pytest.approx(0.5 * 4 + 0.5 * 2.5, abs=0.2)


def test_the_update_moves_the_ema_codebooks_and_an_eval_forward_does_not():
    model = small_model("hybrid", quantizer_dropout=0.0)
    layer = model.quantizer.layers[0]
    x = torch.randn(64, 16)
    model.train()(x)  # k-means start, so both comparisons below start from data codes
    before = {k: getattr(layer, k).clone() for k in ("ema_count", "ema_sum", "embed")}
    model.eval()(torch.randn(64, 16))
    for k, v in before.items():
        assert torch.equal(getattr(layer, k), v), k  # eval: codebooks are read, never written
    bare_trainer(model, epochs=1).update(dagger_batch(8))
    for k, v in before.items():
        assert not torch.allclose(getattr(layer, k), v), k
    # EMA counts: decay * N_k + (1 - decay) n_k keeps their sum at the batch size once warm.
    assert float(layer.ema_count.sum()) == pytest.approx(float(before["ema_count"].sum()), rel=0.5)
