"""Training the motion VQ-VAE (T2M-GPT Sec. 3.1 and Sec. 4.1 / appendix F for the settings).

Loss: :func:`motok.tokenizer.model.vqvae_loss` (Eq. 2-3). Optimizer: AdamW (0.9, 0.99) with a
linear warm-up, then the learning rate times ``gamma`` at each milestone. Data: random
``window``-frame crops of the training split, normalized with the data set's mean/std.

Runs unchanged under ``torchrun``: with ``WORLD_SIZE > 1`` it joins the process group from the
environment (gloo on CPU, NCCL on GPU), wraps the model in DistributedDataParallel, splits the
global batch over ranks, samples data with a per-rank generator and writes only from rank 0.
Resuming restores model, optimizer, scheduler, the global RNGs and every rank's data generator,
so ``K`` iterations + resume to ``2K`` is bitwise equal to ``2K`` straight.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from motok import progress as _progress
from motok.artifacts import hash_inputs
from motok.checkpoint import MetricsLog, load_bundle
from motok.config import ConfigError
from motok.data.dataset import MotionFile
from motok.distributed import (Dist, init_distributed, pick_device, restore_checkpoint, save_checkpoint,
                               shutdown_distributed)
from motok.optim import OptimConfig, lr_factor, optimizer_step
from motok.quantize.registry import build_quantizer
from motok.resume import resolve_config as resume_config
from motok.tokenizer.model import ACTIVATIONS, KIND, TokenizerError, TrainConfig, build_model, vqvae_loss



# --------------------------------------------------------------------------- data

@dataclass
class TrainData:
    features: torch.Tensor  # (F, D) normalized rows of the training clips, concatenated
    starts: torch.Tensor  # (C,) first row of each usable clip
    lengths: torch.Tensor  # (C,) frames of each usable clip (>= window)
    mean: np.ndarray
    std: np.ndarray
    meta: dict  # skeleton, offsets, fps, legacy, num_joints, stats_split


def dataset_meta(mf: MotionFile) -> dict:
    return {"skeleton": mf.skeleton.to_dict(), "offsets": np.asarray(mf.offsets).tolist(), "fps": mf.fps,
            "legacy": mf.legacy, "num_joints": int(mf.skeleton.num_joints),
            "feature_dim": int(mf.h5["frames/features"].shape[1]), "stats_split": stats_split(mf)}


def stats_split(mf: MotionFile) -> str:
    """The split the data set's mean/std were computed over, as preprocessing recorded it
    ("train", or "all" when no clip was in train); "unknown" for files that do not say."""
    st = mf.h5.get("stats")
    split = st.attrs.get("split") if st is not None else None
    return (split.decode() if isinstance(split, bytes) else str(split)) if split is not None else "unknown"


def load_train_data(path: str | Path, split: str, window: int) -> TrainData:
    """Read the split's rows once into memory and normalize with the dataset statistics."""
    with MotionFile(path, "motion-dataset") as mf:
        idx = mf.split_indices(split)
        if not idx:
            raise TokenizerError(f"{path}: no clip in split {split!r} (splits: {sorted(set(mf.splits))})")
        mean, std = mf.stats()
        off = mf.frame_offsets
        rows, starts, lengths, pos = [], [], [], 0
        for i in idx:
            n = int(off[i + 1] - off[i])
            if n < window:  # too short for one crop (the official loader drops these too)
                continue
            rows.append(mf.frames("features", i))
            starts.append(pos)
            lengths.append(n)
            pos += n
        if not rows:
            raise TokenizerError(f"{path}: no {split} clip has {window} frames; lower `window`")
        meta = dataset_meta(mf)
    x = (np.concatenate(rows).astype(np.float32) - mean) / std
    return TrainData(torch.from_numpy(x), torch.tensor(starts), torch.tensor(lengths), mean, std, meta)


class WindowSampler:
    """Random ``window``-frame crops: a clip uniformly, then a start uniformly (official loader).

    The generator is separate from the global RNG so that ranks draw different data while the
    global RNG (quantizer resets, dropout) stays in lock-step on every rank.
    """

    def __init__(self, data: TrainData, window: int, batch: int, seed: int, rank: int):
        self.data, self.window, self.batch = data, window, batch
        self.gen = torch.Generator().manual_seed(seed * 1_000_003 + 7919 * (rank + 1))
        self.ar = torch.arange(window)

    def sample(self) -> torch.Tensor:
        d, g = self.data, self.gen
        clip = torch.randint(len(d.starts), (self.batch,), generator=g)
        span = (d.lengths[clip] - self.window + 1).double()
        off = (torch.rand(self.batch, generator=g, dtype=torch.float64) * span).long()
        rows = (d.starts[clip] + off)[:, None] + self.ar
        return d.features[rows]


