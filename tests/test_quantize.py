"""Quantizers (motok.quantize): assignment, straight-through gradients, EMA and reset updates,
residual VQ, FSQ, statistics, per-item (B, D) latents, construction order, and codebooks staying
identical across two distributed ranks."""

from __future__ import annotations

import datetime
import math
import os
import socket

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from motok.config import from_dict
from motok.quantize.base import QuantizerConfig
from motok.quantize.registry import build_quantizer

CODEBOOK_KINDS = ["vq", "ema", "reset", "ema_reset", "rvq"]


pytestmark = pytest.mark.usefixtures("one_thread")


def make(kind, K=16, D=8, N=None, seed=0, **kw):
    torch.manual_seed(seed)
    N = N if N is not None else (3 if kind == "rvq" else 1)
    return build_quantizer(QuantizerConfig(kind=kind, codebook_size=K, dim=D, num_codebooks=N, **kw))


def layers(q):
    return list(q.layers) if hasattr(q, "layers") else [q]


def set_codebooks(q, books):
    """Overwrite codebook i with books[i], keeping EMA state consistent with it."""
    with torch.no_grad():
        for layer, book in zip(layers(q), books):
            layer.embed.copy_(book)
            if layer.uses_ema:
                layer.ema_sum.copy_(book)
                layer.ema_count.fill_(1.0)


def random_codebooks(q, seed=1):
    g = torch.Generator().manual_seed(seed)
    # Later residual codebooks see smaller residuals; shrink them so they are actually used.
    set_codebooks(q, [torch.randn(q.codebook_size, q.dim, generator=g) * 0.5**i for i in range(q.num_codebooks)])


def rows(z):
    return z.transpose(1, 2).reshape(-1, z.shape[1])


def brute_force(x, books):
    """Residual nearest-code search with an explicit loop over codes, in float64."""
    r, out = x.double(), []
    for book in books:
        book = book.double()
        d = torch.empty(len(r), len(book), dtype=torch.float64)
        for k in range(len(book)):
            d[:, k] = ((r - book[k]) ** 2).sum(1)
        idx = d.argmin(1)
        out.append(idx)
        r = r - book[idx]
    return torch.stack(out, 1)


# --- assignment ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", CODEBOOK_KINDS)
def test_nearest_code_matches_brute_force(kind):
    q = make(kind, quantizer_dropout=0.0)
    random_codebooks(q)
    z = torch.randn(3, q.dim, 20, generator=torch.Generator().manual_seed(2))
    books = list(q.codebooks().clone())
    expect = brute_force(rows(z), books)
    q.eval()
    assert torch.equal(q.encode(z).reshape(-1, q.num_codebooks), expect)
    assert torch.equal(q(z).indices.reshape(-1, q.num_codebooks), expect)
    # In training, codes are assigned with the codebook as it was before this step's update.
    assert torch.equal(q.train()(z).indices.reshape(-1, q.num_codebooks), expect)


def test_distances_stay_float32_under_autocast():
    q = make("ema", K=256, D=64).eval()
    random_codebooks(q)
    z = torch.randn(4, 64, 50, generator=torch.Generator().manual_seed(3))
    expect = brute_force(rows(z), list(q.codebooks()))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = q(z)
        idx = q.encode(z)
    assert torch.equal(idx.reshape(-1, 1), expect) and torch.equal(out.indices, idx)
    assert out.losses["commit"].dtype == torch.float32


# --- gradients ----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", CODEBOOK_KINDS)
def test_straight_through_passes_gradient_unchanged(kind):
    q = make(kind).train()
    random_codebooks(q)
    books = q.codebooks().clone()
    z = torch.randn(2, q.dim, 12, requires_grad=True)
    out = q(z)
    # Forward value: exactly the sum of the (pre-update) codes of the active codebooks.
    idx = out.indices
    expect = torch.zeros(2, 12, q.dim)
    for i in range(out.stats["num_active_codebooks"]):
        expect = expect + books[i][idx[..., i]]
    assert torch.equal(out.z_q, expect.transpose(1, 2))
    w = torch.randn_like(out.z_q)
    (out.z_q * w).sum().backward()
    assert torch.equal(z.grad, w)


@pytest.mark.parametrize("kind", ["vq", "reset"])
def test_learned_codebook_gets_gradient_only_from_codebook_loss(kind):
    q = make(kind, K=8, D=4).train()
    random_codebooks(q)
    book = q.embed.detach().clone()
    z = torch.randn(2, 4, 10, requires_grad=True)
    out = q(z)
    (out.z_q.sum() + out.losses["commit"]).backward()
    assert q.embed.grad is None  # reconstruction and commitment leave the codebook alone
    x, idx = rows(z.detach()), out.indices.reshape(-1)
    # d/dz of mean ||z - sg(e)||^2 = 2 (z - e) / numel, on top of the reconstruction gradient.
    commit_grad = 2 * (x - book[idx]) / x.numel()
    assert torch.allclose(rows(z.grad), 1 + commit_grad, atol=1e-7)
    out.losses["codebook"].backward()
    expect = torch.zeros_like(book).index_add_(0, idx, 2 * (book[idx] - x) / x.numel())
    assert torch.allclose(q.embed.grad, expect, atol=1e-7)
    assert q.embed.grad[idx.unique()].abs().sum(1).gt(0).all()


def test_ema_kinds_have_no_parameters():
    for kind in ("ema", "ema_reset", "rvq"):
        assert list(make(kind).parameters()) == []


