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


def test_a_prefix_is_continued_as_if_sampled():
    """Greedy continuation of a sequence's first codes gives back the rest of it, with and without
    the cache and with guidance's doubled rows; a row's generator goes on from call to call."""
    model = tiny().eval()
    text = torch.randn(2, TEXT_DIM)
    whole = generate(model, text, target_len=torch.tensor([9, 9]), argmax=True)
    head = torch.stack([c[:4] for c in whole.codes])
    for cache in (True, False):
        rest = generate(model, text, target_len=torch.tensor([9, 9]), argmax=True, prefix=head, use_cache=cache)
        assert [c.tolist() for c in rest.codes] == [c[4:].tolist() for c in whole.codes]
    torch.manual_seed(1)
    guided = MotionGPT(GPTConfig(num_layers=2, dim=32, heads=4, block_size=12, dropout=0.0), K, TEXT_DIM,
                       null_text=True).eval()
    with torch.no_grad():
        guided.null_text.normal_()
    whole = generate(guided, text, target_len=torch.tensor([9, 9]), argmax=True, guidance=2.5)
    rest = generate(guided, text, target_len=torch.tensor([9, 9]), argmax=True, guidance=2.5,
                    prefix=torch.stack([c[:4] for c in whole.codes]))
    assert [c.tolist() for c in rest.codes] == [c[4:].tolist() for c in whole.codes]
    g = torch.Generator().manual_seed(3)
    first = generate(model, text[:1], target_len=torch.tensor([3]), seeds=[g]).codes[0]
    assert first.tolist() == generate(model, text[:1], target_len=torch.tensor([3]), seeds=[3]).codes[0].tolist()
    assert not torch.equal(g.get_state(), torch.Generator().manual_seed(3).get_state())  # its stream went on
    from motok.gpt.data import GPTError

    with pytest.raises(GPTError, match="leaves no position"):
        generate(model, text, prefix=torch.zeros(2, model.max_codes, dtype=torch.long))


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


# ----------------------------------------------------------------- CFG, held-out wordings, augmentation

def test_classifier_free_guidance_mixes_the_two_logits():
    from motok.gpt.sample import check_guidance
    from motok.gpt.train import GPTError

    torch.manual_seed(0)
    cfg = GPTConfig(num_layers=2, dim=32, heads=4, block_size=12, dropout=0.0)
    model = MotionGPT(cfg, K, TEXT_DIM, null_text=True).eval()
    with torch.no_grad():
        model.null_text.normal_()
    text = torch.randn(3, TEXT_DIM)
    # guidance 1 is the plain model, whatever the null text
    a = generate(model, text, seeds=[0, 1, 2], record_logits=True, guidance=1.0)
    b = generate(model, text, seeds=[0, 1, 2], record_logits=True, guidance=1.0, use_cache=False)
    assert [c.tolist() for c in a.codes] == [c.tolist() for c in b.codes]
    # guidance g: l_u + g (l_c - l_u) at the first step, with and without the cache
    g = 2.5
    first = generate(model, text, seeds=[0, 1, 2], record_logits=True, guidance=g)
    with torch.no_grad():
        lc = model(text)[:, -1]
        lu = model(text, drop_text=torch.ones(3, dtype=torch.bool))[:, -1]
    torch.testing.assert_close(first.logits[0], lu + g * (lc - lu), atol=1e-5, rtol=1e-5)
    nocache = generate(model, text, seeds=[0, 1, 2], record_logits=True, guidance=g, use_cache=False)
    assert [c.tolist() for c in first.codes] == [c.tolist() for c in nocache.codes]
    for x, y in zip(first.logits, nocache.logits):
        torch.testing.assert_close(x, y, atol=1e-4, rtol=1e-4)
    # the null text really replaces the caption: the dropped rows do not depend on the text
    with torch.no_grad():
        lu2 = model(torch.randn(3, TEXT_DIM), drop_text=torch.ones(3, dtype=torch.bool))[:, -1]
    torch.testing.assert_close(lu, lu2)
    # a model without a null text refuses guidance with a clear error; bad scales are refused
    with pytest.raises(GPTError, match="caption dropout"):
        check_guidance(tiny(), 2.0)
    with pytest.raises(GPTError, match=">= 0"):
        check_guidance(model, -1.0)
    check_guidance(tiny(), 1.0)


