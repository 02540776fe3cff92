"""The motion tokenizer: model shapes, loss, training on a real Bandai slice, exact
resume, torchrun/DDP rank identity, encode -> decode artifacts, evaluation metrics, the CLI.

Quantizer internals are tested in test_quantize.py; here the quantizers run inside the model.
Models are tiny and single-threaded so the file stays fast on a shared 2-core machine.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.artifacts import ArtifactError
from motok.checkpoint import load_bundle
from motok.cli.main import app
from motok.config import ConfigError, load_config
from motok.data.dataset import MotionFile
from motok.features.humanml3d import feature_slices, recover_from_ric
from motok.optim import OptimConfig, lr_factor
from motok.quantize.base import QuantizerConfig
from motok.tokenizer.model import VQVAE, LossConfig, ModelConfig, vqvae_loss
from motok.tokenizer.tokens import TokenFile, decode, encode, evaluate, reconstruction_errors
from motok.tokenizer.model import load_tokenizer
from motok.tokenizer.train import TokenizerError, TrainConfig, resolve_config, train

REPO = Path(__file__).resolve().parents[1]
RECIPES = REPO / "recipes" / "tokenizer"
runner = CliRunner()
TINY = ["model.width=48", "quantizer.dim=32", "quantizer.codebook_size=64", "batch_size=16", "window=32",
        "optim.warmup=5", "log_every=5", "save_every=1000", "threads=1"]


def tiny(*extra: str, recipe=None) -> TrainConfig:
    return load_config(TrainConfig, recipe, TINY + list(extra))


def read_metrics(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def tiny_run(small_dataset, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("tok") / "run"
    train(tiny("iterations=40"), small_dataset, run, command="pytest tiny_run")
    return run


# --------------------------------------------------------------------------- model and loss

def test_model_shapes_rate_and_architecture():
    torch.manual_seed(0)
    m = VQVAE(251, ModelConfig(width=32, down_t=2), QuantizerConfig(codebook_size=16, dim=8)).eval()
    assert m.rate == 4
    dil = [c.dilation[0] for c in m.encoder.modules() if isinstance(c, torch.nn.Conv1d) and c.kernel_size == (3,)
           and c.dilation[0] > 1]
    assert dil[:2] == [9, 3]  # largest dilation first: (9, 3, 1) per stage
    assert any(isinstance(u, torch.nn.Upsample) and u.mode == "nearest" for u in m.decoder.modules())
    x = torch.randn(2, 67, 251)  # 67 = 16 * 4 + 3: the 3 trailing frames are dropped
    out = m(x)
    assert out.recon.shape == (2, 64, 251) and out.indices.shape == (2, 16, 1)
    idx = m.encode(x)
    assert torch.equal(idx, out.indices)
    # decode(encode(x)) is the forward reconstruction, exactly
    assert torch.equal(m.decode(idx), out.recon)
    m8 = VQVAE(251, ModelConfig(width=16, down_t=3), QuantizerConfig(codebook_size=16, dim=8))
    assert m8.rate == 8 and m8(torch.randn(1, 64, 251)).indices.shape == (1, 8, 1)


def _residual_nearest(z: torch.Tensor, books: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference for the quantizer inside the model, from the equations alone: every latent frame
    z[b, :, t] goes to its nearest code (T2M-GPT Eq. 1, explicit distances in float64), and with
    several codebooks the residual goes to the next one (residual VQ). Returns indices (B, T, N)
    and the code sums (B, D, T), added in float32 in codebook order."""
    B, D, T = z.shape
    idx = torch.empty(B, T, len(books), dtype=torch.long)
    zq = torch.zeros(B, D, T)
    for b in range(B):
        for t in range(T):
            r, acc = z[b, :, t].double(), torch.zeros(D)
            for i, book in enumerate(books):
                k = int(((book.double() - r) ** 2).sum(1).argmin())
                idx[b, t, i] = k
                acc = acc + book[k]
                r = r - book[k].double()
            zq[b, :, t] = acc
    return idx, zq