@pytest.mark.parametrize("kind", CODEBOOK_KINDS)
def test_train_steps_count_training_forwards_only(kind):
    """The step counter (a buffer, saved with the codebooks) moves once per training forward,
    and once more per residual layer a batch used; encode, decode and eval forwards leave it."""
    q = make(kind, quantizer_dropout=0.0).train()
    z = torch.randn(2, q.dim, 5)
    for step in (1, 2, 3):
        q(z)
        assert int(q.train_steps) == step
        assert all(int(layer.train_steps) == step for layer in layers(q))
    q.decode(q.encode(z))
    q.eval()(z)
    assert int(q.train_steps) == 3
    assert q.train_steps.dtype == torch.int64  # a float32 counter stops counting exactly at 2^24 steps


@pytest.mark.parametrize("kind", CODEBOOK_KINDS)
def test_encode_decode_and_eval_forward_leave_state_untouched(kind):
    q = make(kind, kmeans_init=True)
    before = {k: v.clone() for k, v in q.state_dict().items()}
    z = torch.randn(2, q.dim, 10)
    q.train().decode(q.encode(z))  # inference calls never update, even in training mode
    q.eval()(z)
    assert all(torch.equal(before[k], v) for k, v in q.state_dict().items())


# --- EMA and reset updates ----------------------------------------------------------------

def test_ema_update_on_a_hand_example():
    """K=3, D=2, decay 3/4, eps 1/4. Codes e0=(0,0), e1=(1,0), e2=(0,1); counts N=(1,1,1), sums m=e.
    Inputs (0.2,0), (0,-0.2) -> e0; (1.2,0.2), (0.8,-0.4) -> e1; e2 unused: n = (2,2,0),
    sums s0=(0.2,-0.2), s1=(2.0,-0.2), s2=(0,0).
    N <- 3/4 N + 1/4 n = (1.25, 1.25, 0.75);  m <- 3/4 m + 1/4 s: m0=(0.05,-0.05), m1=(1.25,-0.05), m2=(0,0.75).
    Laplace: sum N = 3.25, N~ = (N + 1/4) / (3.25 + 3/4) * 3.25 = (39/32, 39/32, 13/16).
    e = m / N~: e0 = (8/195, -8/195), e1 = (40/39, -8/195), e2 = (0, 12/13)."""
    q = make("ema", K=3, D=2, decay=0.75, eps=0.25).train()
    set_codebooks(q, [torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])])
    z = torch.tensor([[0.2, 0.0], [0.0, -0.2], [1.2, 0.2], [0.8, -0.4]]).t()[None]
    out = q(z)
    assert out.indices.reshape(-1).tolist() == [0, 0, 1, 1] and out.stats["dead"] == [0]  # ema never resets
    assert torch.allclose(q.ema_count, torch.tensor([1.25, 1.25, 0.75]))
    assert torch.allclose(q.ema_sum, torch.tensor([[0.05, -0.05], [1.25, -0.05], [0.0, 0.75]]))
    expect = torch.tensor([[8 / 195, -8 / 195], [40 / 39, -8 / 195], [0.0, 12 / 13]])
    assert torch.allclose(q.embed, expect, atol=1e-6)


def clustered(book, used, n=64, seed=4):
    """(1, D, n) inputs, each within 0.01 of one of the codes in `used`."""
    g = torch.Generator().manual_seed(seed)
    pick = torch.tensor(used)[torch.arange(n) % len(used)]
    return (book[pick] + 0.01 * torch.randn(n, book.shape[1], generator=g)).t()[None]


def separated_book(K=8, D=4, seed=5):
    return 5 * torch.randn(K, D, generator=torch.Generator().manual_seed(seed))


def test_reset_replaces_exactly_the_dead_codes():
    q = make("reset", K=8, D=4).train()
    book = separated_book()
    set_codebooks(q, [book])
    # Counts (4, 3, 1, 0, ...): code 2 sits exactly on the threshold (1), which is not dead.
    # Only 8 inputs for 5 dead codes, so drawing with replacement would likely repeat one.
    z = clustered(book, [0, 0, 0, 0, 1, 1, 1, 2], n=8)
    out = q(z)
    after = q.embed.detach()
    assert out.stats["dead"] == [5]
    assert torch.equal(after[:3], book[:3])  # used this step: untouched
    x = rows(z)
    for k in range(3, 8):
        assert not torch.equal(after[k], book[k])
        assert (x == after[k]).all(1).any(), f"code {k} is not one of the inputs"
    assert len(after[3:].unique(dim=0)) == 5  # drawn without replacement
    out.losses["codebook"].backward()  # the in-place reset must not break autograd


def test_reset_window_accumulates_usage_before_resetting():
    q = make("reset", K=8, D=4, reset_window=3).train()
    book = separated_book()
    set_codebooks(q, [book])
    dead = [q(clustered(book, used)).stats["dead"][0] for used in ([0, 1], [2], [0])]
    assert dead == [0, 0, 5]  # codes 0-2 were each used somewhere in the window
    assert torch.equal(q.embed.detach()[:3], book[:3])
    assert q(clustered(book, [0])).stats["dead"] == [0]  # the window restarted


def test_ema_reset_updates_live_codes_like_ema_and_resets_dead_ones():
    ema, ema_reset = make("ema", K=8, D=4).train(), make("ema_reset", K=8, D=4).train()
    book = separated_book()
    set_codebooks(ema, [book])
    ema_reset.load_state_dict(ema.state_dict())
    z = clustered(book, [0, 1, 2])
    ema(z)
    out = ema_reset(z)
    assert out.stats["dead"] == [5]
    assert torch.equal(ema_reset.embed[:3], ema.embed[:3])
    x = rows(z)
    for k in range(3, 8):
        assert (x == ema_reset.embed[k]).all(1).any()
        assert not torch.allclose(ema_reset.embed[k], ema.embed[k])
    assert torch.equal(ema_reset.ema_count[3:], torch.ones(5))
    assert torch.equal(ema_reset.ema_sum[3:], ema_reset.embed[3:])


