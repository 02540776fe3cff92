"""A text-motion co-embedding evaluator trained for any motion-dataset (``motok eval train-evaluator``).

The role of Guo et al.'s (CVPR 2022) evaluator -- a motion encoder and a text encoder whose
distances give R-precision, FID, MM-Dist and Diversity -- but trained contrastively as in TMR
(Petrovich et al. 2023): a symmetric InfoNCE loss with a fixed temperature over the in-batch
pairs, where negatives that share the positive's caption text or its label set (e.g. Bandai's
content x style) are dropped from the denominator, since they are not wrong matches.

- Motion side: normalized features without the 4 foot-contact channels (as Guo's movement
  encoder), a linear layer, two stride-2 convolutions (Guo's unit length of 4 frames), a small
  transformer with sinusoidal positions, masked mean pooling, a linear head.
- Text side: a sentence embedding from a frozen encoder of :mod:`motok.text.encoders`, computed
  once per distinct caption and cached, then a learned MLP. Default ``bow``, a weight-free hashed
  bag of words and word pairs: everything this side knows it learns from the training captions,
  so it is independent of the GPT's frozen ``minilm`` (in Guo et al. and T2M-GPT the evaluator's
  text encoder is not the generator's; a shared one can favour the generator). ``minilm`` (the
  default of motok 0.1.0) remains an option.
- Both embeddings are L2-normalized: Euclidean distance ranks exactly as the cosine the loss
  trains, so the metrics' Euclidean protocol and the training agree.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from motok import progress as _progress
from motok.artifacts import Provenance, command_line, hash_inputs, read_strings
from motok.checkpoint import MetricsLog, load_bundle, register_kind, save_bundle, sha256_state
from motok.config import ConfigError, from_dict, load_config, to_dict
from motok.data.dataset import MotionFile
from motok.errors import MotokError
from motok.features.humanml3d import NUM_CONTACTS
from motok.ranges import In

KIND = "evaluator"
register_kind(KIND, (1,))
UNIT = 4  # frames per motion token of the encoder (Guo's unit_length)


@dataclass
class EvaluatorConfig:
    # any name motok.text.encoders knows: bow | minilm | clip. bow: no pretrained weights, so
    # the evaluator's text side shares nothing with a GPT on minilm or clip (docs/eval.md).
    text_encoder: str = "bow"
    embed_dim: In[int, ">= 1"] = 128  # the shared embedding both towers end in (even)
    width: In[int, ">= 1"] = 128  # the motion encoder's channels and the text MLP's hidden size (even)
    layers: In[int, ">= 1"] = 2  # transformer layers of the motion encoder
    heads: In[int, ">= 1"] = 4  # its attention heads (must divide width)
    dropout: In[float, "[0, 1)"] = 0.1  # in the motion transformer and the text MLP
    temperature: In[float, "> 0"] = 0.1  # the InfoNCE temperature, fixed (TMR's 0.1)
    # Which shared attributes make an in-batch pair no negative: caption text, label set.
    filter_negatives: list[str] = field(default_factory=lambda: ["caption", "label"])
    iterations: In[int, ">= 1"] = 2000  # AdamW steps, one batch each
    batch_size: In[int, ">= 1"] = 64  # clips per batch, each with one of its captions: the in-batch pairs (>= 2)
    lr: In[float, "> 0"] = 3e-4  # AdamW's peak learning rate, after the warm-up; cosine decay to 0 at the end
    weight_decay: In[float, ">= 0"] = 0.01  # AdamW's decoupled weight decay
    warmup: In[int, ">= 0"] = 100  # iterations of linear warm-up
    min_frames: In[int, ">= 1"] = 16  # shortest random crop
    max_frames: In[int, ">= 1"] = 160  # longest training crop (bounds padding; Guo uses 196)
    # a crop keeps at least this share of the clip, so it still matches the caption
    crop_min_fraction: In[float, "(0, 1]"] = 0.7
    split: str = "train"  # the data set's split it trains on
    report_split: str = "test"  # retrieval reported on this split after training
    seed: In[int, ">= 0"] = 0  # weights, batches, captions and crops drawn
    log_every: In[int, ">= 1"] = 50  # iterations per metrics.jsonl row (their mean loss); the last is always logged
    threads: In[int, ">= 0"] = 1  # torch threads; on a shared 2-core machine one thread ran 5x faster than two


class EvaluatorError(MotokError, ValueError):
    pass


# --------------------------------------------------------------------------- text encoders

def text_encoder(name: str):
    """An object with ``encode(list[str]) -> (B, d)`` numpy array: :func:`motok.text.encoders.get_encoder`."""
    from motok.text.encoders import TextEncoderError, get_encoder
    try:
        return get_encoder(name)
    except TextEncoderError as e:
        raise EvaluatorError(str(e)) from None


class CachedText:
    """Sentence embeddings computed once per distinct caption (the frozen side of the text tower)."""

    def __init__(self, encoder):
        self.encoder = encoder
        self.cache: dict[str, np.ndarray] = {}

    def __call__(self, texts: list[str]) -> np.ndarray:
        todo = sorted({t for t in texts if t not in self.cache})
        if todo:
            vecs = np.asarray(self.encoder.encode(todo), dtype=np.float32)
            self.cache.update(zip(todo, vecs))
        return np.stack([self.cache[t] for t in texts])


# --------------------------------------------------------------------------- model

def sinusoid(n: int, dim: int) -> torch.Tensor:
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe = torch.zeros(n, dim)
    pe[:, 0::2] = torch.sin(pos * freq)
    pe[:, 1::2] = torch.cos(pos * freq)
    return pe


class MotionEncoder(nn.Module):
    def __init__(self, in_dim: int, cfg: EvaluatorConfig):
        super().__init__()
        w = cfg.width
        self.inp = nn.Linear(in_dim, w)
        self.conv1 = nn.Conv1d(w, w, 4, 2, 1)
        self.conv2 = nn.Conv1d(w, w, 4, 2, 1)
        layer = nn.TransformerEncoderLayer(w, cfg.heads, 2 * w, cfg.dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.tf = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)
        self.head = nn.Sequential(nn.LayerNorm(w), nn.Linear(w, cfg.embed_dim))

    def forward(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """``x (B, T, in)`` normalized, zero past each length; ``T`` a multiple of 4."""
        B, T, _ = x.shape
        ar = torch.arange(T, device=x.device)
        # Zeroing past each length after every layer makes a clip's embedding independent of
        # how much padding its batch has (the convolutions would otherwise read biases there).
        h = self.inp(x) * (ar[None, :] < lengths[:, None])[..., None]
        l2 = (lengths + 1) // 2
        h = F.gelu(self.conv1(h.transpose(1, 2)))
        h = h * (ar[None, :h.shape[-1]] < l2[:, None])[:, None]
        l4 = ((l2 + 1) // 2).clamp(min=1)
        h = F.gelu(self.conv2(h)).transpose(1, 2)
        pad = ar[None, :h.shape[1]] >= l4[:, None]
        h = h + sinusoid(h.shape[1], h.shape[2]).to(h)
        h = self.tf(h, src_key_padding_mask=pad)
        pooled = (h * ~pad[..., None]).sum(1) / l4[:, None]
        return F.normalize(self.head(pooled), dim=-1)


class Evaluator(nn.Module):
    def __init__(self, feature_dim: int, text_dim: int, cfg: EvaluatorConfig):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("mean", torch.zeros(feature_dim))
        self.register_buffer("std", torch.ones(feature_dim))
        self.motion = MotionEncoder(feature_dim - NUM_CONTACTS, cfg)
        self.text = nn.Sequential(nn.Linear(text_dim, cfg.width), nn.GELU(), nn.Dropout(cfg.dropout),
                                  nn.Linear(cfg.width, cfg.embed_dim))

    def embed_text(self, sent: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.text(sent), dim=-1)

    def prepare(self, clips: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw feature clips ``(T_i, D)`` -> a padded normalized batch without contacts, lengths."""
        lengths = torch.tensor([len(c) for c in clips])
        T = int(-(-int(lengths.max()) // UNIT) * UNIT)
        x = torch.zeros(len(clips), T, self.mean.shape[0] - NUM_CONTACTS)
        for i, c in enumerate(clips):
            z = (torch.as_tensor(np.asarray(c), dtype=torch.float32) - self.mean) / self.std
            x[i, :len(c)] = z[:, :-NUM_CONTACTS]
        return x, lengths


# --------------------------------------------------------------------------- data

@dataclass
class SplitData:
    clips: list[np.ndarray]  # raw features per clip
    captions: list[list[str]]
    labels: list[str]  # canonical JSON of each clip's labels ("" when it has none)
    names: list[str]


def load_split(mf: MotionFile, split: str | None) -> SplitData:
    """Clips of one split with their captions and labels, reading each HDF5 column once."""
    which = mf.split_indices(split) if split else list(range(len(mf)))
    g = mf.h5["captions"]
    cap_clip, texts = g["clip"][()], read_strings(g["text"])
    by_clip: dict[int, list[str]] = {}
    for c, t in zip(cap_clip, texts):
        by_clip.setdefault(int(c), []).append(t)
    labels = read_strings(mf.h5["clips/labels"])
    keep = [i for i in which if by_clip.get(i)]
    return SplitData([mf.frames("features", i) for i in keep], [by_clip[i] for i in keep],
                     ["" if labels[i] in ("{}", "") else labels[i] for i in keep], [mf.names[i] for i in keep])


def negatives_mask(captions: list[str], labels: list[str], which: list[str]) -> torch.Tensor:
    """``(B, B)`` True where pair (i, j), i != j, shares the caption or the label: not a negative."""
    B = len(captions)
    same = torch.zeros(B, B, dtype=torch.bool)
    for key, vals in (("caption", captions), ("label", labels)):
        if key in which:
            ids = {v: k for k, v in enumerate(dict.fromkeys(vals))}
            v = torch.tensor([ids[x] for x in vals])
            s = v[:, None] == v[None, :]
            if key == "label":
                s &= torch.tensor([x != "" for x in vals])[:, None]
            same |= s
    return same & ~torch.eye(B, dtype=torch.bool)


def info_nce(text: torch.Tensor, motion: torch.Tensor, void: torch.Tensor, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE (text->motion and motion->text) with voided negatives removed."""
    logits = (text @ motion.T / temperature).masked_fill(void, float("-inf"))
    target = torch.arange(len(text))
    return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))


def crop(n: int, cfg: EvaluatorConfig, rng: np.random.Generator) -> tuple[int, int]:
    lo = min(n, max(cfg.min_frames, int(math.ceil(cfg.crop_min_fraction * n))))
    hi = min(n, cfg.max_frames)
    length = int(rng.integers(min(lo, hi), hi + 1))
    return int(rng.integers(0, n - length + 1)), length


# --------------------------------------------------------------------------- embedding API

class LoadedEvaluator:
    """A trained evaluator: ``texts(list[str])`` and ``motions(list of raw (T, D) features)`` -> numpy."""

    def __init__(self, model: Evaluator, meta: dict):
        self.model, self.meta = model.eval(), meta
        self.text_cache = CachedText(text_encoder(meta["config"]["text_encoder"]))

    @torch.no_grad()
    def texts(self, texts: list[str]) -> np.ndarray:
        return self.model.embed_text(torch.from_numpy(self.text_cache(texts))).numpy()

    @torch.no_grad()
    def motions(self, clips: list[np.ndarray], batch: int = 64) -> np.ndarray:
        D = self.model.mean.shape[0]
        for c in clips[:1]:
            if c.shape[-1] != D:
                raise EvaluatorError(f"motions have {c.shape[-1]}-d features; the evaluator expects {D}")
        # Similar lengths together: less padding to push through the convolutions.
        order = np.argsort([len(c) for c in clips], kind="stable")
        out = np.zeros((len(clips), self.model.cfg.embed_dim), dtype=np.float32)
        for s in range(0, len(order), batch):
            sel = order[s:s + batch]
            x, lengths = self.model.prepare([clips[i] for i in sel])
            out[sel] = self.model.motion(x, lengths).numpy()
        return out


def load_evaluator(run: str | Path) -> LoadedEvaluator:
    meta, state, _ = load_bundle(run, KIND)
    cfg = from_dict(EvaluatorConfig, meta["config"])
    model = Evaluator(int(meta["extra"]["feature_dim"]), int(meta["extra"]["text_dim"]), cfg)
    model.load_state_dict(state)
    return LoadedEvaluator(model, meta)


# --------------------------------------------------------------------------- retrieval

def _ranks(scores: np.ndarray, positive: np.ndarray) -> np.ndarray:
    """1-based rank of the best-scored positive of each row (ties count against it)."""
    best = np.where(positive, scores, -np.inf).max(1)
    return (np.where(positive, -np.inf, scores) >= best[:, None]).sum(1) + 1


def _summary(ranks: np.ndarray, prefix: str) -> dict:
    return {f"{prefix}R@1": float((ranks <= 1).mean()), f"{prefix}R@3": float((ranks <= 3).mean()),
            f"{prefix}median_rank": float(np.median(ranks))}


def retrieval(ev: LoadedEvaluator, data: SplitData, chance_draws: int = 20, seed: int = 0) -> dict:
    """Text->motion (every caption queries all motions; hit = its own clip) and motion->text (each
    motion ranks the split's distinct captions; hit = one of its own), with chance from random
    scores; ``label_R@1`` counts a top-1 clip with the query's label as a hit."""
    m = ev.motions(data.clips)
    q_text = [t for caps in data.captions for t in caps]
    q_clip = np.array([i for i, caps in enumerate(data.captions) for _ in caps])
    uniq = list(dict.fromkeys(q_text))
    t = ev.texts(uniq)
    col = {x: k for k, x in enumerate(uniq)}
    t2m_pos = q_clip[:, None] == np.arange(len(m))[None]
    m2t_pos = np.zeros((len(m), len(uniq)), dtype=bool)
    for i, caps in enumerate(data.captions):
        m2t_pos[i, [col[x] for x in caps]] = True
    labels = np.array(data.labels)
    same_label = (labels[q_clip][:, None] == labels[None]) & (labels[q_clip][:, None] != "")

    def measure(t2m_scores, m2t_scores):
        out = {**_summary(_ranks(t2m_scores, t2m_pos), "t2m_"), **_summary(_ranks(m2t_scores, m2t_pos), "m2t_")}
        if same_label.any():
            out["t2m_label_R@1"] = float(same_label[np.arange(len(q_clip)), t2m_scores.argmax(1)].mean())
        return out

    sim = t[[col[x] for x in q_text]] @ m.T
    res = measure(sim, m @ t.T)
    rng = np.random.default_rng(seed)
    draws = [measure(rng.random(sim.shape), rng.random((len(m), len(uniq)))) for _ in range(chance_draws)]
    chance = {k: float(np.mean([d[k] for d in draws])) for k in res}
    out = {"clips": len(m), "captions": len(q_text), "distinct_captions": len(uniq), **res, "chance": chance}
    if same_label.any():
        # What a perfect reader of the captions can reach when several clips share a label: the
        # right label every time, then a uniform guess among its clips.
        n = np.maximum(same_label.sum(1), 1)
        out["label_oracle"] = {"t2m_R@1": float(np.mean(1 / n)), "t2m_R@3": float(np.mean(np.minimum(3 / n, 1)))}
    return out


# --------------------------------------------------------------------------- training

def resolve_config(recipe=None, overrides=()) -> EvaluatorConfig:
    cfg = load_config(EvaluatorConfig, recipe, overrides)
    bad = sorted(set(cfg.filter_negatives) - {"caption", "label"})
    if bad:
        raise ConfigError(f"filter_negatives: {bad} not among caption, label")
    if cfg.iterations < 1 or cfg.batch_size < 2 or cfg.temperature <= 0 or cfg.embed_dim % 2 or cfg.width % 2:
        raise ConfigError("iterations >= 1, batch_size >= 2, temperature > 0, even embed_dim and width")
    return cfg


def train_evaluator(cfg: EvaluatorConfig, data_path: str | Path, run: str | Path, command: str | None = None) -> dict:
    """Train into the bundle folder ``run``; returns a summary with retrieval on ``cfg.report_split``."""
    from motok.tokenizer.train import stats_split
    run, data_path = Path(run), Path(data_path)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    enc = CachedText(text_encoder(cfg.text_encoder))
    with MotionFile(data_path, "motion-dataset") as mf:
        train = load_split(mf, cfg.split)
        if len(train.clips) < 2:
            raise EvaluatorError(f"{data_path}: split {cfg.split!r} has {len(train.clips)} captioned clip(s); need 2+")
        report = load_split(mf, cfg.report_split) if cfg.report_split in mf.splits else None
        mean, std = mf.stats()
        meta = {"feature_dim": int(mf.h5["frames/features"].shape[1]), "num_joints": int(mf.skeleton.num_joints),
                "fps": mf.fps, "stats_split": stats_split(mf)}
    enc([t for caps in train.captions for t in caps])
    text_dim = len(next(iter(enc.cache.values())))
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    model = Evaluator(meta["feature_dim"], text_dim, cfg)
    model.mean.copy_(torch.from_numpy(np.asarray(mean, np.float32)))
    model.std.copy_(torch.from_numpy(np.asarray(std, np.float32)))
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    # Linear warm-up, then cosine decay to 0 over the run.
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: min(1.0, (i + 1) / (cfg.warmup + 1)) * 0.5 * (
        1 + math.cos(math.pi * min(i, cfg.iterations) / cfg.iterations)))
    log = MetricsLog(run / "metrics.jsonl")
    B = min(cfg.batch_size, len(train.clips))
    history, acc, n_acc, t0 = [], 0.0, 0, time.perf_counter()
    model.train()
    with _progress.make_progress("it", extra="loss {task.fields[loss]:.3f}") as bar:
        task = bar.add_task("evaluator", total=cfg.iterations, loss=float("nan"))
        for it in range(1, cfg.iterations + 1):
            idx = rng.choice(len(train.clips), B, replace=False)
            caps = [train.captions[i][rng.integers(len(train.captions[i]))] for i in idx]
            clips = []
            for i in idx:
                s, n = crop(len(train.clips[i]), cfg, rng)
                clips.append(train.clips[i][s:s + n])
            x, lengths = model.prepare(clips)
            m = model.motion(x, lengths)
            t = model.embed_text(torch.from_numpy(enc(caps)))
            loss = info_nce(t, m, negatives_mask(caps, [train.labels[i] for i in idx], cfg.filter_negatives),
                            cfg.temperature)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            lv = float(loss.detach())
            if not math.isfinite(lv):
                raise EvaluatorError(f"loss is {lv} at iteration {it}; lower lr")
            acc += lv
            n_acc += 1
            bar.update(task, advance=1, loss=lv)
            if it % cfg.log_every == 0 or it == cfg.iterations:
                rec = {"iteration": it, "loss": acc / n_acc, "lr": sched.get_last_lr()[0],
                       "it_s": it / (time.perf_counter() - t0)}
                log.log(rec)
                history.append(rec)
                acc, n_acc = 0.0, 0
    model.eval()
    ev = LoadedEvaluator(model, {"config": to_dict(cfg)})
    ev.text_cache = enc
    summary = {"run": str(run), "data": str(data_path), "text_encoder": cfg.text_encoder, "text_dim": text_dim,
               "iterations": cfg.iterations, "seconds": round(time.perf_counter() - t0, 1),
               "first_loss": history[0]["loss"], "final_loss": history[-1]["loss"]}
    if report is not None and len(report.clips) > 1:
        summary["retrieval"] = {"split": cfg.report_split, **retrieval(ev, report)}
    prov = Provenance(command=command or command_line(), config=to_dict(cfg), inputs=hash_inputs([data_path]))
    save_bundle(run, KIND, model.state_dict(), to_dict(cfg), prov,
                extra={**meta, "text_dim": text_dim, "dataset": Path(data_path),
                       "dataset_sha256": prov.inputs.get(str(data_path)), "summary": summary})
    summary["model_sha256"] = sha256_state(model.state_dict())
    return summary