@pytest.mark.parametrize("kind", ["vq", "ema_reset", "rvq"])
def test_model_sends_every_latent_frame_to_its_nearest_code(kind):
    torch.manual_seed(0)
    n = 3 if kind == "rvq" else 1
    m = VQVAE(251, ModelConfig(width=16, depth=1),
              QuantizerConfig(kind=kind, codebook_size=32, dim=8, num_codebooks=n, quantizer_dropout=0.0))
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 32, 251, generator=g)
    layers = list(m.quantizer.layers) if kind == "rvq" else [m.quantizer]
    with torch.no_grad():
        z = m.encoder(x.transpose(1, 2))  # (2, 8, 8)
        # Codes on the scale of the latents (of the residuals, for later codebooks), so that
        # many different codes win and a wrong layout of the (B, D, T) rows would show.
        for i, layer in enumerate(layers):
            layer.embed.copy_(float(z.std()) * 0.5**i * torch.randn(32, 8, generator=g))
    books = list(m.quantizer.codebooks().clone())
    idx, zq = _residual_nearest(z, books)
    assert len(idx.unique()) > 4
    m.eval()
    assert torch.equal(m.encode(x), idx)
    out = m(x)
    assert torch.equal(out.indices, idx)
    assert torch.equal(out.recon, m.decoder(zq).transpose(1, 2))
    assert torch.equal(m.decode(idx), out.recon)
    # Training: codes are read before the update, and the reconstruction gradient reaches the
    # encoder output unchanged (straight-through, T2M-GPT Eq. 3).
    seen = {}

    def keep(module, inputs, output):
        inputs[0].retain_grad()
        output.z_q.retain_grad()
        seen.update(z=inputs[0], zq=output.z_q)

    hook = m.quantizer.register_forward_hook(keep)
    out = m.train()(x)
    hook.remove()
    assert torch.equal(out.indices, idx) and torch.equal(seen["zq"], zq)
    out.recon.pow(2).sum().backward()
    assert seen["z"].grad.abs().sum() > 0 and torch.equal(seen["z"].grad, seen["zq"].grad)


_EMA_KEYS = ["rng_seed", "train_steps", "embed", "ema_count", "ema_sum", "initted"]
BUNDLE_QUANTIZER_KEYS = {  # the checkpoint format: renaming any of these breaks old bundles
    "vq": ["rng_seed", "train_steps", "embed", "initted"],
    "reset": ["rng_seed", "train_steps", "embed", "window_count", "initted"],
    "ema": _EMA_KEYS,
    "ema_reset": _EMA_KEYS,
    "rvq": ["rng_seed", "train_steps"] + [f"layers.{i}.{k}" for i in range(2) for k in _EMA_KEYS],
    "fsq": ["rng_seed", "train_steps", "project_in.weight", "project_in.bias", "project_out.weight",
            "project_out.bias"],
}


@pytest.mark.parametrize("kind", list(BUNDLE_QUANTIZER_KEYS))
def test_state_dict_keys_are_the_bundle_format(kind):
    q = QuantizerConfig(kind=kind, codebook_size=16, dim=8, num_codebooks=2 if kind == "rvq" else 1)
    state = VQVAE(251, ModelConfig(width=16, depth=1), q).state_dict()
    assert {k.split(".")[0] for k in state} == {"encoder", "quantizer", "decoder", "mean", "std"}
    keys = [k.removeprefix("quantizer.") for k in state if k.startswith("quantizer.")]
    assert sorted(keys) == sorted(BUNDLE_QUANTIZER_KEYS[kind])