def test_kmeans_init_runs_lloyd_once_on_the_first_training_batch():
    q = make("vq", K=4, D=2, kmeans_init=True).train()
    init = q.embed.detach().clone()
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    g = torch.Generator().manual_seed(6)
    x = centres.repeat_interleave(50, 0) + torch.randn(200, 2, generator=g)
    q(x.t()[None])
    book = q.embed.detach().clone()
    assert not torch.equal(book, init) and int(q.initted) == 1
    # A fixed point of Lloyd's algorithm: every code is the mean of the inputs nearest to it.
    idx = torch.cdist(x, book).argmin(1)
    for k in idx.unique():
        assert torch.allclose(book[k], x[idx == k].mean(0), atol=1e-4)
    q(x.t()[None])
    assert torch.equal(q.embed.detach(), book)  # not re-initialised


def test_a_kmeans_start_survives_the_first_reset_check():
    """The EMA counts of a k-means start are the cluster sizes: with a reset threshold of 2 (the
    priors'), counts of 1 would mark every code dead at the first update and replace the
    clustering with random rows of the batch."""
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    x = centres.repeat_interleave(50, 0) + torch.randn(200, 2, generator=torch.Generator().manual_seed(6))
    q = make("ema_reset", K=4, D=2, kmeans_init=True, reset_threshold=2.0).train()
    out = q(x.t()[None])
    assert out.stats["dead"] == [0]  # no code reset
    book = q.embed.detach()
    idx = torch.cdist(x, book).argmin(1)
    sizes = torch.bincount(idx, minlength=4).float()
    # the start's counts were the cluster sizes; the update of a fixed point leaves them so
    assert (sizes >= 2).all() and torch.allclose(q.ema_count, sizes)
    for k in range(4):  # and the codes the clusters' means: Lloyd's result, not random rows
        assert torch.allclose(book[k], x[idx == k].mean(0), atol=1e-4)


def far_batch(n=64, D=8, seed=13):
    """(1, D, n) encoder outputs around 5, far outside the uniform start's [-1/K, 1/K]."""
    return (5 + torch.randn(n, D, generator=torch.Generator().manual_seed(seed))).t()[None]


@pytest.mark.parametrize("kind", ["vq", "ema", "reset", "ema_reset"])
def test_t2m_gpt_init_starts_each_kind_as_the_official_code(kind):
    """T2M-GPT (models/quantize_cnn.py): the plain quantizer starts at U(-1/K, 1/K); EMA, reset
    and EMA+reset take K rows of the first training batch, with EMA counts 1 and sums = codes."""
    K, D = 16, 8
    q = make(kind, K=K, D=D, init="t2m_gpt").train()
    start = q.embed.detach().clone()
    assert start.abs().max() <= 1.0 / K
    z = far_batch(D=D)
    x = rows(z)
    out = q(z)
    idx = out.indices.reshape(-1)
    codes = rows(out.z_q.detach())  # the codes this step was assigned to, before its update
    if kind == "vq":
        assert int(q.initted) == 1 and out.stats["usage"][0] < 0.5  # far data lands on a few codes
        assert codes.abs().max() <= 1.0 / K
        return
    assert int(q.initted) == 1 and out.stats["usage"] == [1.0]  # each code wins at least its own row
    for k in idx.unique():  # every code is one of the batch's rows, exactly
        assert (x == codes[idx == k][0]).all(1).any()
    assert len(codes.unique(dim=0)) == K  # drawn without replacement
    if q.uses_ema:
        c = torch.zeros(K, D).index_copy_(0, idx, codes)
        n = torch.bincount(idx, minlength=K).float()
        sums = torch.zeros(K, D).index_add_(0, idx, x)
        assert torch.allclose(q.ema_count, 0.99 * 1.0 + 0.01 * n)
        assert torch.allclose(q.ema_sum, 0.99 * c + 0.01 * sums, atol=1e-6)
    q(far_batch(D=D, seed=14))
    assert int(q.initted) == 1  # only the first batch initialises


@pytest.mark.parametrize("init", ["batch", "t2m_gpt"])
def test_batch_init_with_fewer_rows_than_codes_adds_t2m_gpt_noise(init):
    K, D = 16, 8
    q = make("ema", K=K, D=D, init=init).train()
    z = far_batch(n=10, D=D)
    out = q(z)
    err = (out.z_q - z).abs()
    # Each row went to a noisy copy of itself: N(0, (0.01/sqrt(D))^2) per coordinate.
    assert err.max() > 0 and err.max() < 6 * 0.01 / math.sqrt(D)
    assert len(q.embed.unique(dim=0)) == K  # no two codes tie


def test_uniform_init_is_the_old_start_and_bad_inits_are_refused():
    for kind in ("ema", "reset", "ema_reset"):
        q = make(kind, init="uniform").train()
        out = q(far_batch())
        assert int(q.initted) == 1 and out.stats["usage"][0] < 0.5  # started at U(-1/K, 1/K): a few codes win
    assert make("ema").init_method == "uniform"  # the shared default, which the physics priors use
    assert make("ema", kmeans_init=True).init_method == "kmeans"
    for bad in ({"init": "random"}, {"init": "batch", "kmeans_init": True}):
        with pytest.raises(ValueError, match="init"):
            make("ema", **bad)


def line_book(*xs):
    """Codes (x, 0) on a line, far apart: which code a row (x', 0) goes to is read off by eye."""
    return torch.tensor([[float(x), 0.0] for x in xs])


def on_line(*xs):
    """(1, 2, n) inputs (x, 0)."""
    return line_book(*xs).t()[None]


