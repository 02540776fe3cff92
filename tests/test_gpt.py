"""The text-to-motion GPT: KV cache, End/Pad, corruption, overfitting, sampling, resume, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.checkpoint import load_bundle
from motok.config import load_config
from motok.data.dataset import MotionFile
from motok.gpt.model import GPTConfig, MotionGPT, count_parameters
from motok.gpt.sample import filter_logits, generate
from motok.gpt.train import IGNORE, TrainConfig, corrupt, gpt_loss, make_batch, resolve_config, train

K, TEXT_DIM = 16, 8


pytestmark = pytest.mark.usefixtures("one_thread")


def tiny(block_size: int = 12, dropout: float = 0.0, layers: int = 2, dim: int = 32) -> MotionGPT:
    torch.manual_seed(0)
    cfg = GPTConfig(num_layers=layers, dim=dim, heads=4, block_size=block_size, dropout=dropout)
    return MotionGPT(cfg, K, TEXT_DIM)


# --------------------------------------------------------------------------- model (synthetic tokens)

def test_kv_cache_logits_equal_full_recomputation():
    model = tiny().eval()
    text = torch.randn(3, TEXT_DIM)
    a = generate(model, text, seeds=[0, 1, 2], record_logits=True, use_cache=True)
    b = generate(model, text, seeds=[0, 1, 2], record_logits=True, use_cache=False)
    assert [c.tolist() for c in a.codes] == [c.tolist() for c in b.codes]
    assert len(a.logits) == len(b.logits) > 1
    for x, y in zip(a.logits, b.logits):
        torch.testing.assert_close(x, y, atol=1e-5, rtol=1e-5)
    # A prefill of several positions after cached ones (the masked path) matches too.
    idx = torch.randint(0, K, (3, 7))
    full = model(text, idx)
    cache = model.new_cache(3)
    first = model(text, idx[:, :2], cache)
    rest = model(None, idx[:, 2:], cache)
    torch.testing.assert_close(torch.cat([first, rest], 1), full, atol=1e-5, rtol=1e-5)


def test_end_and_pad_handling():
    model = tiny().eval()
    assert (model.end_id, model.pad_id) == (K, K + 1)
    assert model.head.out_features == K + 1  # codes + End: Pad is never predicted
    seqs = [torch.tensor([3, 4, 5]), torch.tensor([7])]
    inp, tgt = make_batch(seqs, [True, False], model.end_id, model.pad_id)
    assert inp.tolist() == [[3, 4, 5], [7, K + 1, K + 1]]
    assert tgt.tolist() == [[3, 4, 5, K], [7, IGNORE, IGNORE, IGNORE]]  # a crop that stops early: no End
    text = torch.randn(2, TEXT_DIM)
    # Causality: Pads after the sequence change nothing before them, and the loss ignores them.
    short = model(text[1:], inp[1:, :1])
    padded = model(text[1:], inp[1:])
    torch.testing.assert_close(padded[:, :2], short, atol=1e-6, rtol=1e-6)
    loss_short, _ = gpt_loss(short, tgt[1:, :2])
    loss_padded, _ = gpt_loss(padded, tgt[1:])
    torch.testing.assert_close(loss_short, loss_padded)
    # Sampling: End is never the first token; finished rows stop at their End.
    biased = tiny().eval()
    with torch.no_grad():
        # ln_f's output then sums to dim at every position, so End's logit is 50 * dim: End wins.
        biased.ln_f.bias.fill_(1.0)
        biased.head.weight[K] = 50.0
    g = generate(biased, text, seeds=[0, 1])
    assert [len(c) for c in g.codes] == [1, 1] and g.steps == 2
    assert all(int(c.max()) < K for c in g.codes)


@pytest.mark.parametrize("tau", [0.0, 0.3, 0.5, 1.0])
def test_corruption_rate_matches_tau(tau):
    gen = torch.Generator().manual_seed(0)
    codes = torch.randint(0, K, (400, 50), generator=gen)
    valid = torch.ones_like(codes, dtype=torch.bool)
    valid[:, 40:] = False  # Pad positions are never touched
    out, hit = corrupt(codes, valid, torch.full((400,), tau), K, gen)
    changed = out != codes
    assert torch.equal(changed, hit) and not changed[:, 40:].any()
    assert abs(changed[:, :40].float().mean().item() - tau) < 0.01
    assert out.min() >= 0 and out.max() < K
    u, hit_u = corrupt(codes, valid, torch.rand(400, generator=gen), K, gen)
    assert abs(hit_u[:, :40].float().mean().item() - 0.5) < 0.05  # tau ~ U[0, 1]: 0.5 on average


def test_tiny_model_overfits_tiny_batch():
    model = tiny(block_size=10, layers=2, dim=64).train()
    gen = torch.Generator().manual_seed(1)
    text = torch.randn(4, TEXT_DIM, generator=gen)
    seqs = [torch.randint(0, K, (n,), generator=gen) for n in (3, 5, 7, 9)]
    inp, tgt = make_batch(seqs, [True] * 4, model.end_id, model.pad_id)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3, betas=(0.5, 0.99))
    for _ in range(150):
        loss, _ = gpt_loss(model(text, inp), tgt)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.02
    g = generate(model, text, argmax=True)
    assert [c.tolist() for c in g.codes] == [s.tolist() for s in seqs]


def test_target_length_seeds_and_filters():
    model = tiny().eval()
    text = torch.randn(3, TEXT_DIM)
    g = generate(model, text, target_len=torch.tensor([2, 5, 99]), seeds=[0, 1, 2])
    assert [len(c) for c in g.codes] == [2, 5, model.max_codes]  # 99 is clamped to the positions
    a = generate(model, text, seeds=[4, 5, 6], top_k=5, top_p=0.9, temperature=0.8)
    b = generate(model, text, seeds=[4, 5, 6], top_k=5, top_p=0.9, temperature=0.8)
    assert [c.tolist() for c in a.codes] == [c.tolist() for c in b.codes]
    # A row's draw depends on its own seed only, not on its batch neighbours.
    alone = generate(model, text[1:2], seeds=[5], top_k=5, top_p=0.9, temperature=0.8)
    assert alone.codes[0].tolist() == a.codes[1].tolist()
    c = generate(model, text, seeds=[7, 8, 9])
    assert [x.tolist() for x in c.codes] != [x.tolist() for x in generate(model, text, seeds=[0, 1, 2]).codes]
    lg = torch.tensor([[4.0, 3.0, 2.0, 1.0, 0.0]])
    assert torch.isfinite(filter_logits(lg, top_k=2)).sum() == 2
    assert torch.isfinite(filter_logits(lg, top_p=1e-3)).sum() == 1  # the best code always survives


def test_paper_recipe_is_the_paper_size():
    cfg = load_config(TrainConfig, "recipes/gpt/paper.yaml")
    assert (cfg.model.num_layers, cfg.model.dim, cfg.model.heads, cfg.model.block_size) == (18, 1024, 16, 51)
    assert cfg.optim.betas == [0.5, 0.99] and cfg.optim.lr == 1e-4 and cfg.tau == 0.5
    with torch.device("meta"):
        n = count_parameters(MotionGPT(cfg.model, 512, 512))
    assert 200e6 < n < 260e6
    small = load_config(TrainConfig, "recipes/gpt/default.yaml")
    with torch.device("meta"):
        assert count_parameters(MotionGPT(small.model, 512, 384)) < 10e6


# --------------------------------------------------------------------------- with a real (tiny) tokenizer

@pytest.fixture(scope="session")
def tiny_tokens(tmp_path_factory, small_dataset):
    """A 10-iteration tokenizer on the walk_normal slice and its tokens artifact (with captions)."""
    from motok.quantize.base import QuantizerConfig
    from motok.tokenizer.model import ModelConfig
    from motok.tokenizer.tokens import encode
    from motok.tokenizer.train import TrainConfig as TokConfig
    from motok.tokenizer.train import train as train_tokenizer

    root = tmp_path_factory.mktemp("gpt-tok")
    cfg = TokConfig(model=ModelConfig(width=32, depth=1), quantizer=QuantizerConfig(codebook_size=32, dim=16),
                    iterations=10, batch_size=8, window=32, log_every=5, save_every=10, threads=1)
    train_tokenizer(cfg, small_dataset, root / "tok", command="pytest tiny tokenizer")
    encode(root / "tok", small_dataset, root / "tokens.h5", command="pytest tiny tokens")
    return root / "tok", root / "tokens.h5"


TINY_GPT = ["model.num_layers=1", "model.dim=32", "model.heads=2", "model.block_size=24", "text_encoder=bow",
            "batch_size=4", "log_every=2", "eval_every=2", "save_every=3", "threads=1", "optim.lr=0.001"]


def test_train_resume_is_exact_and_never_runs_the_encoder(tiny_tokens, tmp_path, monkeypatch):
    _, tokens = tiny_tokens
    cfg = resolve_config(None, TINY_GPT + ["iterations=6", f"text_cache={tmp_path / 'emb.h5'}"])
    straight = train(cfg, tokens, tmp_path / "a", command="pytest")
    assert (tmp_path / "emb.h5").exists()  # every caption embedded once, up front
    import motok.text.cache as cache_mod

    def no_encoder(name):
        raise AssertionError("the text encoder ran although every caption is cached")
    monkeypatch.setattr(cache_mod, "get_encoder", no_encoder)
    train(cfg, tokens, tmp_path / "b", stop_at=3, command="pytest")
    train(resolve_config(None, [], tmp_path / "b", resume=True), tokens, tmp_path / "b", resume=True)
    ma, sa, _ = load_bundle(tmp_path / "a")
    mb, sb, _ = load_bundle(tmp_path / "b")
    assert ma["model_sha256"] == mb["model_sha256"] and mb["extra"]["iteration"] == 6
    rows_a = [json.loads(x) for x in (tmp_path / "a/metrics.jsonl").read_text().splitlines()]
    rows_b = [json.loads(x) for x in (tmp_path / "b/metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows_b] == [2, 3, 4, 6] and [r["iteration"] for r in rows_a] == [2, 4, 6]
    assert rows_a[-1]["loss"] == pytest.approx(rows_b[-1]["loss"])
    assert "val_loss" in rows_a[-1] and 0.0 <= rows_a[-1]["tau_measured"] <= 1.0
    assert straight["iteration"] == 6 and np.isfinite(straight["loss"])


def test_sample_cli_writes_a_valid_motion(tiny_tokens, tmp_path):
    from motok.cli.main import app
    tok, tokens = tiny_tokens
    run = tmp_path / "gpt"
    cfg = resolve_config(None, TINY_GPT + ["iterations=2"])
    train(cfg, tokens, run, command="pytest")
    runner = CliRunner()
    args = ["--quiet", "gpt", "sample", "--gpt", str(run), "--text", "a person walks forward", "--text",
            "someone waves", "-n", "2", "--seed", "3", "--seconds", "1.6", "--top-k", "8", "--json"]
    r = runner.invoke(app, args + ["-o", str(tmp_path / "s.h5"), "--render", str(tmp_path / "s.gif"),
                                   "--bvh", str(tmp_path / "s.bvh")])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["clips"] == 4 and out["tokens"] == [8, 8, 8, 8]  # 1.6 s = 32 frames = 8 tokens at rate 4
    assert len(out["render"]) == 4 and len(out["bvh"]) == 4
    with MotionFile(tmp_path / "s.h5", "motion") as mf:
        assert len(mf) == 4 and mf.fps == 20.0
        c = mf.clip(0)
        assert c.num_frames == 32 and c.joints.shape == (32, 21, 3) and np.isfinite(c.joints).all()
        assert c.features.shape[1] == 251 and c.captions[0][0] == "a person walks forward"
        codes_a = [mf.clip(i).labels["codes"] for i in range(4)]
    r2 = runner.invoke(app, args + ["-o", str(tmp_path / "t.h5")])
    assert r2.exit_code == 0, r2.output
    with MotionFile(tmp_path / "t.h5", "motion") as mf:
        assert [mf.clip(i).labels["codes"] for i in range(4)] == codes_a  # seeds reproduce
    bad = runner.invoke(app, ["gpt", "sample", "--gpt", str(tmp_path / "nope"), "--text", "x",
                              "-o", str(tmp_path / "x.h5")])
    assert bad.exit_code == 2 and "bundle" in bad.output


def test_torchrun_two_ranks_stay_identical(tiny_tokens, tmp_path):
    """DDP under torchrun (gloo on CPU): both ranks end with the same weights, rank 0 writes."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    _, tokens = tiny_tokens
    motok = Path(sys.executable).with_name("motok")
    torchrun = Path(sys.executable).with_name("torchrun")
    sets = [x for s in TINY_GPT + ["iterations=3", f"text_cache={tmp_path / 'emb.h5'}"] for x in ("--set", s)]
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1", "OMP_NUM_THREADS": "1"}
    r = subprocess.run([str(torchrun), "--nproc_per_node", "2", "--no-python", str(motok), "-q", "gpt", "train",
                        "--tokens", str(tokens), "-o", str(tmp_path / "ddp"), "--json", *sets],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    meta = json.loads((tmp_path / "ddp/bundle.json").read_text())
    hashes = meta["extra"]["rank_state_sha256"]
    assert meta["extra"]["world_size"] == 2 and len(hashes) == 2 and hashes[0] == hashes[1] == meta["model_sha256"]