def test_loss_terms():
    J = 21
    x = torch.randn(2, 16, 12 * J - 1)
    zero = {"commit": torch.tensor(0.0)}
    total, parts = vqvae_loss(x, x, zero, LossConfig(), J)
    assert float(total) == 0.0 and float(parts["vel"]) == 0.0
    # the velocity term sees only the joint-position block by default
    y = x.clone()
    y[..., feature_slices(J)["rot"]] += 1.0
    assert float(vqvae_loss(y, x, zero, LossConfig(), J)[1]["vel"]) == 0.0
    assert float(vqvae_loss(y, x, zero, LossConfig(vel_block="all"), J)[1]["vel"]) > 0.0
    # a constant offset of positions has zero frame-to-frame velocity error, but not without differencing
    y = x.clone()
    y[..., feature_slices(J)["ric"]] += 0.5
    assert float(vqvae_loss(y, x, zero, LossConfig(), J)[1]["vel"]) < 1e-12
    assert float(vqvae_loss(y, x, zero, LossConfig(vel_diff=False), J)[1]["vel"]) > 0.1
    # commitment and codebook weights
    losses = {"commit": torch.tensor(2.0), "codebook": torch.tensor(3.0)}
    total, _ = vqvae_loss(x, x, losses, LossConfig(beta_commit=0.02, codebook=1.0), J)
    assert float(total) == pytest.approx(0.04 + 3.0)


def test_lr_schedule_warmup_then_steps():
    cfg = OptimConfig(warmup=4, milestones=[10, 20], gamma=0.1)
    assert [round(lr_factor(i, cfg), 3) for i in range(5)] == [0.2, 0.4, 0.6, 0.8, 1.0]
    assert lr_factor(9, cfg) == 1.0 and lr_factor(10, cfg) == pytest.approx(0.1)
    assert lr_factor(25, cfg) == pytest.approx(0.01)


def test_every_recipe_loads_and_table_variants_share_a_budget():
    cfgs = {p.stem: load_config(TrainConfig, p) for p in RECIPES.glob("*.yaml")}
    assert {"default", "paper", "vq", "ema", "reset", "ema_reset", "rvq"} <= set(cfgs)
    table = [cfgs[k] for k in ("vq", "ema", "reset", "ema_reset", "rvq")]
    assert len({(c.iterations, c.batch_size, c.window, json.dumps(c.model.__dict__)) for c in table}) == 1
    codes = {c.quantizer.codebook_size * (c.quantizer.num_codebooks if c.quantizer.kind == "rvq" else 1)
             for c in table}
    assert codes == {512}
    p = cfgs["paper"]
    assert (p.model.width, p.quantizer.dim, p.quantizer.codebook_size, p.batch_size, p.window) == (512, 512, 512, 256, 64)
    # Codebooks start as in T2M-GPT's code, by default and in every recipe (docs/tokenizer.md).
    assert TrainConfig().quantizer.init == "t2m_gpt" and {c.quantizer.init for c in cfgs.values()} == {"t2m_gpt"}
    starts = {k: VQVAE(251, ModelConfig(width=16, depth=1), cfgs[k].quantizer).quantizer for k in ("vq", "ema", "rvq")}
    assert starts["vq"].init_method == "uniform" and starts["ema"].init_method == "batch"
    assert {layer.init_method for layer in starts["rvq"].layers} == {"batch"}


# --------------------------------------------------------------------------- training

def test_100_iterations_lower_the_reconstruction_loss(small_dataset, tmp_path):
    out = train(tiny("iterations=100"), small_dataset, tmp_path / "run")
    rec = [r["recon"] for r in read_metrics(tmp_path / "run")]
    assert len(rec) == 20 and out["iteration"] == 100
    assert np.mean(rec[-3:]) < 0.7 * np.mean(rec[:2]), rec
    last = read_metrics(tmp_path / "run")[-1]
    for k in ("loss", "recon", "vel", "commit", "usage", "perplexity", "lr", "it_s", "frames_s"):
        assert np.isfinite(last[k]), k
    assert 0 < last["usage"] <= 1 and last["perplexity"] >= 1
    meta, state, ts = load_bundle(tmp_path / "run", "tokenizer", with_train_state=True)
    assert int(ts["iteration"]) == 100 and meta["extra"]["dataset_sha256"] and meta["config"]["iterations"] == 100
    with MotionFile(small_dataset) as mf:
        np.testing.assert_array_equal(state["mean"].numpy(), mf.stats()[0])
    assert {"optimizer", "scheduler", "rng", "data_rng"} <= set(ts)