def test_reset_window_counts_usage_per_window_and_resets_from_the_batch():
    """reset_window 2, threshold 1, codes at x = 0, 10, 20, 30. Window 1: step 1 uses codes 0, 1, 2,
    step 2 code 0 twice; code 3 alone unused, so exactly one code is reset, to the only row value of
    step 2, (1, 0). Window 2 starts from zero counts: steps 3-4 use codes 1 and 2 only, so codes 0
    (busy in window 1) and 3 (the new one, unused) are dead, and take the two rows of step 4."""
    q = make("reset", K=4, D=2, reset_window=2).train()
    set_codebooks(q, [line_book(0, 10, 20, 30)])
    assert q(on_line(0.1, 10.1, 20.1)).stats["dead"] == [0]  # step 1: no check
    assert q(on_line(1, 1)).stats["dead"] == [1]
    assert torch.equal(q.embed.detach(), line_book(0, 10, 20, 1))
    assert q(on_line(10.3)).stats["dead"] == [0]
    out = q(on_line(10.4, 20.4))
    assert out.indices.reshape(-1).tolist() == [1, 2] and out.stats["dead"] == [2]
    after = q.embed.detach()
    assert torch.equal(after[1:3], line_book(10, 20))
    assert sorted(float(after[k, 0]) for k in (0, 3)) == pytest.approx([10.4, 20.4])


def test_as_many_dead_codes_as_rows_take_every_row_once():
    """8 dead codes and a batch of 8 distinct rows: drawn without replacement, the new codes are
    the rows themselves in some order (with replacement, 8 draws repeat one with probability
    1 - 8!/8^8 > 0.99)."""
    q = make("reset", K=10, D=2).train()
    set_codebooks(q, [line_book(*range(0, 100, 10))])
    xs = [0.1, 0.2, 0.3, 0.4, 10.1, 10.2, 10.3, 10.4]
    assert q(on_line(*xs)).stats["dead"] == [8]
    assert sorted(float(v) for v in q.embed.detach()[2:, 0]) == pytest.approx(xs)


def test_a_reset_ema_code_restarts_with_count_and_sum_of_the_threshold():
    """ema_reset, decay 1/2, threshold 2, codes (0,0), (10,0), (0,10), (10,10) with counts 1.
    Four rows around code 0 (sum (0,0)) and four around code 1 (sum (40,0)): n = (4, 4, 0, 0),
    N <- N/2 + n/2 = (2.5, 2.5, 0.5, 0.5), m <- m/2 + s/2: m0 = (0,0), m1 = (25,0); codes 2 and 3
    fall under 2 and restart as rows of the batch with count 2 and sum 2 x the row."""
    q = make("ema_reset", K=4, D=2, decay=0.5, reset_threshold=2.0).train()
    set_codebooks(q, [torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])])
    x = torch.tensor([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.1], [0.0, -0.1],
                      [10.1, 0.0], [9.9, 0.0], [10.0, 0.1], [10.0, -0.1]])
    out = q(x.t()[None])
    assert out.indices.reshape(-1).tolist() == [0] * 4 + [1] * 4 and out.stats["dead"] == [2]
    assert torch.equal(q.ema_count, torch.tensor([2.5, 2.5, 2.0, 2.0]))
    assert torch.allclose(q.ema_sum[:2], torch.tensor([[0.0, 0.0], [25.0, 0.0]]), atol=1e-6)
    assert torch.allclose(q.embed[:2], torch.tensor([[0.0, 0.0], [10.0, 0.0]]), atol=1e-4)  # m / N~, N~ ~ N
    new = q.embed[2:]
    assert all((x == row).all(1).any() for row in new) and not torch.equal(new[0], new[1])
    assert torch.equal(q.ema_sum[2:], 2 * new)


# --- residual VQ --------------------------------------------------------------------------

def test_rvq_z_q_is_the_sum_of_codebook_vectors_and_any_prefix_decodes():
    q = make("rvq", N=4).eval()
    random_codebooks(q)
    z = torch.randn(2, q.dim, 15, generator=torch.Generator().manual_seed(7))
    out = q(z)
    idx, books = out.indices, q.codebooks()
    manual = torch.zeros(2, 15, q.dim)
    for i in range(4):
        manual = manual + books[i][idx[..., i]]
    assert torch.equal(out.z_q, manual.transpose(1, 2))
    assert torch.equal(q.decode(q.encode(z)), out.z_q)
    for m in range(1, 5):
        part = q.encode(z, num_codebooks=m)
        assert torch.equal(part[..., :m], idx[..., :m]) and (part[..., m:] == -1).all()
        assert torch.equal(q(z, num_codebooks=m).z_q, q.decode(part))
        assert torch.equal(q.decode(idx, num_codebooks=m), q.decode(idx[..., :m]))


def test_rvq_residual_error_does_not_grow_with_more_codebooks(golden_features, golden_dir):
    mean, std = np.load(golden_dir / "Mean.npy"), np.load(golden_dir / "Std.npy")
    feats = torch.from_numpy(((golden_features - mean) / std).astype(np.float32))  # (170, 263)
    q = make("rvq", K=32, D=feats.shape[1], N=4, quantizer_dropout=0.0, kmeans_init=True).train()
    g = torch.Generator().manual_seed(8)
    for _ in range(20):
        starts = torch.randint(0, len(feats) - 32, (4,), generator=g)
        q(torch.stack([feats[s:s + 32] for s in starts.tolist()]).transpose(1, 2))
    q.eval()
    z = feats.t()[None]
    err = [float(z.pow(2).mean())]
    err += [float((z - q.decode(q.encode(z, m))).pow(2).mean()) for m in range(1, 5)]
    assert all(b <= a + 1e-6 for a, b in zip(err, err[1:])), err
    assert err[4] < 0.5 * err[1], err