def test_augmented_captions():
    from motok.gpt.augment import caption_groups, crossover, noisy, recombined_captions, word_dropout_captions

    assert crossover("A tired person walks forward.", "Someone walks straight ahead wearily.") == \
        ["A tired person walks straight ahead wearily."]
    assert crossover("a b", "c d") == []
    caps = [["A person walks forward.", "Someone walks slowly like an old person."],
            ["Someone walks slowly like an old person."], ["A person runs fast."]]
    assert sorted(map(sorted, caption_groups(caps))) == [[0, 1], [2]]
    new = recombined_captions(caps, 5, seed=0)
    existing = {t for c in caps for t in c}
    assert new and all(t not in existing for _, t in new) and all(g == [0, 1] for g, _ in new)
    # "Someone walks forward." is one word short of the shorter source, so it is dropped; a cut at a
    # word that ends one source can join two whole phrases (the rule's known imperfection).
    assert {t for _, t in new} == {"A person walks slowly like an old person.",
                                   "Someone walks slowly like an old person walks forward."}
    assert recombined_captions(caps, 5, seed=0, keep=lambda t: "forward" not in t) == \
        [([0, 1], "A person walks slowly like an old person.")]
    assert len(recombined_captions(caps, 1, seed=0)) == 1  # at most per_group per group
    v1 = word_dropout_captions(["a person walks forward slowly"], 0.5, 4, seed=1)
    assert v1 == word_dropout_captions(["a person walks forward slowly"], 0.5, 4, seed=1)  # seeded
    assert v1 and all(set(v.split()) < set(src.split()) and v for src, v in v1)
    e = torch.nn.functional.normalize(torch.randn(512, 384), dim=-1)
    d = noisy(e, 0.3, torch.Generator().manual_seed(0)) - e
    assert d.norm(dim=-1).mean() == pytest.approx(0.3, rel=0.05)
    assert noisy(e, 0.0) is e


def test_heldout_wordings_never_train_and_augmentation_adds_pairs(tiny_tokens, tmp_path):
    from motok.gpt.train import load_code_data
    from motok.text.cache import TextEmbeddingCache
    from motok.text.phrasings import is_heldout
    from motok.tokenizer.tokens import TokenFile

    _, tokens = tiny_tokens
    cache = TextEmbeddingCache(tmp_path / "emb.h5")
    plain = load_code_data(tokens, "train", "bow", cache)
    with TokenFile(tokens) as tf:
        texts = sorted({c[0] for i, s in enumerate(tf.splits) if s == "train" for c in tf.captions(i)})
    n_held = sum(map(is_heldout, texts))
    assert n_held > 0 and len(plain.text) == len(texts)
    held = load_code_data(tokens, "train", "bow", cache, resolve_config(None, ["holdout=v1"]))
    assert len(held.text) == len(texts) - n_held
    assert len(held.pair_clip) < len(plain.pair_clip)
    aug = load_code_data(tokens, "train", "bow", cache,
                         resolve_config(None, ["holdout=v1", "recombine=10", "word_dropout=0.3",
                                               "word_dropout_variants=2"]))
    assert len(aug.pair_clip) > len(held.pair_clip) and len(aug.text) > len(held.text)
    assert len(aug.text) == int(aug.pair_text.max()) + 1


@pytest.mark.parametrize("override,match", [("caption_dropout=1.5", "caption_dropout"), ("holdout=v9", "holdout"),
                                            ("guidance=2", "caption_dropout"), ("text_noise=-1", "text_noise"),
                                            ("recombine=-1", "recombine")])