@pytest.mark.parametrize("kind", ["vq", "ema_reset", "rvq"])
def test_resume_is_bitwise_exact(small_dataset, tmp_path, kind):
    q = [f"quantizer.kind={kind}"] + (["quantizer.num_codebooks=3", "quantizer.codebook_size=16"] if kind == "rvq" else [])
    cfg = tiny("iterations=20", *q)
    train(cfg, small_dataset, tmp_path / "straight")
    train(cfg, small_dataset, tmp_path / "resumed", stop_at=10)
    assert load_bundle(tmp_path / "resumed", with_train_state=True)[2]["iteration"] == 10
    train(resolve_config(None, [], tmp_path / "resumed", resume=True), small_dataset, tmp_path / "resumed", resume=True)
    a, b = load_bundle(tmp_path / "straight")[1], load_bundle(tmp_path / "resumed")[1]
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert read_metrics(tmp_path / "resumed")[-1]["loss"] == read_metrics(tmp_path / "straight")[-1]["loss"]
    assert [r["iteration"] for r in read_metrics(tmp_path / "resumed")] == [5, 10, 15, 20]


def test_resume_guards(tiny_run, small_dataset, tmp_path):
    with pytest.raises(ConfigError, match="model"):
        resolve_config(None, ["model.width=64"], tiny_run, resume=True)
    cfg = resolve_config(None, ["iterations=60"], tiny_run, resume=True)  # extending a run is fine
    assert cfg.iterations == 60
    import h5py
    other = tmp_path / "other.h5"
    other.write_bytes(Path(small_dataset).read_bytes())
    with h5py.File(other, "r+") as f:
        f.attrs["fps"] = 30.0  # another data set, same layout
    with pytest.raises(TokenizerError, match="hash differs"):
        train(cfg, other, tiny_run, resume=True)


def test_an_older_bundle_without_init_resumes_with_its_uniform_start(small_dataset, tmp_path):
    run = tmp_path / "old"
    train(tiny("iterations=4", "quantizer.init=uniform"), small_dataset, run, stop_at=2)
    meta_path = run / "bundle.json"
    meta = json.loads(meta_path.read_text())
    del meta["config"]["quantizer"]["init"]  # as written by motok 0.1
    meta_path.write_text(json.dumps(meta))
    cfg = resolve_config(None, [], run, resume=True)
    assert cfg.quantizer.init == "uniform"
    train(cfg, small_dataset, run, resume=True)
    with pytest.raises(ConfigError, match="quantizer"):  # but not into another start
        resolve_config(None, ["quantizer.init=t2m_gpt"], run, resume=True)


def test_bundle_records_the_split_the_statistics_came_from(small_dataset, tmp_path):
    import h5py
    train(tiny("iterations=1"), small_dataset, tmp_path / "a")
    assert load_bundle(tmp_path / "a")[0]["extra"]["stats_split"] == "train"
    other = tmp_path / "all.h5"
    other.write_bytes(Path(small_dataset).read_bytes())
    with h5py.File(other, "r+") as f:
        f["stats"].attrs["split"] = "all"  # as preprocessing writes it when no clip is in train
    train(tiny("iterations=1"), other, tmp_path / "b")
    assert load_bundle(tmp_path / "b")[0]["extra"]["stats_split"] == "all"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("kind", ["ema_reset", "rvq"])