def test_rvq_quantizer_dropout_uses_a_prefix_and_leaves_the_rest_untouched():
    q = make("rvq", N=3, quantizer_dropout=1.0).train()
    random_codebooks(q)
    g = torch.Generator().manual_seed(9)
    seen = set()
    for _ in range(30):
        before = q.codebooks().clone()
        steps = [int(layer.train_steps) for layer in q.layers]
        out = q(torch.randn(2, q.dim, 10, generator=g))
        m = out.stats["num_active_codebooks"]
        seen.add(m)
        assert (out.indices[..., :m] >= 0).all() and (out.indices[..., m:] == -1).all()
        assert torch.equal(q.codebooks()[m:], before[m:])
        assert [int(layer.train_steps) for layer in q.layers[m:]] == steps[m:]
        assert not torch.equal(q.codebooks()[:m], before[:m])  # EMA moved the active ones
        assert out.stats["usage"][m:] == [0.0] * (3 - m) and all(u > 0 for u in out.stats["usage"][:m])
    assert seen == {1, 2, 3}
    no_drop = make("rvq", N=3, quantizer_dropout=0.0).train()
    assert {no_drop(torch.randn(2, 8, 10)).stats["num_active_codebooks"] for _ in range(10)} == {3}


def test_rvq_quantizer_dropout_share_of_steps_under_a_seed():
    """quantizer_dropout 0.5 over N = 4: half the steps draw M ~ U{1..4}, so M < 4 on
    0.5 * 3/4 = 37.5 % of the steps and each M < 4 on 12.5 % (200 steps: binomial std 3.4 %
    and 2.3 %). Codebooks left out report index -1 and no reset; an explicit M always wins."""
    q = make("rvq", K=4, D=2, N=4, quantizer_dropout=0.5, rvq_base="ema").train()
    g = torch.Generator().manual_seed(15)
    seen = []
    for _ in range(200):
        out = q(torch.randn(3, 2, generator=g))
        m = out.stats["num_active_codebooks"]
        seen.append(m)
        assert out.stats["dead"] == [0, 0, 0, 0] and (out.indices[:, m:] == -1).all()
        assert out.stats["usage"][m:] == out.stats["perplexity"][m:] == [0.0] * (4 - m)
    assert abs(sum(m < 4 for m in seen) / 200 - 0.375) < 0.1
    for m in (1, 2, 3):
        assert abs(seen.count(m) / 200 - 0.125) < 0.07, (m, seen.count(m))
    assert all(q(torch.randn(3, 2), num_codebooks=2).stats["num_active_codebooks"] == 2 for _ in range(20))


def test_single_codebook_kinds_refuse_more_than_one_codebook():
    for kind in ("vq", "ema_reset", "fsq"):
        q = build_quantizer(QuantizerConfig(kind=kind, codebook_size=4, dim=3, fsq_levels=[2, 3]))
        z = torch.randn(2, 3)
        assert q(z, num_codebooks=1).indices.shape == (2, 1)
        for call in (lambda: q(z, num_codebooks=2), lambda: q.encode(z, num_codebooks=2),
                     lambda: q.decode(torch.zeros(2, 1, dtype=torch.long), num_codebooks=2)):
            with pytest.raises(ValueError, match="num_codebooks must be in 1..1"):
                call()


# --- FSQ ----------------------------------------------------------------------------------

@pytest.mark.parametrize("levels", [[8, 5, 5, 5], [2, 3, 4]])
def test_fsq_indices_round_trip(levels):
    q = build_quantizer(QuantizerConfig(kind="fsq", dim=len(levels), fsq_levels=levels)).eval()
    K = math.prod(levels)
    assert q.codebook_size == K
    grid = q.codebooks()[0]  # (K, d): every point of the implicit codebook
    assert len(grid.unique(dim=0)) == K and grid.abs().max() <= 1.0
    # encode bounds its input with tanh first, so feed the pre-images of the grid points
    # (pulled in slightly: atanh(+-1) is infinite).
    pre = torch.atanh(grid * (1 - 1e-6))
    assert torch.equal(q.encode(pre.t()[None]).reshape(-1), torch.arange(K))
    assert torch.equal(q.decode(torch.arange(K).reshape(1, K, 1)), grid.t()[None])


def test_fsq_forward_matches_encode_decode_and_trains_the_projection():
    q = build_quantizer(QuantizerConfig(kind="fsq", dim=16)).train()
    z = torch.randn(2, 16, 9, requires_grad=True)
    out = q(z)
    assert out.indices.shape == (2, 9, 1) and 0 <= int(out.indices.min()) and int(out.indices.max()) < 1000
    out.z_q.pow(2).sum().backward()
    assert z.grad.abs().sum() > 0 and q.project_in.weight.grad.abs().sum() > 0
    assert float(out.losses["commit"]) == 0.0
    q.eval()
    assert torch.equal(q(z).z_q, q.decode(q.encode(z)))


