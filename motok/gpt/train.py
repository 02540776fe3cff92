"""Training the text-to-motion GPT (T2M-GPT Sec. 3.2, Eq. 5, and Sec. 4.1).

Objective (Eq. 5): next-token cross-entropy over the codes of a motion followed by the End
token, each sequence averaged over its own tokens and then over the batch (as the official
code). Inputs after End are Pad and their targets are ignored.

Corrupted sequences (Sec. 3.2, "a simple but effective strategy"): a fraction ``tau`` of the
*input* codes is replaced by random codes while the targets stay clean, so the model learns to
continue from its own imperfect samples. ``tau`` is fixed, or drawn per sequence from U[0, 1]
(``tau_uniform``). A replacement is always a *different* code, so the measured fraction of
changed inputs equals ``tau`` (the official code may draw the same code back, 1 / K of the time).

The text encoder never runs inside the loop: every caption is embedded once through
:mod:`motok.text.cache`. Long clips (more codes than the positions allow) are cropped at a
random start; a crop that stops before the clip's end gets no End target.

Runs unchanged under ``torchrun`` (the tokenizer's process-group helpers: DDP, global batch
split over ranks, per-rank data generator, rank 0 writes); resuming restores model, optimizer,
scheduler, global RNGs and every rank's data generator, so K + resume to 2K equals 2K straight.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F

from motok import progress as _progress
from motok.artifacts import hash_inputs
from motok.checkpoint import MetricsLog, load_bundle, resolve_ref
from motok.config import ConfigError
from motok.distributed import (Dist, init_distributed, pick_device, restore_checkpoint, save_checkpoint,
                               shutdown_distributed)
from motok.optim import lr_factor, optimizer_step
from motok.resume import resolve_config as resume_config
from motok.gpt.augment import noisy
from motok.gpt.data import (HOLDOUTS, IGNORE, CodeData, GPTError, SequenceSampler, corrupt,  # noqa: F401
                             default_cache_path, load_code_data, make_batch)
from motok.gpt.model import KIND, MotionGPT, TrainConfig, build_model
from motok.text.cache import TextEmbeddingCache
from motok.tokenizer.tokens import TokenFile



def gpt_loss(logits: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """Eq. 5: cross-entropy per sequence (mean over its tokens), then mean over the batch."""
    ce = F.cross_entropy(logits.transpose(1, 2), target, ignore_index=IGNORE, reduction="none")
    valid = target != IGNORE
    per_seq = (ce * valid).sum(1) / valid.sum(1).clamp(min=1)
    acc = ((logits.argmax(-1) == target) & valid).sum() / valid.sum().clamp(min=1)
    return per_seq.mean(), {"acc": acc.detach()}


# --------------------------------------------------------------------------- config & bundle

def check_augmentation(cfg: TrainConfig) -> None:
    """Clear errors naming the field, before any work."""
    for name in ("caption_dropout", "word_dropout"):
        if not (0.0 <= getattr(cfg, name) < 1.0):
            raise ConfigError(f"{name} {getattr(cfg, name)} must be in [0, 1)")
    for name in ("recombine", "word_dropout_variants"):
        if getattr(cfg, name) < 0:
            raise ConfigError(f"{name} {getattr(cfg, name)} must be >= 0")
    if cfg.snap < 0:
        raise ConfigError(f"snap {cfg.snap} must be >= 0 (0 = off)")
    if cfg.text_noise < 0:
        raise ConfigError(f"text_noise {cfg.text_noise} must be >= 0")
    if cfg.holdout not in HOLDOUTS:
        raise ConfigError(f"holdout {cfg.holdout!r}: choose from {list(HOLDOUTS)}")
    from motok.text.encoders import TokenFeatures
    if cfg.model.text_tokens not in (0, TokenFeatures.length) or \
            cfg.text_encoder.endswith("_tokens") != (cfg.model.text_tokens > 0):
        raise ConfigError(f"model.text_tokens {cfg.model.text_tokens} and text_encoder {cfg.text_encoder!r}: "
                          f"token-level conditioning needs both (a *_tokens encoder and text_tokens: "
                          f"{TokenFeatures.length}), or neither")
    if cfg.guidance != 1.0 and cfg.caption_dropout <= 0:
        raise ConfigError(f"guidance {cfg.guidance} needs caption_dropout > 0 (the null text it guides against)")


def resolve_config(recipe=None, overrides=(), run: Path | None = None, resume: bool = False) -> TrainConfig:
    """Recipe + overrides; on resume the saved config, which they may not change beyond what
    ``TrainConfig.resume_may_change`` allows (motok.resume)."""
    return resume_config(TrainConfig, recipe, overrides, run, KIND, resume)


@torch.no_grad()
def evaluate_loss(model: MotionGPT, data: CodeData, device, batch: int = 64) -> dict:
    """Teacher-forced loss and accuracy, no corruption: the first caption of every clip, its first codes."""
    was = model.training
    model.eval()
    first = {}
    for k, c in enumerate(data.pair_clip.tolist()):
        first.setdefault(c, k)
    rows = list(first.values())
    tot = {"loss": 0.0, "acc": 0.0}
    for a in range(0, len(rows), batch):
        pick = torch.tensor(rows[a:a + batch])
        seqs, ends = [], []
        for c in data.pair_clip[pick].tolist():
            n = min(int(data.lengths[c]), model.max_codes)
            seqs.append(data.codes[int(data.starts[c]):int(data.starts[c]) + n])
            ends.append(n == int(data.lengths[c]))
        inp, tgt = make_batch(seqs, ends, model.end_id, model.pad_id)
        loss, parts = gpt_loss(model(data.text[data.pair_text[pick]].to(device), inp.to(device)), tgt.to(device))
        tot["loss"] += float(loss) * len(pick)
        tot["acc"] += float(parts["acc"]) * len(pick)
    model.train(was)
    return {k: v / len(rows) for k, v in tot.items()}


# --------------------------------------------------------------------------- loop

def train(cfg: TrainConfig, tokens: str | Path, run: str | Path, resume: bool = False,
          stop_at: int | None = None, command: str | None = None) -> dict:
    """Train (or resume) a GPT on a ``tokens`` artifact into the bundle folder ``run``.

    ``stop_at`` ends early at that iteration with a checkpoint, as an interruption would."""
    d = init_distributed()
    try:
        return _train(cfg, Path(tokens), Path(run), resume, stop_at, command, d)
    finally:
        shutdown_distributed(d)


def _train(cfg: TrainConfig, tokens: Path, run: Path, resume, stop_at, command, d: Dist) -> dict:
    if cfg.batch_size % d.world:
        raise GPTError(f"batch_size {cfg.batch_size} does not split over {d.world} ranks")
    if not (0.0 <= cfg.tau <= 1.0):
        raise ConfigError(f"tau {cfg.tau} must be in [0, 1]")
    check_augmentation(cfg)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    device = pick_device(cfg.device, d, GPTError)
    inputs = hash_inputs([tokens])
    cache_path = Path(cfg.text_cache) if cfg.text_cache else default_cache_path(tokens)
    # Rank 0 fills the cache; the others wait and then find every caption in it.
    if d.main:
        data, val = _load(tokens, cfg, cache_path)
    if d.world > 1:
        dist.barrier()
    if not d.main:
        data, val = _load(tokens, cfg, cache_path, write=False)
    with TokenFile(tokens) as tf:
        K, tok_meta = tf.codebook_size, dict(tf.h5.attrs)
    text_dim = int(data.text.shape[1])

    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    model = build_model(cfg, K, text_dim).to(device).train()
    decay = [p for n, p in model.named_parameters() if p.dim() >= 2]
    no_decay = [p for n, p in model.named_parameters() if p.dim() < 2]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": cfg.optim.weight_decay},
                             {"params": no_decay, "weight_decay": 0.0}], lr=cfg.optim.lr, betas=tuple(cfg.optim.betas))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: lr_factor(i, cfg.optim))
    sampler = SequenceSampler(data, cfg.batch_size // d.world, model.max_codes, cfg.seed, d.rank)

    start = 0
    if resume:
        meta, state, ts = load_bundle(run, KIND, with_train_state=True)
        if meta["extra"].get("tokens_sha256") != inputs[str(tokens)]:
            raise GPTError(f"--resume: {tokens} is not the tokens artifact {run} was trained on (hash differs)")
        if int(ts["world_size"]) != d.world:
            raise GPTError(f"--resume: saved with {int(ts['world_size'])} ranks, now {d.world}")
        start = restore_checkpoint(model, opt, sched, sampler.gen, d, state, ts)
    net = model
    if d.world > 1:
        ids = [d.local_rank] if device.type == "cuda" else None
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=ids)

    log = MetricsLog(run / "metrics.jsonl", resume_from=start if resume else None) if d.main else None
    end = min(cfg.iterations, stop_at) if stop_at is not None else cfg.iterations
    # Path values: stored relative to the run, so the run works from any directory (checkpoint.py).
    places = resolve_ref(str(tok_meta["tokenizer"]), tokens.parent)
    tok_run = next((p for p in places if p.exists()), places[0])
    extra = {"tokens": tokens, "tokens_sha256": inputs[str(tokens)], "tokenizer": tok_run,
             "tokenizer_sha256": str(tok_meta["tokenizer_sha256"]), "codebook_size": K, "codebook": 0,
             "tokenizer_codebooks": int(tok_meta["num_codebooks"]), "rate": int(tok_meta["rate"]),
             "fps": float(tok_meta["fps"]), "text_encoder": cfg.text_encoder, "text_dim": text_dim,
             "text_cache": cache_path, "train_pairs": len(data.pair_clip)}
    acc, n_acc, ntok, t_log, last = {}, 0, 0, time.perf_counter(), {}

    def save(it: int):
        save_checkpoint(run, KIND, model, opt, sched, sampler.gen, d, cfg, inputs, extra, it, last, command)

    with _progress.make_progress("it", extra="loss {task.fields[loss]:.3f} acc {task.fields[acc]:.2f}") as bar:
        task = bar.add_task("gpt", total=end, completed=start, loss=float("nan"), acc=float("nan"))
        if not d.main:
            bar.stop()
        for it in range(start + 1, end + 1):
            text, seqs, ends = sampler.sample()
            inp, tgt = make_batch(seqs, ends, model.end_id, model.pad_id)
            if cfg.tau_uniform:
                tau = torch.rand(len(seqs), generator=sampler.gen)
            else:
                tau = torch.full((len(seqs),), cfg.tau)
            inp, hit = corrupt(inp, inp != model.pad_id, tau, K, sampler.gen)
            text = noisy(text, cfg.text_noise, sampler.gen)
            drop = None
            if cfg.caption_dropout > 0:
                drop = (torch.rand(len(seqs), generator=sampler.gen) < cfg.caption_dropout).to(device)
            loss, parts = gpt_loss(net(text.to(device), inp.to(device), drop_text=drop), tgt.to(device))
            optimizer_step(loss, model.parameters(), opt, sched, cfg.optim.grad_clip)
            lv = loss.item()
            if not math.isfinite(lv):
                raise GPTError(f"loss is {lv} at iteration {it}; lower optim.lr")
            valid = int((inp != model.pad_id).sum())
            step = {"loss": lv, "acc": float(parts["acc"]), "tau_measured": float(hit.sum()) / max(valid, 1)}
            for k, v in step.items():
                acc[k] = acc.get(k, 0.0) + v
            n_acc += 1
            ntok += valid + len(seqs)
            if d.main:
                bar.update(task, advance=1, loss=lv, acc=float(parts["acc"]))
            if it % cfg.log_every == 0 or it == end:
                dt = time.perf_counter() - t_log
                last = {"iteration": it, **{k: v / n_acc for k, v in acc.items()}, "lr": sched.get_last_lr()[0],
                        "it_s": n_acc / dt, "tokens_s": ntok * d.world / dt}
                if val is not None and d.main and (it % cfg.eval_every == 0 or it == end):
                    last.update({f"val_{k}": v for k, v in evaluate_loss(model, val, device).items()})
                if log is not None:
                    log.log(last)
                acc, n_acc, ntok, t_log = {}, 0, 0, time.perf_counter()
            if it % cfg.save_every == 0 or it == end:
                save(it)
    return {"run": str(run), "iteration": end, "iterations": cfg.iterations, "world_size": d.world,
            **{k: last.get(k) for k in ("loss", "acc", "val_loss", "val_acc", "it_s", "tokens_s")}}


def _load(tokens: Path, cfg: TrainConfig, cache_path: Path, write: bool = True):
    cache = TextEmbeddingCache(cache_path)
    if not write:
        cache.path = None  # read-only on non-zero ranks
    data = load_code_data(tokens, cfg.split, cfg.text_encoder, cache, cfg)
    val = None
    if cfg.val_split:
        try:
            val = load_code_data(tokens, cfg.val_split, cfg.text_encoder, cache)
        except GPTError:
            val = None  # no such split (small sets): train without a validation loss
    if cache.truncated:
        first = next(iter(cache.truncated))
        _progress.info(f"[yellow]note:[/] {len(cache.truncated)} caption(s) are longer than the {cfg.text_encoder} "
                       f"encoder reads and were cut off, e.g. {first[:60]!r}")
    return data, val