# --------------------------------------------------------------------------- optimizer

def make_optimizer(model: torch.nn.Module, cfg: OptimConfig):
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=cfg.lr, betas=tuple(cfg.betas), weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: lr_factor(i, cfg))
    return opt, sched


# --------------------------------------------------------------------------- distributed

def _ddp_args() -> set[str]:
    import inspect
    return set(inspect.signature(torch.nn.parallel.DistributedDataParallel.__init__).parameters)


# --------------------------------------------------------------------------- config & bundle

def check_config(cfg: TrainConfig) -> TrainConfig:
    """Fail before any work on values the dataclass types cannot rule out."""
    try:
        build_quantizer(cfg.quantizer)
    except ValueError as e:
        raise ConfigError(f"quantizer: {e}") from None
    problems = []
    if cfg.model.activation not in ACTIVATIONS:
        problems.append(f"model.activation {cfg.model.activation!r} is not one of {sorted(ACTIVATIONS)}")
    if cfg.loss.vel_block not in ("ric", "all"):
        problems.append(f"loss.vel_block {cfg.loss.vel_block!r} is not ric or all")
    if cfg.model.width < 1 or cfg.model.depth < 1 or cfg.model.down_t < 0:
        problems.append("model.width and model.depth must be >= 1, model.down_t >= 0")
    if cfg.iterations < 1 or cfg.batch_size < 1 or cfg.log_every < 1 or cfg.save_every < 1:
        problems.append("iterations, batch_size, log_every and save_every must be >= 1")
    if cfg.window < 1 or cfg.window % 2 ** cfg.model.down_t:
        problems.append(f"window {cfg.window} must be a positive multiple of the rate {2 ** cfg.model.down_t}")
    if problems:
        raise ConfigError("; ".join(problems))
    return cfg


def resolve_config(recipe=None, overrides=(), run: Path | None = None, resume: bool = False) -> TrainConfig:
    """Recipe + overrides; on resume the saved config, which they may not change beyond what
    ``TrainConfig.resume_may_change`` allows (motok.resume)."""
    return check_config(resume_config(TrainConfig, recipe, overrides, run, KIND, resume))


# --------------------------------------------------------------------------- loop

def _stat_mean(v, n: int) -> float:
    vals = [float(x) for x in (v if isinstance(v, (list, tuple)) else [v])[:n] if x is not None]
    return sum(vals) / len(vals) if vals else float("nan")


def train(cfg: TrainConfig, data_path: str | Path, run: str | Path, resume: bool = False,
          stop_at: int | None = None, command: str | None = None) -> dict:
    """Train (or resume) a tokenizer into the bundle folder ``run``; returns a summary.

    ``stop_at`` ends the run early at that iteration with a checkpoint, as an interruption would
    (the LR schedule still follows ``cfg.iterations``).
    """
    run, data_path = Path(run), Path(data_path)
    d = init_distributed()
    try:
        return _train(cfg, data_path, run, resume, stop_at, command, d)
    finally:
        shutdown_distributed(d)