def test_fsq_codes_indices_and_statistics_on_hand_values():
    """Levels (3, 4) on a 2-d latent (no projections): channel 0 takes tanh(h) rounded to
    {-1, 0, 1}; channel 1 takes 1.5 tanh(h) rounded to the half-integers {-1.5, -0.5, 0.5, 1.5},
    divided by 1.5. Index = i0 + 3 i1 with i = code * half_width + half_width.
    Rows tanh(h) = (0.9, -0.9) [twice], (-0.2, 0.2), (-0.6, 0.5), (0.5, 0.99):
    channel 0: 0.9 -> 1; -0.2 -> 0; -0.6 -> -1; 0.5 -> 0 (a tie, rounded to even as torch.round);
    channel 1: -1.35 -> -1.5; 0.3 -> 0.5; 0.75 -> 0.5; 1.485 -> 1.5.
    Indices 2 + 0, 1 + 6, 0 + 6, 1 + 9 = 2, 7, 6, 10 of K = 12; histogram 2, 1, 1, 1 of 5:
    usage 4/12, perplexity exp(-(0.4 ln 0.4 + 3 * 0.2 ln 0.2))."""
    q = build_quantizer(QuantizerConfig(kind="fsq", dim=2, fsq_levels=[3, 4]))
    v = torch.tensor([[0.9, -0.9], [0.9, -0.9], [-0.2, 0.2], [-0.6, 0.5], [0.5, 0.99]])
    h = torch.atanh(v)
    assert float(torch.tanh(h[4, 0])) == 0.5  # the tie is exact in float32
    codes = torch.tensor([[1.0, -1.0], [1.0, -1.0], [0.0, 1 / 3], [-1.0, 1 / 3], [0.0, 1.0]])
    perplexity = math.exp(-(0.4 * math.log(0.4) + 3 * 0.2 * math.log(0.2)))
    for mode in (q.eval(), q.train()):
        out = mode(h)
        assert torch.allclose(out.z_q, codes, atol=1e-7)
        assert out.indices.reshape(-1).tolist() == [2, 2, 7, 6, 10]
        assert out.stats["usage"] == [pytest.approx(4 / 12)] and out.stats["dead"] == [0]
        assert out.stats["perplexity"] == [pytest.approx(perplexity, rel=1e-6)]
        assert out.stats["num_active_codebooks"] == 1
        assert float(out.losses["commit"]) == 0.0 and float(out.losses["codebook"]) == 0.0
    assert q.encode(h).reshape(-1).tolist() == [2, 2, 7, 6, 10]
    assert torch.allclose(q.decode(torch.tensor([[2], [7], [6], [10]])), codes[1:], atol=1e-7)


def test_fsq_saves_only_its_seed_steps_and_projections():
    """The grid (levels, mixed-radix basis, half widths, shifts) follows from the config: a
    checkpoint holds none of it, so bundles written before and after keep loading."""
    for dim, extra in ((2, set()), (5, {"project_in.weight", "project_in.bias", "project_out.weight",
                                          "project_out.bias"})):
        q = build_quantizer(QuantizerConfig(kind="fsq", dim=dim, fsq_levels=[3, 4]))
        assert set(q.state_dict()) == {"rng_seed", "train_steps"} | extra


# --- statistics, config, checkpoints ------------------------------------------------------

def test_usage_and_perplexity_on_a_hand_example():
    """Histogram (2, 1, 1, 0): p = (1/2, 1/4, 1/4, 0), H = 1/2 ln 2 + 2 * 1/4 ln 4 = 3/2 ln 2,
    perplexity = 2^1.5; usage = 3/4."""
    q = make("vq", K=4, D=2).eval()
    set_codebooks(q, [torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])])
    z = torch.tensor([[0.1, 0.0], [0.0, 0.1], [9.9, 0.0], [0.0, 9.9]]).t()[None]
    stats = q(z).stats
    assert stats["usage"] == [0.75] and stats["dead"] == [0] and stats["num_active_codebooks"] == 1
    assert stats["perplexity"][0] == pytest.approx(2**1.5, rel=1e-6)


def test_config_validation_and_yaml_style_construction():
    for bad in ({"kind": "lfq"}, {"kind": "ema", "num_codebooks": 2}, {"kind": "rvq", "rvq_base": "fsq"},
                {"kind": "fsq", "fsq_levels": [1, 4]}, {"decay": 1.0}):
        with pytest.raises(ValueError):
            build_quantizer(QuantizerConfig(**bad))
    cfg = from_dict(QuantizerConfig, {"kind": "fsq", "dim": 8, "fsq_levels": [4, 4]})
    assert build_quantizer(cfg).codebook_size == 16


def test_config_validation_names_each_bad_value_and_accepts_the_boundaries():
    SIZES = "codebook_size, dim, num_codebooks and reset_window must be >= 1"
    RANGES = "need 0 <= decay < 1, eps >= 0 and 0 <= quantizer_dropout <= 1"
    bad = [("kind 'lfq' is not one of", dict(kind="lfq")),
           ("rvq_base 'fsq' is not one of", dict(kind="rvq", rvq_base="fsq")),
           ("num_codebooks=2 needs kind 'rvq'", dict(kind="ema", num_codebooks=2)),
           (SIZES, dict(codebook_size=0)), (SIZES, dict(dim=0)),
           (SIZES, dict(kind="rvq", num_codebooks=0)), (SIZES, dict(reset_window=0)),
           (RANGES, dict(decay=1.0)), (RANGES, dict(decay=-0.1)), (RANGES, dict(eps=-1e-5)),
           (RANGES, dict(quantizer_dropout=1.5)), (RANGES, dict(quantizer_dropout=-0.5)),
           ("init 'random' is not one of", dict(init="random")),
           ("kmeans_init=true contradicts init='batch'", dict(init="batch", kmeans_init=True)),
           (r"fsq_levels must be a non-empty list of integers >= 2, got \[1, 4\]", dict(kind="fsq", fsq_levels=[1, 4])),
           ("fsq_levels must be", dict(kind="fsq", fsq_levels=[]))]
    for message, kw in bad:
        with pytest.raises(ValueError, match=f"^bad QuantizerConfig: (.*; )?{message}"):  # each problem whole
            build_quantizer(QuantizerConfig(**kw))
    with pytest.raises(ValueError, match="kind 'lfq' is not one of .*; need 0 <= decay < 1"):  # every problem, joined
        build_quantizer(QuantizerConfig(kind="lfq", decay=2.0))
    for kw in (dict(decay=0.0, eps=0.0, quantizer_dropout=0.0), dict(kind="rvq", num_codebooks=1, quantizer_dropout=1.0),
               dict(codebook_size=1, dim=1, reset_window=1), dict(init="kmeans", kmeans_init=True),
               dict(kind="fsq", fsq_levels=[2])):
        build_quantizer(QuantizerConfig(**kw))
    kinds = {kind: type(build_quantizer(QuantizerConfig(kind=kind, num_codebooks=2 if kind == "rvq" else 1))).__name__
             for kind in ("vq", "ema", "reset", "ema_reset", "rvq", "fsq")}
    assert kinds == {"vq": "VectorQuantizer", "ema": "VectorQuantizer", "reset": "VectorQuantizer",
                     "ema_reset": "VectorQuantizer", "rvq": "ResidualVQ", "fsq": "FSQuantizer"}


