"""The generation row of the T2M protocol: sample a motok GPT for the captions of the
evaluation split, as T2M-GPT's evaluation does (``utils/eval_trans.py``: one motion per test
caption in every repeat, and 30 motions for each of 100 captions for MModality).

The samples are written as one ``motion`` artifact whose clip labels say what each is for
(``role`` t2m or mm, ``sample`` set, ``source`` clip, ``text``), so the same file can be rendered,
kept, and evaluated again with ``motok eval t2m --motions``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motok import progress as _progress
from motok.eval.evaluator import EvaluatorError
from motok.eval.protocol import T2MConfig
from motok.eval.sets import MotionSet, motion_set


def generated_set(gpt: Path, tokenizer: Path | None, ref: MotionSet, cfg: T2MConfig, out: Path | None,
                  command: str | None = None, fps: float | None = None) -> MotionSet:
    """Sample the GPT for the split's captions (``gen_sets`` sets of one motion per clip, caption drawn
    at random, plus ``mm_samples`` motions for each of ``mm_captions`` captions), write them as a
    ``motion`` artifact (``out``, kept for rendering and re-evaluation) and read it back as a row.
    ``fps``: the rate of the data and evaluator, which the GPT's tokenizer must share (checked first)."""
    import tempfile

    import torch

    from motok.artifacts import Provenance, command_line
    from motok.data.dataset import write_motion
    from motok.gpt.sample import generate, load_for_sampling
    from motok.skeleton import Skeleton
    from motok.tokenizer.tokens import features_to_clip

    model, meta, tok, tok_meta, tok_run, cache = load_for_sampling(gpt, tokenizer, error=EvaluatorError)
    ex = meta["extra"]
    tex, rate = tok_meta["extra"], int(ex["rate"])
    if fps is not None and abs(float(tex["fps"]) - fps) > 1e-6:
        raise EvaluatorError(f"{gpt} generates motion at {float(tex['fps']):g} fps (its tokenizer {tok_run}'s); the "
                             f"data and the evaluator are at {fps:g} fps")
    if int(tex["feature_dim"]) != ref.clips[0].shape[1]:
        raise EvaluatorError(f"{gpt} generates {tex['feature_dim']}-d features (its tokenizer {tok_run}'s); the data "
                             f"has {ref.clips[0].shape[1]}-d ones")
    rng = np.random.default_rng([cfg.seed, 7])
    jobs = []  # (text, target tokens or None, labels)
    for s in range(cfg.gen_sets):
        for i, caps in enumerate(ref.captions):
            text = caps[rng.integers(len(caps))]
            target = len(ref.clips[i]) // rate if cfg.gt_length else None
            jobs.append((text, target, {"role": "t2m", "sample": s, "source": i, "text": text}))
    picks = rng.choice(len(ref.captions), min(cfg.mm_captions, len(ref.captions)), replace=False)
    if cfg.mm_samples > 1:
        for i in picks:
            text = ref.captions[i][0]
            target = len(ref.clips[i]) // rate if cfg.gt_length else None
            jobs += [(text, target, {"role": "mm", "sample": k, "source": int(i), "text": text})
                     for k in range(cfg.mm_samples)]
    emb = torch.from_numpy(cache.embed(list(dict.fromkeys(j[0] for j in jobs)), ex["text_encoder"], write=False))
    row_of = {t: k for k, t in enumerate(dict.fromkeys(j[0] for j in jobs))}
    skeleton = Skeleton.from_dict(tex["skeleton"], source=f"{tok_run}/bundle.json")
    clips = []
    with _progress.make_progress("motions") as bar, torch.no_grad():
        task = bar.add_task("generate", total=len(jobs))
        for a in range(0, len(jobs), cfg.gen_batch):
            chunk = jobs[a:a + cfg.gen_batch]
            tl = torch.tensor([max(1, j[1]) for j in chunk]) if cfg.gt_length else None
            seeds = [cfg.seed * 1_000_003 + a + b for b in range(len(chunk))]
            g = generate(model, emb[[row_of[j[0]] for j in chunk]], target_len=tl, temperature=cfg.temperature,
                         top_k=cfg.top_k_sampling, top_p=cfg.top_p, seeds=seeds)
            for b, (text, _, lab) in enumerate(chunk):
                feats = tok.decode_features(g.codes[b].view(1, -1, 1), 1)[0].numpy()
                # the seed travels with the sample, so `gpt sample --closed-loop -d` redraws it exactly
                clips.append(features_to_clip(f"gen-{a + b:06d}", feats, skeleton, bool(tex["legacy"]),
                                              labels={**lab, "seed": seeds[b]}, captions=[(text, "", 0.0, 0.0)]))
            bar.advance(task, len(chunk))
    out = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="motok-eval-")) / "generated.h5"
    prov = Provenance(command=command or command_line(),
                      config={"gpt": str(gpt), "tokenizer": str(tok_run), "protocol": cfg.__dict__},
                      inputs={str(Path(gpt) / "model.safetensors"): meta["model_sha256"],
                              str(tok_run / "model.safetensors"): tok_meta["model_sha256"]})
    write_motion(out, "motion", prov, clips, skeleton, np.asarray(tex["offsets"], np.float32), float(tex["fps"]),
                 bool(tex["legacy"]))
    name = f"generation ({Path(gpt).name}, {'GT length' if cfg.gt_length else 'predicted length'})"
    ms = motion_set(out, name)
    ms.extra.update({"gpt": str(gpt), "gpt_sha256": meta["model_sha256"], "gt_length": cfg.gt_length,
                     "gpt_text_encoder": ex["text_encoder"]})
    return ms
