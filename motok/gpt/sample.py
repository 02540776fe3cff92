"""Text -> codes -> motion: sampling the T2M-GPT transformer (Sec. 3.2, inference).

Generation starts from the text embedding alone (position 0) and draws one code per step from
``p(S_i | c, S_<i)`` until End. Every (text, sample) pair is a row of one batch; a row that has
emitted End is fed Pad and ignored while the others go on, and the loop stops when all have.

- ``target_len`` (``--seconds``): End is masked before that many codes and forced at it.
  Without it, End is masked only at step 0 (a motion has at least one token) and forced when
  the positions run out (``block_size - 1`` codes).
- Filtering: temperature, then top-k, then top-p (nucleus) on the logits; ``argmax`` picks the
  best remaining code instead of sampling.
- Randomness: sample ``j`` draws its Gumbel noise from its own generator seeded ``seed + j``
  (Gumbel-max is an exact categorical draw), so a sample does not depend on which other texts
  or how many samples share the batch, and ``--seed s`` sample ``j`` equals ``--seed s + j`` sample 0.
- With the key/value cache each step runs one position; without it (benchmarks, tests) the
  whole prefix is recomputed; both give the same logits.
- Continuation (``prefix``): the rows start from given codes instead of from the text alone, as
  if the model had sampled them (the closed loop of ``motok.control.closed_loop`` feeds it the
  tokens of the simulated motion); ``target_len`` then counts them, and what is returned is
  the codes after them. Without a prefix nothing changes, to the bit.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from motok import progress as _progress
from motok.artifacts import Provenance, command_line
from motok.atomic import check_writable
from motok.checkpoint import bundle_ref
from motok.data.dataset import write_motion
from motok.gpt.data import GPTError
from motok.gpt.model import MotionGPT, load_gpt
from motok.text.cache import TextEmbeddingCache
from motok.text.encoders import get_encoder

if TYPE_CHECKING:
    from motok.tokenizer.tokens import Tokenizer


def filter_logits(logits: torch.Tensor, temperature: float = 1.0, top_k: int | None = None,
                  top_p: float | None = None) -> torch.Tensor:
    """Temperature, top-k and nucleus filtering; removed entries become -inf (one always survives)."""
    if temperature <= 0:
        raise GPTError(f"temperature {temperature} must be > 0 (use --argmax for greedy decoding)")
    x = logits / temperature
    if top_k is not None and 0 < top_k < x.shape[-1]:
        kth = torch.topk(x, top_k, dim=-1).values[..., -1:]
        x = x.masked_fill(x < kth, float("-inf"))
    if top_p is not None and top_p < 1.0:
        srt, order = torch.sort(x, dim=-1, descending=True)
        cum = torch.softmax(srt, dim=-1).cumsum(-1)
        # Drop a token when the tokens ranked above it already hold top_p of the mass.
        drop_sorted = (cum - torch.softmax(srt, dim=-1)) >= top_p
        drop_sorted[..., 0] = False
        x = x.masked_fill(torch.zeros_like(drop_sorted).scatter(-1, order, drop_sorted), float("-inf"))
    return x


@dataclass
class Generation:
    codes: list[torch.Tensor]  # per row, (L_b,) code indices without End
    logits: list[torch.Tensor]  # per step, (B, K + 1) raw logits (filled when record_logits)
    steps: int


@torch.no_grad()
def generate(model: MotionGPT, text: torch.Tensor, *, target_len: torch.Tensor | None = None,
             temperature: float = 1.0, top_k: int | None = None, top_p: float | None = None,
             argmax: bool = False, seeds: list | None = None, use_cache: bool = True,
             record_logits: bool = False, guidance: float | None = None,
             prefix: torch.Tensor | None = None) -> Generation:
    """Autoregressive codes for each row of ``text`` (B, text_dim); see the module docstring.
    ``guidance`` (default: the model's own, from its training config) != 1 applies classifier-free
    guidance. ``seeds``: an int per row, or a ``torch.Generator`` per row whose stream goes on
    from call to call (a closed loop's successive plans). ``prefix`` (B, P): codes every row
    continues from; the codes returned are the new ones only."""
    model.eval()
    B, end, pad, cap = text.shape[0], model.end_id, model.pad_id, model.max_codes
    dev = text.device
    g_scale = float(model.default_guidance if guidance is None else guidance)
    check_guidance(model, g_scale)
    cfg_on = g_scale != 1.0
    if target_len is not None:
        target_len = torch.as_tensor(target_len, device=dev).clamp(1, cap)
    gens = [s if isinstance(s, torch.Generator) else torch.Generator().manual_seed(int(s))
            for s in (seeds if seeds is not None else range(B))]
    P = 0 if prefix is None else int(prefix.shape[1])
    if P >= cap:
        raise GPTError(f"a prefix of {P} codes leaves no position to generate (the model holds {cap})")
    # With guidance the batch holds every row twice: with its text, then with the null text.
    rows_text = torch.cat([text, text]) if cfg_on else text
    drop = torch.arange(2 * B, device=dev) >= B if cfg_on else None
    cache = model.new_cache(len(rows_text)) if use_cache else None

    def step(lg: torch.Tensor) -> torch.Tensor:  # l_u + g (l_c - l_u), Ho & Salimans 2022, Eq. 6 on logits
        return lg[B:] + g_scale * (lg[:B] - lg[B:]) if cfg_on else lg

    seq = torch.empty(B, 0, dtype=torch.long, device=dev) if not P else prefix.to(dev, torch.long)
    fed = None if not P else torch.cat([seq, seq]) if cfg_on else seq  # text and prefix in one call
    logits = step(model(rows_text, fed, cache, drop_text=drop)[:, -1])
    done = torch.zeros(B, dtype=torch.bool, device=dev)
    lengths = torch.full((B,), cap, dtype=torch.long, device=dev)
    recorded = []
    for t in range(P, cap + 1):
        if record_logits:
            recorded.append(logits.float().cpu())
        lg = logits.float().clone()
        ban_end = torch.full((B,), t == P, device=dev) if target_len is None else t < target_len
        force_end = torch.full((B,), t >= cap, device=dev) if target_len is None else t >= target_len
        lg[ban_end, end] = float("-inf")
        lg = filter_logits(lg, 1.0 if argmax else temperature, top_k, top_p)
        if not argmax:
            u = torch.stack([torch.rand(lg.shape[-1], generator=g) for g in gens]).to(dev)
            lg = lg - torch.log(-torch.log(u))  # + Gumbel noise: the argmax is a categorical draw
        tok = lg.argmax(-1)
        tok = torch.where(force_end, torch.full_like(tok, end), tok)
        newly = (tok == end) & ~done
        lengths[newly] = t
        done |= newly
        if bool(done.all()):
            break
        feed = torch.where(done, torch.full_like(tok, pad), tok)
        seq = torch.cat([seq, feed[:, None]], dim=1)
        fed = torch.cat([seq, seq]) if cfg_on else seq
        if use_cache:
            out = model(None, fed[:, -1:], cache)
        else:
            out = model(rows_text, fed, drop_text=drop)
        logits = step(out[:, -1])
    return Generation([seq[b, P:lengths[b]].cpu() for b in range(B)], recorded, seq.shape[1] + 1 - P)


def check_guidance(model: MotionGPT, guidance: float) -> None:
    """Guidance needs a scale >= 0 and, unless it is 1 (off), a model with a null text."""
    if not (math.isfinite(guidance) and guidance >= 0):
        raise GPTError(f"--guidance {guidance} must be >= 0 (1 = no guidance)")
    if guidance != 1.0 and model.null_text is None:
        raise GPTError(f"--guidance {guidance} needs a GPT trained with caption dropout (caption_dropout > 0); "
                       f"this one was not: use --guidance 1")


def _slug(text: str, n: int = 40) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:n] or "text"


def sample_name(i: int, text: str, j: int) -> str:
    """The clip name of sample ``j`` of text ``i``: ``03-a-person-walks-forward-01``."""
    return f"{i:02d}-{_slug(text)}-{j:02d}"


def _numbered(path: Path, names: list[str], k: int) -> Path:
    return path if len(names) == 1 else path.with_name(f"{path.stem}_{names[k]}{path.suffix}")


def check_sampling(texts: list[str], *, num_samples: int = 1, temperature: float = 1.0, top_k: int | None = None,
                   top_p: float | None = None, argmax: bool = False, seconds: float | None = None,
                   codebook_size: int | None = None) -> None:
    """Refuse sampling settings that would be silently meaningless, before any work."""
    if not texts:
        raise GPTError("no text given: use --text or --texts-file")
    blank = [i + 1 for i, t in enumerate(texts) if not str(t).strip()]
    if blank:
        raise GPTError(f"text {blank[0]} is empty: give a sentence to generate from")
    if num_samples < 1:
        raise GPTError(f"--num-samples {num_samples} must be >= 1")
    if not argmax and not (math.isfinite(temperature) and temperature > 0):
        raise GPTError(f"--temperature {temperature} must be > 0 (use --argmax for greedy decoding)")
    if top_k is not None and (top_k < 1 or (codebook_size is not None and top_k > codebook_size)):
        limit = f"{codebook_size}, the codebook size" if codebook_size is not None else "the codebook size"
        raise GPTError(f"--top-k {top_k} must be between 1 and {limit}")
    if top_p is not None and not (0.0 < top_p <= 1.0):
        raise GPTError(f"--top-p {top_p} must be in (0, 1]")
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise GPTError(f"--seconds {seconds} must be > 0")


def load_for_sampling(run: str | Path, tokenizer: str | Path | None = None, allow_mismatch: bool = False,
                      error: type[Exception] = GPTError, snap: int | None = None):
    """The GPT of ``run``, the tokenizer that decodes its codes (``tokenizer`` or the one it was
    trained with) and its caption cache: ``(model, meta, tok_model, tok_meta, tok_run, cache)``.
    With ``snap`` (default: the run's recipe) the cache snaps new sentences (:mod:`motok.gpt.snap`)."""
    from motok.gpt.snap import snapping

    from motok.tokenizer.model import load_tokenizer

    run = Path(run)
    model, meta = load_gpt(run)
    ex = meta["extra"]
    tok_run = Path(tokenizer) if tokenizer is not None else bundle_ref(run, meta, "tokenizer",
                                                                       hint="; pass --tokenizer")
    tok_model, tok_meta = load_tokenizer(tok_run)
    if tok_meta["model_sha256"] != ex["tokenizer_sha256"] and not allow_mismatch:
        raise error(f"{tok_run} is not the tokenizer {run} was trained with (sha256 {tok_meta['model_sha256'][:12]} "
                    f"vs {ex['tokenizer_sha256'][:12]}); pass --tokenizer or --allow-mismatch")
    from motok.tokenizer.tokens import check_codes_fit
    check_codes_fit(tok_model, tok_run, run, int(ex["codebook_size"]), int(ex["rate"]), int(ex.get("codebook", 0)) + 1,
                    error=error)
    # A missing cache only costs encoding the texts again.
    cache = TextEmbeddingCache(bundle_ref(run, meta, "text_cache", required=False))
    k = int(meta["config"].get("snap", 0) if snap is None else snap)
    if k < 0:
        raise error(f"--snap {k} must be >= 0 (0 = off)")
    return model, meta, tok_model, tok_meta, tok_run, snapping(cache, run, meta, k)


@dataclass(repr=False)
class Sampler:
    """A GPT run ready to sample: the model, the tokenizer that decodes its codes and the
    caption cache its texts are embedded through (snapping new sentences where the run does)."""

    run: Path
    model: MotionGPT
    meta: dict
    tokenizer: "Tokenizer"
    cache: object  # TextEmbeddingCache, or the SnappingCache around it

    def __repr__(self) -> str:
        return (f"Sampler({str(self.run)!r}, text encoder {self.meta['extra']['text_encoder']!r}, "
                f"tokenizer {str(self.tokenizer.run)!r})")


def load_sampler(run: str | Path, tokenizer: str | Path | None = None, allow_mismatch: bool = False,
                 snap: int | None = None) -> Sampler:
    """:func:`load_for_sampling`, named by its parts."""
    from motok.tokenizer.tokens import Tokenizer

    model, meta, tok_model, tok_meta, tok_run, cache = load_for_sampling(run, tokenizer, allow_mismatch, snap=snap)
    return Sampler(Path(run), model, meta, Tokenizer(tok_run, tok_model, tok_meta), cache)


@dataclass
class Samples:
    """What :func:`sample_clips` made: one decoded clip per (text, sample), in that order, with
    its codes, and the settings that made them (the provenance of a written file)."""

    clips: list  # motok.data.dataset.Clip, on the tokenizer's skeleton at its frame rate
    codes: list[torch.Tensor]  # per clip, (L,) code indices without End
    config: dict  # texts, seeds, filtering, target tokens, guidance, snapped sentences
    truncated: list[dict]  # texts cut off by the text encoder's window: {"text": 1-based index, "tokens": n}
    times: dict  # seconds spent embedding texts, generating and decoding


def sample_clips(s: Sampler, texts: list[str], *, num_samples: int = 1, seed: int = 0, temperature: float = 1.0,
                 top_k: int | None = None, top_p: float | None = None, argmax: bool = False,
                 seconds: float | None = None, guidance: float | None = None, batch_size: int = 64) -> Samples:
    """Sample ``num_samples`` motions per text in memory (sample ``j`` seeded ``seed + j``) and
    decode them with the tokenizer; the work of ``motok gpt sample`` without its files."""
    model, ex, tok = s.model, s.meta["extra"], s.tokenizer
    texts = list(texts)
    check_sampling(texts, num_samples=num_samples, temperature=temperature, top_k=top_k, top_p=top_p, argmax=argmax,
                   seconds=seconds, codebook_size=int(ex["codebook_size"]))
    guidance = float(model.default_guidance if guidance is None else guidance)
    check_guidance(model, guidance)
    t0 = time.perf_counter()
    emb = torch.from_numpy(s.cache.embed(texts, ex["text_encoder"], write=False))
    truncated = [{"text": i + 1, "tokens": s.cache.truncated[t]} for i, t in enumerate(texts) if t in s.cache.truncated]
    for tr in truncated:  # printed even with --quiet: the motion answers another text than the one given
        _progress.console.print(f"[yellow]warning:[/] text {tr['text']} is {tr['tokens']} tokens long; the "
                       f"{ex['text_encoder']} text encoder reads only the first "
                       f"{get_encoder(ex['text_encoder']).window}, the rest was cut off")
    t_text = time.perf_counter()

    rate, fps = int(ex["rate"]), tok.fps
    target = None
    if seconds is not None:
        want = max(1, round(seconds * fps / rate))
        if want > model.max_codes:
            _progress.info(f"[yellow]note:[/] --seconds {seconds} needs {want} tokens; the model stops at "
                           f"{model.max_codes} ({model.max_codes * rate / fps:.1f} s)")
        target = min(want, model.max_codes)
    rows = [(i, j) for i in range(len(texts)) for j in range(num_samples)]
    codes: list[torch.Tensor] = []
    for a in range(0, len(rows), batch_size):
        chunk = rows[a:a + batch_size]
        tl = None if target is None else torch.full((len(chunk),), target)
        g = generate(model, emb[[i for i, _ in chunk]], target_len=tl, temperature=temperature, top_k=top_k,
                     top_p=top_p, argmax=argmax, seeds=[seed + j for _, j in chunk], guidance=guidance)
        codes += g.codes
    t_gen = time.perf_counter()

    skeleton = tok.skeleton
    clips = [tok.decode(sample_name(i, texts[i], j), c, 1, skeleton, split="none",
                        labels={"text": texts[i], "sample": j, "seed": seed + j, "codes": c.tolist()},
                        captions=[(texts[i], "", 0.0, 0.0)])
             for (i, j), c in zip(rows, codes)]
    snapped = getattr(s.cache, "snapped", {})
    cfg = {"texts": list(texts), "num_samples": num_samples, "seed": seed, "temperature": temperature,
           "top_k": top_k, "top_p": top_p, "argmax": argmax, "seconds": seconds, "target_tokens": target,
           "codebooks_decoded": 1, "guidance": guidance,
           "snapped": {t: c[0] for t, c in snapped.items() if t in texts}}
    times = {"text_s": t_text - t0, "generate_s": t_gen - t_text, "decode_s": time.perf_counter() - t_gen}
    return Samples(clips, codes, cfg, truncated, times)


def sample(run: str | Path, texts: list[str], out: str | Path, *, num_samples: int = 1, seed: int = 0,
           temperature: float = 1.0, top_k: int | None = None, top_p: float | None = None, argmax: bool = False,
           seconds: float | None = None, render: str | Path | None = None, bvh: str | Path | None = None,
           tokenizer: str | Path | None = None, allow_mismatch: bool = False, batch_size: int = 64,
           guidance: float | None = None, snap: int | None = None, command: str | None = None) -> dict:
    """Sample ``num_samples`` motions per text (:func:`sample_clips`), write them as one
    ``motion`` artifact ``out``, and optionally render GIFs/MP4s and BVHs (one per clip, numbered
    when there are several)."""
    from motok.render.stick import SUFFIXES

    texts = list(texts)
    opts = dict(num_samples=num_samples, temperature=temperature, top_k=top_k, top_p=top_p, argmax=argmax,
                seconds=seconds)
    check_sampling(texts, **opts)
    check_writable(out)
    if render is not None:
        check_writable(render, suffixes=SUFFIXES, what="--render")
    if bvh is not None:
        check_writable(bvh, what="--bvh")
    t0 = time.perf_counter()
    s = load_sampler(run, tokenizer, allow_mismatch, snap=snap)
    t_load = time.perf_counter()
    made = sample_clips(s, texts, **opts, seed=seed, guidance=guidance, batch_size=batch_size)
    tok, clips, codes = s.tokenizer, made.clips, made.codes
    t_dec0 = time.perf_counter()
    skeleton, offsets, fps = tok.skeleton, tok.offsets, tok.fps
    names = [c.name for c in clips]
    cfg = {"gpt": str(run), "tokenizer": str(tok.run), **made.config}
    prov = Provenance(command=command or command_line(), config=cfg,
                      inputs={str(Path(run) / "model.safetensors"): s.meta["model_sha256"],
                              str(tok.run / "model.safetensors"): tok.meta["model_sha256"]})
    write_motion(out, "motion", prov, clips, skeleton, offsets, fps, tok.legacy)
    t_dec = time.perf_counter()

    renders, bvhs = [], []
    if render is not None:
        from motok.render.clip import render_clip
        for k, c in enumerate(clips):
            renders.append(str(render_clip(c, skeleton, _numbered(Path(render), names, k), fps)))
    if bvh is not None:
        from motok.data.export import export_bvh
        for k, c in enumerate(clips):
            bvhs.append(str(export_bvh(_numbered(Path(bvh), names, k), c.joints, skeleton, offsets, fps)))
    rate = int(s.meta["extra"]["rate"])
    return {"output": str(out), "clips": len(clips), "names": names, "truncated": made.truncated,
            "tokens": [len(c) for c in codes], "seconds": [round(len(c) * rate / fps, 2) for c in codes],
            "render": renders, "bvh": bvhs, "time_load_s": round(t_load - t0 + made.times["text_s"], 2),
            "time_generate_s": round(made.times["generate_s"], 3),
            "time_decode_write_s": round(made.times["decode_s"] + t_dec - t_dec0, 3),
            "time_total_s": round(time.perf_counter() - t0, 2)}