def test_torchrun_two_ranks_stay_identical(small_dataset, tmp_path, kind):
    run = tmp_path / "ddp"
    q = [f"quantizer.kind={kind}"] + (["quantizer.num_codebooks=3", "quantizer.codebook_size=16"] if kind == "rvq" else [])
    sets = [a for s in TINY + q + ["iterations=8", "save_every=4"] for a in ("--set", s)]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr", "127.0.0.1",
           "--master_port", str(_free_port()), "-m", "motok.cli.main", "-q", "tokenize", "train",
           "--data", str(small_dataset), "-o", str(run), *sets]
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1", "OMP_NUM_THREADS": "1"}
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[:3000] + "\n...\n" + r.stderr[-3000:]
    meta, state, ts = load_bundle(run, "tokenizer", with_train_state=True)
    hashes = meta["extra"]["rank_state_sha256"]
    # weights, EMA statistics and codebooks: one hash over the whole state per rank
    assert len(hashes) == 2 and hashes[0] == hashes[1] == meta["model_sha256"]
    assert meta["extra"]["world_size"] == 2 and int(ts["iteration"]) == 8
    # each rank drew its own data
    assert ts["data_rng"].shape[0] == 2 and not torch.equal(ts["data_rng"][0], ts["data_rng"][1])
    assert [r["iteration"] for r in read_metrics(run)] == [5, 8]  # rank 0 alone wrote the log


def test_paper_recipe_starts_on_cpu(small_dataset, tmp_path):
    cfg = load_config(TrainConfig, RECIPES / "paper.yaml", ["batch_size=2", "threads=1", "window=32"])
    out = train(cfg, small_dataset, tmp_path / "paper", stop_at=1)
    assert out["iteration"] == 1 and np.isfinite(out["loss"])
    model, _ = load_tokenizer(tmp_path / "paper")
    assert model.quantizer.dim == 512 and model.rate == 4


# --------------------------------------------------------------------------- artifacts