def _train(cfg, data_path, run, resume, stop_at, command, d: Dist) -> dict:
    check_config(cfg)
    if cfg.batch_size % d.world:
        raise TokenizerError(f"batch_size {cfg.batch_size} does not split over {d.world} ranks")
    if not data_path.is_file():
        raise TokenizerError(f"{data_path}: no such file")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    device = pick_device(cfg.device, d, TokenizerError)
    inputs = hash_inputs([data_path])
    data_hash = inputs[str(data_path)]
    saved = load_bundle(run, KIND, with_train_state=True) if resume else None
    if saved is not None:
        if saved[0]["extra"].get("dataset_sha256") != data_hash:
            raise TokenizerError(f"--resume: {data_path} is not the data set {run} was trained on (hash differs)")
        if int(saved[2]["world_size"]) != d.world:
            raise TokenizerError(f"--resume: saved with {int(saved[2]['world_size'])} ranks, now {d.world}")
    data = load_train_data(data_path, cfg.split, cfg.window)
    J = data.meta["num_joints"]

    # Same seed on every rank: identical initial weights and lock-step global RNG draws.
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    model = build_model(cfg, data.features.shape[1])
    model.set_stats(data.mean, data.std)
    model.to(device).train()
    opt, sched = make_optimizer(model, cfg.optim)
    sampler = WindowSampler(data, cfg.window, cfg.batch_size // d.world, cfg.seed, d.rank)

    start = 0
    if saved is not None:
        _, state, ts = saved
        start = restore_checkpoint(model, opt, sched, sampler.gen, d, state, ts)

    net = model
    if d.world > 1:
        # Codebooks that can go unused in a step (plain-VQ RVQ under dropout) need the slow path.
        unused = any(p.requires_grad for p in model.quantizer.parameters())
        # No per-step buffer broadcast: EMA codebooks must agree through the quantizer's own
        # all-reduce (which the DDP test checks), not by being overwritten from rank 0 each step.
        sync = ({"forward_sync_buffers": False} if "forward_sync_buffers" in _ddp_args()
                else {"broadcast_buffers": False})
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[d.local_rank] if device.type == "cuda" else None,
            find_unused_parameters=unused, **sync)

    log = MetricsLog(run / "metrics.jsonl", resume_from=start if resume else None) if d.main else None
    end = min(cfg.iterations, stop_at) if stop_at is not None else cfg.iterations
    frames_per_it = cfg.batch_size * cfg.window
    acc: dict[str, float] = {}
    n_acc, t_log, last = 0, time.perf_counter(), {}
    dev_meta = {**data.meta, "dataset": Path(data_path), "dataset_sha256": data_hash,
                "rate": model.rate, "num_codebooks": model.num_codebooks,
                "codebook_size": int(model.quantizer.codebook_size), "code_dim": int(model.quantizer.dim)}

    def save(it: int):
        save_checkpoint(run, KIND, model, opt, sched, sampler.gen, d, cfg, inputs, dev_meta, it, last, command)

    with _progress.make_progress("it", extra="loss {task.fields[loss]:.4f} usage {task.fields[usage]:.2f}") as bar:
        task = bar.add_task("tokenizer", total=end, completed=start, loss=float("nan"), usage=float("nan"))
        if not d.main:
            bar.stop()
        for it in range(start + 1, end + 1):
            x = sampler.sample().to(device, non_blocking=True)
            out = net(x)
            total, parts = vqvae_loss(out.recon, x, out.losses, cfg.loss, J, cfg.quantizer.beta)
            optimizer_step(total, model.parameters(), opt, sched, cfg.optim.grad_clip)

            m = out.stats.get("num_active_codebooks", model.num_codebooks)
            parts = {k: float(v) for k, v in parts.items()}
            parts["usage"] = _stat_mean(out.stats.get("usage"), m)
            parts["perplexity"] = _stat_mean(out.stats.get("perplexity"), m)
            parts["dead"] = _stat_mean(out.stats.get("dead"), m)
            if not math.isfinite(parts["loss"]):
                raise TokenizerError(f"loss is {parts['loss']} at iteration {it}; lower optim.lr or check the data")
            for k, v in parts.items():
                acc[k] = acc.get(k, 0.0) + v
            n_acc += 1
            if d.main:
                bar.update(task, advance=1, loss=parts["loss"], usage=parts["usage"])
            if it % cfg.log_every == 0 or it == end:
                dt = time.perf_counter() - t_log
                last = {"iteration": it, **{k: v / n_acc for k, v in acc.items()},
                        "lr": sched.get_last_lr()[0], "it_s": n_acc / dt, "frames_s": n_acc * frames_per_it / dt,
                        "usage_per_codebook": [float(u) for u in out.stats.get("usage", [])],
                        "perplexity_per_codebook": [float(u) for u in out.stats.get("perplexity", [])]}
                if log is not None:
                    log.log(last)
                acc, n_acc, t_log = {}, 0, time.perf_counter()
            if it % cfg.save_every == 0 or it == end:
                save(it)
    return {"run": str(run), "iteration": end, "iterations": cfg.iterations, "world_size": d.world,
            **{k: last.get(k) for k in ("loss", "recon", "usage", "perplexity", "it_s", "frames_s")}}