def test_output_keeps_the_input_dtype():
    q = make("ema", K=4, D=2).eval()
    set_codebooks(q, [torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])])
    z = torch.tensor([[0.9, 0.1], [0.1, 0.8]], dtype=torch.bfloat16)
    out = q(z)
    assert out.z_q.dtype == torch.bfloat16 and out.losses["commit"].dtype == torch.float32
    assert out.indices.tolist() == [[1], [2]] and torch.equal(out.z_q.float(), torch.tensor([[1.0, 0.0], [0.0, 1.0]]))


@pytest.mark.parametrize("kind", ["ema_reset", "rvq", "vq", "fsq"])
def test_state_round_trips_through_safetensors(kind, tmp_path):
    from safetensors.torch import load_file, save_file

    q = make(kind).train()
    z = torch.randn(2, 8, 10)
    for _ in range(3):
        q(z)
    save_file({k: v.contiguous() for k, v in q.state_dict().items()}, str(tmp_path / "q.safetensors"))
    fresh = make(kind, seed=123)
    fresh.load_state_dict(load_file(str(tmp_path / "q.safetensors")))
    assert torch.equal(fresh.eval().encode(z), q.eval().encode(z))


# --- per-item latents (B, D) --------------------------------------------------------------

ALL_KINDS = {
    "vq": dict(kind="vq"),
    "ema": dict(kind="ema"),
    # threshold 1.5 with 16 codes for 12 rows: codes die every step, so resets are exercised.
    "reset": dict(kind="reset", reset_window=2, reset_threshold=1.5),
    "ema_reset": dict(kind="ema_reset", kmeans_init=True, reset_threshold=1.5),
    "rvq": dict(kind="rvq", num_codebooks=3, quantizer_dropout=0.5),
    "fsq": dict(kind="fsq", fsq_levels=[4, 3, 3]),
}


def twins(kw, seed=10):
    """Two quantizers with the same initial state: one fed (B, D), one (B, D, 1)."""
    out = []
    for _ in range(2):
        torch.manual_seed(seed)
        out.append(build_quantizer(QuantizerConfig(codebook_size=16, dim=8, **kw)).train())
    return out


@pytest.mark.parametrize("name", list(ALL_KINDS))
def test_per_item_latents_equal_length_one_sequences(name):
    flat, seq = twins(ALL_KINDS[name])
    g = torch.Generator().manual_seed(11)
    params_f, params_s = list(flat.parameters()), list(seq.parameters())
    resets = 0
    for _ in range(8):
        z = 2 * torch.randn(12, 8, generator=g)
        z2, z3 = z.clone().requires_grad_(), z[..., None].clone().requires_grad_()
        a, b = flat(z2), seq(z3)
        assert a.z_q.shape == (12, 8) and a.indices.shape == (12, flat.num_codebooks)
        assert torch.equal(a.z_q, b.z_q[..., 0]) and torch.equal(a.indices, b.indices[:, 0])
        assert a.losses.keys() == b.losses.keys()
        assert all(torch.equal(a.losses[k], b.losses[k]) for k in a.losses)
        assert a.stats == b.stats
        resets += sum(a.stats["dead"])
        w = torch.randn(12, 8, generator=g)
        for out, w_ in ((a, w), (b, w[..., None])):
            ((out.z_q * w_).sum() + out.losses["commit"] + out.losses["codebook"]).backward()
        assert torch.equal(z2.grad, z3.grad[..., 0])
        for pf, ps in zip(params_f, params_s):
            assert torch.equal(pf.grad, ps.grad)
            pf.grad = ps.grad = None
        sf, ss = flat.state_dict(), seq.state_dict()
        assert all(torch.equal(sf[k], ss[k]) for k in sf)
    if name in ("reset", "ema_reset"):
        assert resets > 0
    flat.eval(), seq.eval()
    z = torch.randn(5, 8, generator=g)
    idx = flat.encode(z)
    assert idx.shape == (5, flat.num_codebooks) and torch.equal(idx, seq.encode(z[..., None])[:, 0])
    assert torch.equal(flat.decode(idx), seq.decode(idx[:, None])[..., 0])
    assert torch.equal(flat.decode(idx), flat(z).z_q)
    for m in range(1, flat.num_codebooks + 1):
        part = flat.encode(z, num_codebooks=m)
        assert torch.equal(part, seq.encode(z[..., None], num_codebooks=m)[:, 0])
        assert torch.equal(flat.decode(part[:, :m]), flat(z, num_codebooks=m).z_q)


@pytest.mark.parametrize("kind", CODEBOOK_KINDS)
def test_straight_through_reaches_per_item_latents_exactly(kind):
    q = make(kind).train()
    random_codebooks(q)
    books = q.codebooks().clone()
    z = torch.randn(6, q.dim, requires_grad=True)
    out = q(z)
    expect = sum(books[i][out.indices[:, i]] for i in range(out.stats["num_active_codebooks"]))
    assert torch.equal(out.z_q, expect)
    w = torch.randn_like(out.z_q)
    (out.z_q * w).sum().backward()
    assert torch.equal(z.grad, w)