def test_encode_decode_round_trip(tiny_run, small_dataset, tmp_path):
    tok, mot = tmp_path / "tokens.h5", tmp_path / "motion.h5"
    s = encode(tiny_run, small_dataset, tok)
    model, meta = load_tokenizer(tiny_run)
    with MotionFile(small_dataset) as mf, TokenFile(tok) as tf:
        assert tf.names == mf.names and tf.splits == mf.splits and s["clips"] == len(mf)
        assert tf.rate == 4 and tf.num_codebooks == 1 and tf.tokenizer_sha256 == meta["model_sha256"]
        assert json.loads(tf.h5.attrs["tokenizer_config"]) == meta["config"]
        for i in range(len(mf)):
            T = mf.frame_offsets[i + 1] - mf.frame_offsets[i]
            idx = tf.indices(i)
            assert idx.shape == (T // 4, 1) and idx.min() >= 0 and idx.max() < 64
            assert tf.h5["clips/frames"][i] == 4 * (T // 4) and tf.h5["clips/source_frames"][i] == T
            assert [c[0] for c in tf.captions(i)] == [c[0] for c in mf.captions(i)]
    decode(tiny_run, tok, mot)
    with MotionFile(small_dataset) as src, MotionFile(mot, "motion") as mf, TokenFile(tok) as tf:
        for i in range(len(mf)):
            c = mf.clip(i)
            T = src.frame_offsets[i + 1] - src.frame_offsets[i]
            assert c.num_frames == 4 * len(tf.indices(i)) == T // 4 * 4
            assert c.name == src.names[i] and c.split == src.splits[i] and len(c.captions) == 3
            np.testing.assert_allclose(c.joints, recover_from_ric(c.features, 21), atol=1e-5)
            np.testing.assert_array_equal(c.root_translation, c.joints[:, 0])
            np.testing.assert_allclose(np.linalg.norm(c.local_quats, axis=-1), 1.0, atol=1e-4)
        # decoding the tokens equals the model's own reconstruction of the source clip
        x = torch.from_numpy(src.frames("features", 0))[None]
        recon = model.denormalize(model(model.normalize(x)).recon)[0].detach().numpy()
        np.testing.assert_allclose(mf.frames("features", 0), recon, atol=1e-5)
    # the motion artifact is accepted by render and BVH export
    r = runner.invoke(app, ["-q", "export", "bvh", str(mot), "--clip", "0", "-o", str(tmp_path / "a.bvh")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["-q", "render", str(mot), "--clip", "0", "-o", str(tmp_path / "a.png"), "--max-frames", "8"])
    assert r.exit_code == 0, r.output


def test_decode_refuses_tokens_of_another_tokenizer(tiny_run, small_dataset, tmp_path):
    tok = tmp_path / "tokens.h5"
    encode(tiny_run, small_dataset, tok)
    other = tmp_path / "other"
    train(tiny("iterations=2", "seed=7"), small_dataset, other)
    with pytest.raises(ArtifactError, match="another tokenizer"):
        decode(other, tok, tmp_path / "m.h5")
    decode(other, tok, tmp_path / "m.h5", allow_mismatch=True)


# --------------------------------------------------------------------------- evaluation

def test_metric_is_zero_for_perfect_reconstruction(small_dataset):
    with MotionFile(small_dataset) as mf:
        gt = mf.frames("features", 0).astype(np.float64)
    e = reconstruction_errors(gt, gt, 21)
    assert all(float(np.abs(v).max()) == 0.0 for v in e.values())
    pred = gt.copy()
    pred[:, feature_slices(21)["root_y"]] += 0.01  # the root 1 cm higher, the other joints unchanged
    e = reconstruction_errors(pred, gt, 21)
    np.testing.assert_allclose(e["mpjpe"], 10.0 * 20 / 21, rtol=1e-9)  # 20 joints 1 cm off relative to the root
    np.testing.assert_allclose(e["mpjpe_global"], 10.0 / 21, rtol=1e-9)
    assert e["accel"].max() < 1e-6  # a constant offset has no acceleration


def test_eval_equals_an_independent_computation(tiny_run, small_dataset):
    """`tokenize eval` against the definitions computed another way: the model's forward pass
    (not encode/decode), joints by recover_from_ric, errors written out, all frames pooled."""
    with MotionFile(small_dataset) as mf:
        split = next(s for s in ("test", "val", "train") if mf.split_indices(s))
        clips = [mf.frames("features", i).astype(np.float64) for i in mf.split_indices(split)]
    r = evaluate(tiny_run, small_dataset, split)
    model, _ = load_tokenizer(tiny_run)
    rel, glob, acc, codes = [], [], [], []
    with torch.no_grad():
        for gt in clips:
            gt = gt[: len(gt) // 4 * 4]
            out = model(model.normalize(torch.from_numpy(gt).float()[None]))
            pred = model.denormalize(out.recon)[0].double().numpy()
            codes.append(out.indices.reshape(-1).numpy())
            p, g = recover_from_ric(pred, 21), recover_from_ric(gt, 21)
            rel.append(np.sqrt((((p - p[:, :1]) - (g - g[:, :1])) ** 2).sum(-1)).mean(1))
            glob.append(np.sqrt(((p - g) ** 2).sum(-1)).mean(1))
            acc.append(np.sqrt((((p[2:] - 2 * p[1:-1] + p[:-2]) - (g[2:] - 2 * g[1:-1] + g[:-2])) ** 2).sum(-1)).mean(1))
    assert r["clips"] == len(clips) and r["frames"] == sum(len(c) // 4 * 4 for c in clips)
    assert r["mpjpe_mm"] == pytest.approx(1000 * np.concatenate(rel).mean(), rel=1e-4)
    assert r["mpjpe_global_mm"] == pytest.approx(1000 * np.concatenate(glob).mean(), rel=1e-4)
    assert r["accel_error_mm"] == pytest.approx(1000 * np.concatenate(acc).mean(), rel=1e-4)
    used = np.unique(np.concatenate(codes))
    cb = r["codebooks"][0]
    assert cb["used"] == len(used) and cb["dead"] == 64 - len(used) and cb["usage"] == len(used) / 64
    n = np.bincount(np.concatenate(codes), minlength=64) / sum(map(len, codes))
    assert cb["perplexity"] == pytest.approx(np.exp(-(n[n > 0] * np.log(n[n > 0])).sum()))


# --------------------------------------------------------------------------- command line

def test_cli_train_resume_encode_decode_eval(small_dataset, tmp_path):
    run, tok, mot = tmp_path / "run", tmp_path / "t.h5", tmp_path / "m.h5"
    sets = [a for s in TINY + ["iterations=6"] for a in ("--set", s)]
    r = runner.invoke(app, ["-q", "tokenize", "train", "--data", str(small_dataset), "--recipe",
                            str(RECIPES / "default.yaml"), "-o", str(run), *sets, "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["iteration"] == 6
    r = runner.invoke(app, ["-q", "tokenize", "train", "--data", str(small_dataset), "-o", str(run), "--resume",
                            "--set", "iterations=8", "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["iteration"] == 8, r.output
    r = runner.invoke(app, ["-q", "tokenize", "encode", "-t", str(run), "--data", str(small_dataset), "-o", str(tok)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["-q", "tokenize", "decode", str(tok), "-t", str(run), "-o", str(mot), "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["clips"] == 24, r.output
    r = runner.invoke(app, ["-q", "tokenize", "eval", "-t", str(run), "--data", str(small_dataset), "--split", "train",
                            "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["mpjpe_mm"] > 0, r.output
    r = runner.invoke(app, ["-q", "tokenize", "eval", "-t", str(run), "--data", str(small_dataset), "--split", "train"])
    assert r.exit_code == 0 and "mpjpe_mm" in r.output and "perplexity" in r.output


def test_cli_errors_are_one_line(small_dataset, tmp_path):
    r = runner.invoke(app, ["tokenize", "train", "--data", str(small_dataset), "-o", str(tmp_path / "r"), "--resume"])
    assert r.exit_code == 2 and "bundle" in r.output
    r = runner.invoke(app, ["tokenize", "train", "--data", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "r")])
    assert r.exit_code == 2 and "missing.h5" in r.output
    r = runner.invoke(app, ["tokenize", "train", "--data", str(small_dataset), "-o", str(tmp_path / "r"),
                            "--set", "quantizer.kind=nope"])
    assert r.exit_code == 2 and "kind" in r.output


def test_resuming_on_other_kernels_says_so(small_dataset, tmp_path, capsys):
    """Resuming stays correct on another machine, but it cannot repeat the uninterrupted run to the
    digit: the training says which of the checkpoint's recorded kernels or versions changed, and
    says nothing when they did not."""
    import json

    cfg = tiny("iterations=4")
    train(cfg, small_dataset, tmp_path / "run", stop_at=2)
    capsys.readouterr()
    train(resolve_config(None, ["iterations=6"], tmp_path / "run", resume=True), small_dataset, tmp_path / "run",
          resume=True, stop_at=4)
    assert "other arithmetic" not in capsys.readouterr().err
    meta = json.loads((tmp_path / "run" / "bundle.json").read_text())
    meta["provenance"]["machine"]["numpy_simd"] = ["SOME_OTHER_TARGET"]
    (tmp_path / "run" / "bundle.json").write_text(json.dumps(meta))
    train(resolve_config(None, ["iterations=6"], tmp_path / "run", resume=True), small_dataset, tmp_path / "run",
          resume=True)
    err = capsys.readouterr().err
    assert "other arithmetic" in err and "SOME_OTHER_TARGET" in err
    assert load_bundle(tmp_path / "run", with_train_state=True)[2]["iteration"] == 6
