"""Tokenizer speed: training throughput (motion frames/s) of the default and the paper-size
VQ-VAE, and encode/decode speed as a factor over realtime (20 fps).

Every model is timed in the same run under the same load, next to two references: a float32
GEMM rate (GFLOP/s, to compare machines and load levels) and the paper-size model (to compare
sizes). Inputs are random normalized features of the HumanML3D/Bandai layout (251 dims):
the convolutions cost the same for any values, and no data set is needed. With ``--tokenizer
RUN --data DATA.h5`` it also times the artifact path end to end (``tokens.encode`` /
``tokens.decode``: HDF5, recover_from_ric, local rotations, writing).

    .venv/bin/python benchmarks/tokenizer.py [--threads 1 2] [--steps 8]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from motok.config import load_config
from motok.tokenizer.model import VQVAE, vqvae_loss
from motok.tokenizer.train import TrainConfig, make_optimizer

RECIPES = Path(__file__).resolve().parents[1] / "recipes" / "tokenizer"
FPS = 20.0
D, J = 251, 21


def gemm_gflops(seconds: float = 1.0) -> float:
    a, b = torch.randn(512, 512), torch.randn(512, 512)
    a @ b
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        n += 1
    return 2 * 512 ** 3 * n / (time.perf_counter() - t0) / 1e9


def build(recipe: str) -> tuple[VQVAE, TrainConfig]:
    cfg = load_config(TrainConfig, RECIPES / f"{recipe}.yaml")
    torch.manual_seed(0)
    return VQVAE(D, cfg.model, cfg.quantizer), cfg


def train_rate(recipe: str, batch: int, steps: int) -> float:
    """Motion frames per second through a full step: forward, loss, backward, AdamW."""
    model, cfg = build(recipe)
    model.train()
    opt, sched = make_optimizer(model, cfg.optim)
    x = torch.randn(batch, cfg.window, D)

    def step():
        out = model(x)
        loss, _ = vqvae_loss(out.recon, x, out.losses, cfg.loss, J, cfg.quantizer.beta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    step()  # first step allocates and picks kernels
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return steps * batch * cfg.window / (time.perf_counter() - t0)


def codec_rates(recipe: str, frames: int, batch: int, reps: int) -> tuple[float, float]:
    """(encode, decode) motion frames per second for ``batch`` clips of ``frames`` frames."""
    model, _ = build(recipe)
    model.eval()
    x = torch.randn(batch, frames, D)
    idx = model.encode_features(x)
    model.decode_features(idx)
    t0 = time.perf_counter()
    for _ in range(reps):
        idx = model.encode_features(x)
    enc = reps * batch * frames / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    for _ in range(reps):
        model.decode_features(idx)
    dec = reps * batch * frames / (time.perf_counter() - t0)
    return enc, dec


def artifact_rates(run: str, data: str) -> tuple[float, float, int]:
    from motok.data.dataset import MotionFile
    from motok.tokenizer.tokens import decode, encode
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        encode(run, data, Path(tmp) / "t.h5", command="benchmarks/tokenizer.py")
        t_enc = time.perf_counter() - t0
        t0 = time.perf_counter()
        decode(run, Path(tmp) / "t.h5", Path(tmp) / "m.h5", command="benchmarks/tokenizer.py")
        t_dec = time.perf_counter() - t0
        with MotionFile(Path(tmp) / "m.h5") as mf:
            frames = int(mf.frame_offsets[-1])
    return frames / t_enc, frames / t_dec, frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--steps", type=int, default=8, help="timed training steps per model")
    ap.add_argument("--paper-batch", type=int, default=32,
                    help="windows per step for the paper-size model (the recipe's 256 takes ~10 s a step on CPU)")
    ap.add_argument("--clip-frames", type=int, default=200, help="frames per clip for encode/decode (10 s)")
    ap.add_argument("--tokenizer", default=None, help="a trained run, for the end-to-end artifact timing")
    ap.add_argument("--data", default=None, help="a motion-dataset, for the end-to-end artifact timing")
    args = ap.parse_args()

    default_cfg = load_config(TrainConfig, RECIPES / "default.yaml")
    models = [("default", default_cfg.batch_size), ("paper", args.paper_batch)]
    for threads in args.threads:
        torch.set_num_threads(threads)
        print(f"\n## {threads} thread(s); reference GEMM {gemm_gflops():.0f} GFLOP/s")
        print(f"{'model':<8} {'params':>7} {'batch':>5} {'train frames/s':>15} "
              f"{'encode x RT (1 clip)':>21} {'decode x RT (1 clip)':>21} {'encode x RT (32)':>17} {'decode x RT (32)':>17}")
        for name, batch in models:
            params = sum(p.numel() for p in build(name)[0].parameters()) / 1e6
            tr = train_rate(name, batch, args.steps if name == "default" else max(2, args.steps // 4))
            e1, d1 = codec_rates(name, args.clip_frames, 1, 20)
            eb, db = codec_rates(name, args.clip_frames, 32, 2)
            print(f"{name:<8} {params:>6.1f}M {batch:>5} {tr:>15,.0f} {e1 / FPS:>21,.0f} {d1 / FPS:>21,.0f} "
                  f"{eb / FPS:>17,.0f} {db / FPS:>17,.0f}")
    if args.tokenizer and args.data:
        torch.set_num_threads(args.threads[0])
        enc, dec, frames = artifact_rates(args.tokenizer, args.data)
        print(f"\nartifacts end to end ({frames:,} frames, {torch.get_num_threads()} thread(s)): "
              f"encode {enc / FPS:,.0f}x realtime, decode (with joints and rotations) {dec / FPS:,.0f}x realtime")


if __name__ == "__main__":
    main()