def test_augmentation_settings_are_checked(tiny_tokens, tmp_path, override, match):
    from motok.config import ConfigError

    _, tokens = tiny_tokens
    with pytest.raises(ConfigError, match=match):
        train(resolve_config(None, TINY_GPT + ["iterations=1", override]), tokens, tmp_path / "x", command="pytest")


def test_caption_dropout_run_samples_with_its_guidance(tiny_tokens, tmp_path):
    from motok.cli.main import app

    _, tokens = tiny_tokens
    run = tmp_path / "cfg"
    train(resolve_config(None, TINY_GPT + ["iterations=3", "caption_dropout=0.5", "guidance=3", "text_noise=0.1",
                                           "holdout=v1", "recombine=3"]), tokens, run, command="pytest")
    meta, state, _ = load_bundle(run)
    assert "null_text" in state and meta["config"]["guidance"] == 3.0
    runner = CliRunner()
    base = ["--quiet", "gpt", "sample", "--gpt", str(run), "--text", "a person walks forward", "--seconds", "1.6",
            "--json"]
    r = runner.invoke(app, base + ["-o", str(tmp_path / "a.h5")])
    assert r.exit_code == 0, r.output
    with MotionFile(tmp_path / "a.h5", "motion") as mf:
        assert mf.provenance.config["guidance"] == 3.0  # the run's own guidance is the default
    r1 = runner.invoke(app, base + ["-o", str(tmp_path / "b.h5"), "--guidance", "1"])
    assert r1.exit_code == 0, r1.output
    plain = tmp_path / "plain"
    train(resolve_config(None, TINY_GPT + ["iterations=1"]), tokens, plain, command="pytest")
    bad = runner.invoke(app, ["gpt", "sample", "--gpt", str(plain), "--text", "x", "--guidance", "2",
                              "-o", str(tmp_path / "c.h5")])
    assert bad.exit_code == 2 and "caption dropout" in bad.output


def test_snapping_conditions_new_sentences_on_training_captions(tiny_tokens, tmp_path):
    from motok.gpt.sample import load_for_sampling
    from motok.gpt.snap import SnappingCache, training_captions
    from motok.text.encoders import encode

    tok, tokens = tiny_tokens
    run = tmp_path / "snap"
    train(resolve_config(None, TINY_GPT + ["iterations=1", "holdout=v1", "snap=1"]), tokens, run, command="pytest")
    *_, cache = load_for_sampling(run)
    assert isinstance(cache, SnappingCache)
    caps = training_captions(tokens, "train", "v1")
    assert caps and len(cache.captions) == len(caps)
    new = "somebody strolls at a steady pace"
    e = cache.embed([caps[0], new], "bow", write=False)
    np.testing.assert_array_equal(e[0], encode([caps[0]], "bow")[0])  # a training caption is unchanged
    ref = encode(caps, "bow")
    q = encode([new], "bow")[0]
    nearest = int(np.argmax(ref @ q))
    np.testing.assert_allclose(e[1], ref[nearest], atol=1e-6)  # k = 1: exactly its nearest caption
    assert cache.snapped[new] == [caps[nearest]]
    k3 = SnappingCache(cache.cache, caps, "bow", 3).embed([new], "bow", write=False)[0]
    assert np.linalg.norm(k3) == pytest.approx(1.0, abs=1e-5) and not np.allclose(k3, q)
    *_, off = load_for_sampling(run, snap=0)  # --snap 0 turns it off
    assert not isinstance(off, SnappingCache)
    from motok.cli.main import app
    r = CliRunner().invoke(app, ["--quiet", "gpt", "sample", "--gpt", str(run), "--text", new, "--seconds", "0.8",
                                 "-o", str(tmp_path / "s.h5"), "--json"])
    assert r.exit_code == 0, r.output
    with MotionFile(tmp_path / "s.h5", "motion") as mf:
        assert mf.provenance.config["snapped"] == {new: caps[nearest]}