def test_fsq_straight_through_skips_only_the_rounding():
    # dim == len(levels): no projections, so z_q = round(tanh(z) * h) / h and the estimator
    # gives dz_q/dz = 1 - tanh(z)^2, the derivative of the bound alone.
    q = build_quantizer(QuantizerConfig(kind="fsq", dim=3, fsq_levels=[2, 3, 4])).train()
    z = torch.randn(7, 3, requires_grad=True)
    out = q(z)
    h = (q.levels.float() - 1) / 2
    shift = (1 - q.levels % 2).float() / 2
    expect = (torch.round(torch.tanh(z.detach()) * h - shift) + shift) / h
    assert torch.allclose(out.z_q, expect, atol=1e-7)
    w = torch.randn_like(out.z_q)
    (out.z_q * w).sum().backward()
    assert torch.allclose(z.grad, w * (1 - torch.tanh(z.detach()) ** 2), atol=1e-6)


def test_per_item_latents_under_autocast_and_bad_shapes():
    q = make("ema", K=64, D=16).eval()
    random_codebooks(q)
    z = torch.randn(32, 16, generator=torch.Generator().manual_seed(12))
    expect = brute_force(z, list(q.codebooks()))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = q(z)
    assert torch.equal(out.indices, expect) and out.z_q.dtype == torch.float32
    for kind in ALL_KINDS:
        q = build_quantizer(QuantizerConfig(codebook_size=16, dim=8, **{**ALL_KINDS[kind], "kmeans_init": False}))
        for bad in (torch.randn(4, 7), torch.randn(4, 8, 2, 1), torch.randn(8)):
            with pytest.raises(ValueError, match="expected z"):
                q(bad)
            with pytest.raises(ValueError, match="expected z"):
                q.encode(bad)
        with pytest.raises(ValueError, match="expected indices"):
            q.decode(torch.zeros(4, dtype=torch.long))


# --- construction order -------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["vq", "ema_reset", "rvq", "fsq"])
def test_initial_state_follows_the_documented_draw_order(kind):
    """Fixed-seed runs (and so every recorded result) depend on the order in which a new
    quantizer draws from the global RNG: its generator seed, then its codes (per residual
    layer: seed, then codes), then FSQ's projections."""
    K, D = 16, 8
    q = make(kind, K=K, D=D, seed=3)
    torch.manual_seed(3)
    assert torch.equal(q.rng_seed, torch.randint(0, 2**62, (1,)))
    if kind == "fsq":
        p_in, p_out = torch.nn.Linear(D, 4), torch.nn.Linear(4, D)
        assert torch.equal(q.project_in.weight, p_in.weight) and torch.equal(q.project_out.bias, p_out.bias)
        return
    for layer in layers(q):
        if layer is not q:
            assert torch.equal(layer.rng_seed, torch.randint(0, 2**62, (1,)))
        assert torch.equal(layer.embed, torch.empty(K, D).uniform_(-1.0 / K, 1.0 / K))


# --- distributed --------------------------------------------------------------------------

DDP_CONFIGS = {
    # threshold 1.5: codes die every step, so resets also follow the k-means init in step 1.
    "ema_reset": dict(kind="ema_reset", codebook_size=16, dim=8, kmeans_init=True, reset_threshold=1.5),
    # dropout 0.5, not 1.0: whether to drop must also agree across ranks.
    "rvq": dict(kind="rvq", codebook_size=16, dim=8, num_codebooks=3, quantizer_dropout=0.5),
    "reset": dict(kind="reset", codebook_size=16, dim=8, reset_window=2),
    # the T2M-GPT start: codes drawn from both ranks' first batches must agree too.
    "ema_reset_batch": dict(kind="ema_reset", codebook_size=16, dim=8, init="batch", reset_threshold=1.5),
    "fsq": dict(kind="fsq", dim=8, fsq_levels=[4, 4, 3]),
}


def _ddp_worker(rank: int, world: int, port: int, out_dir: str) -> None:
    torch.set_num_threads(1)
    # A timeout, so ranks issuing mismatched collectives fail the test instead of hanging it.
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world,
                            timeout=datetime.timedelta(seconds=20))
    try:
        results = {}
        for name, kw in DDP_CONFIGS.items():
            torch.manual_seed(100 + rank)  # different initial codebooks: the first step must align them
            q = build_quantizer(QuantizerConfig(**kw)).train()
            g = torch.Generator().manual_seed(1000 + rank)
            stats = []
            for _ in range(10):
                # Different data and different batch sizes on each rank.
                z = (1 + rank) * torch.randn(3 + rank, 8, 6, generator=g) + rank
                stats.append(q(z).stats)
            results[name] = {"state": q.state_dict(), "stats": stats}
        torch.save(results, os.path.join(out_dir, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_training_keeps_codebooks_identical(tmp_path):
    mp.spawn(_ddp_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    for name in DDP_CONFIGS:
        s0, s1 = r0[name]["state"], r1[name]["state"]
        assert s0.keys() == s1.keys()
        for k in s0:
            assert torch.equal(s0[k], s1[k]), f"{name}: {k} differs between ranks"
        assert r0[name]["stats"] == r1[name]["stats"]
        if name != "fsq":
            assert sum(sum(s["dead"]) for s in r0[name]["stats"]) > 0, f"{name}: no reset was exercised"
    assert {s["num_active_codebooks"] for s in r0["rvq"]["stats"]} == {1, 2, 3}
