"""The text-to-motion protocol of Guo et al. (CVPR 2022) as T2M-GPT (Zhang et al. 2023, Table 1)
reports it, on any motion-dataset with a motok evaluator (``motok eval t2m``).

Rows: real motion, tokenizer reconstruction, generation (a GPT with predicted or ground-truth
length, or any ``motion`` artifact). Each row is measured ``repeats`` times (20) against the real
motion of the split; a repeat draws, as the reference evaluation loader does, one caption per clip
and a crop of each clip to a multiple of 4 frames (one unit shorter with probability 1/3, at a
random offset), then R-precision/MM-Dist in shuffled batches of 32, FID against that repeat's
real crops, Diversity over 300 pairs and, where several samples per caption exist, MModality.
Mean and 95% CI per metric; the physical metrics (:mod:`motok.eval.physical`) are deterministic
and reported once per row.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from motok import progress as _progress
from motok.data.dataset import MotionFile
from motok.eval import metrics as M
from motok.eval.evaluator import UNIT, EvaluatorError, LoadedEvaluator, load_evaluator, load_split
from motok.eval.physical import PhysicalSums, clip_sums
from motok.features.humanml3d import recover_from_ric


@dataclass
class T2MConfig:
    split: str = "test"
    repeats: int = 20
    batch: int = 32  # R-precision batch: 1 true caption and 31 others
    top_k: int = 3
    diversity_times: int = 300
    mm_pairs: int = 10  # MModality pairs per caption (reference: 10 of 30 samples)
    unit_crop: bool = True  # the reference loader's crop to a multiple of 4 frames
    seed: int = 0
    physical: bool = True
    # Generation with --gpt: sets of one sample per clip (the protocol regenerates every repeat:
    # gen_sets = repeats; fewer sets are reused in turn) and the MModality samples.
    gen_sets: int = 20
    gt_length: bool = False  # target the ground-truth length instead of stopping at End
    mm_captions: int = 100
    mm_samples: int = 30
    temperature: float = 1.0
    top_k_sampling: int | None = None
    top_p: float | None = None
    gen_batch: int = 64
    threads: int = 1  # torch threads (one is fastest on a shared 2-core machine)


@dataclass
class MotionSet:
    """One row's motions: raw features per clip, each clip's captions, and how repeats use them."""
    name: str
    clips: list[np.ndarray]
    captions: list[list[str]]
    sample: np.ndarray | None = None  # per clip; repeat r uses the clips with sample == r mod (max + 1)
    mm_groups: list[list[int]] = field(default_factory=list)  # clip indices generated for one caption
    mm_clips: list[np.ndarray] = field(default_factory=list)
    joints: list[np.ndarray] | None = None  # for the physical metrics (else recovered from features)
    extra: dict = field(default_factory=dict)

    def for_repeat(self, r: int) -> list[int]:
        if self.sample is None:
            return list(range(len(self.clips)))
        return list(np.flatnonzero(self.sample == r % (int(self.sample.max()) + 1)))


def unit_crop(n: int, rng: np.random.Generator) -> tuple[int, int]:
    """The reference evaluation crop: length a multiple of 4, one unit less 1 time in 3, random start."""
    if n < 2 * UNIT:
        return 0, n
    m = (n // UNIT - int(rng.random() < 1 / 3)) * UNIT
    return int(rng.integers(0, n - m + 1)), m


class Embedder:
    """Motion embeddings of crops, cached: a crop recurs across repeats (few offsets per clip)."""

    def __init__(self, ev: LoadedEvaluator):
        self.ev, self.cache = ev, {}

    def __call__(self, key: str, clips: list[np.ndarray], idx: list[int], rng, crop: bool) -> np.ndarray:
        spans = [unit_crop(len(clips[i]), rng) if crop else (0, len(clips[i])) for i in idx]
        keys = [(key, i, s, m) for i, (s, m) in zip(idx, spans)]
        todo = [k for k in dict.fromkeys(keys) if k not in self.cache]
        if todo:
            vecs = self.ev.motions([clips[i][s:s + m] for _, i, s, m in todo])
            self.cache.update(zip(todo, vecs))
        return np.stack([self.cache[k] for k in keys])


def physical_of(ms: MotionSet, fps: float, feet) -> dict:
    tot = PhysicalSums()
    for k, c in enumerate(ms.clips):
        j = ms.joints[k] if ms.joints is not None else recover_from_ric(np.asarray(c, np.float64), ms.extra["num_joints"])
        tot.add(clip_sums(j, fps, feet))
    return tot.result()


def evaluate_rows(ev: LoadedEvaluator, ref: MotionSet, rows: list[MotionSet], cfg: T2MConfig) -> list[dict]:
    """Every row against the reference (real motion of the split), ``cfg.repeats`` times."""
    emb = Embedder(ev)
    per_row = [{} for _ in rows]
    with _progress.make_progress("repeats") as bar:
        task = bar.add_task("t2m", total=cfg.repeats * len(rows))
        for r in range(cfg.repeats):
            rng = np.random.default_rng([cfg.seed, r])
            ref_emb = emb("real", ref.clips, list(range(len(ref.clips))), rng, cfg.unit_crop)
            for k, row in enumerate(rows):
                rrng = np.random.default_rng([cfg.seed, r, k + 1])
                idx = row.for_repeat(r)
                if len(idx) < 2:
                    raise EvaluatorError(f"row {row.name}: {len(idx)} motion(s) in repeat {r}; need 2+")
                key = "real" if row is ref else f"row{k}"  # the real row shares the reference's crops
                m = emb(key, row.clips, idx, rrng, cfg.unit_crop)
                caps = [row.captions[i][rrng.integers(len(row.captions[i]))] for i in idx]
                t = ev.texts(caps)
                rp, mmd = M.r_precision(t, m, rrng, cfg.batch, cfg.top_k)
                vals = {f"R@{j + 1}": float(rp[j]) for j in range(cfg.top_k)}
                vals.update({"FID": M.fid(ref_emb, m), "MM-Dist": mmd,
                             "Diversity": M.diversity(m, rrng, cfg.diversity_times)})
                if row.mm_groups:
                    g = emb(f"row{k}/mm", row.mm_clips, list(range(len(row.mm_clips))), rrng, cfg.unit_crop)
                    vals["MModality"] = M.multimodality([g[ix] for ix in row.mm_groups], rrng, cfg.mm_pairs)
                for name, v in vals.items():
                    per_row[k].setdefault(name, []).append(v)
                bar.advance(task)
    out = []
    for row, vals in zip(rows, per_row):
        res = {"name": row.name, "motions": len(row.for_repeat(0)),
               "metrics": {n: dict(zip(("mean", "ci"), M.mean_ci(v))) for n, v in vals.items()},
               "repeats": {n: v for n, v in vals.items()}, **row.extra}
        if row.mm_groups:
            res["mmodality_counts"] = {"captions": len(row.mm_groups),
                                       "samples_per_caption": int(np.median([len(g) for g in row.mm_groups])),
                                       "pairs_per_caption": cfg.mm_pairs}
        out.append(res)
    return out


# --------------------------------------------------------------------------- row sources

def real_set(data: Path, split: str) -> tuple[MotionSet, dict]:
    with MotionFile(data, "motion-dataset") as mf:
        sd = load_split(mf, split)
        if len(sd.clips) < 2:
            raise KeyError(f"{data}: split {split!r} has {len(sd.clips)} captioned clip(s) (splits: {sorted(set(mf.splits))})")
        idx = [mf.index(n) for n in sd.names]
        joints = [mf.frames("joints", i) for i in idx]
        sk = mf.skeleton
        info = {"fps": mf.fps, "feet": (tuple(sk.feet_left), tuple(sk.feet_right)), "num_joints": sk.num_joints,
                "names": sd.names, "labels": sd.labels}
    return MotionSet("real motion", sd.clips, sd.captions, joints=joints, extra={"num_joints": sk.num_joints}), info


def recon_set(ref: MotionSet, tokenizer: Path, num_joints: int, num_codebooks: int | None = None) -> MotionSet:
    """Every clip through the tokenizer (cut to a multiple of its rate, as ``tokenize eval``)."""
    import torch

    from motok.tokenizer.train import load_tokenizer
    model, meta = load_tokenizer(tokenizer)
    m = num_codebooks or model.num_codebooks
    clips, caps, err = [], [], {"mpjpe": [], "mpjpe_global": [], "accel": []}
    with torch.no_grad():
        for c, cap, j in zip(ref.clips, ref.captions, ref.joints):
            T = len(c) // model.rate * model.rate
            if T < UNIT:
                continue
            codes = model.encode_features(torch.from_numpy(np.asarray(c[:T]))[None], m)[..., :m]
            pred = model.decode_features(codes, m)[0].numpy()
            clips.append(pred)
            caps.append(cap)
            pj = recover_from_ric(pred.astype(np.float64), num_joints)
            gj = recover_from_ric(np.asarray(c[:T], np.float64), num_joints)
            err["mpjpe"].append(M.mpjpe(pj, gj))
            err["mpjpe_global"].append(M.mpjpe(pj, gj, root_relative=False))
            err["accel"].append(M.acceleration_error(pj, gj))
    recon = {"mpjpe_mm": float(np.concatenate(err["mpjpe"]).mean()),
             "mpjpe_global_mm": float(np.concatenate(err["mpjpe_global"]).mean()),
             "accel_error_mm": float(np.concatenate(err["accel"]).mean())}
    return MotionSet(f"reconstruction ({Path(tokenizer).name})", clips, caps,
                     extra={"num_joints": num_joints, "recon": recon, "tokenizer": str(tokenizer),
                            "tokenizer_sha256": meta["model_sha256"]})


def motion_set(path: Path, name: str | None = None) -> MotionSet:
    """Any ``motion`` artifact. Clips labelled ``role: mm`` (or, without roles, several ``sample``
    labels per caption) feed MModality; ``sample`` labels spread the others over the repeats."""
    with MotionFile(path) as mf:
        sd = load_split(mf, None)
        if not sd.clips:
            raise KeyError(f"{path}: no clip has a caption; the t2m metrics need the text of every motion")
        idx = [mf.index(n) for n in sd.names]
        joints = [mf.frames("joints", i) for i in idx]
        J = mf.skeleton.num_joints
    labels = [json.loads(x) if x else {} for x in sd.labels]
    roles = [lab.get("role", "") for lab in labels]
    main = [k for k, r in enumerate(roles) if r != "mm"]
    mm = [k for k, r in enumerate(roles) if r == "mm"] if "mm" in roles else \
        [k for k in main if "sample" in labels[k]]
    groups: dict[tuple, list[int]] = {}
    for pos, k in enumerate(mm):
        # By source clip too: two clips with one caption text are still two MModality captions.
        groups.setdefault((labels[k].get("source"), labels[k].get("text", sd.captions[k][0])), []).append(pos)
    samples = [labels[k].get("sample") for k in main]
    sample = np.array(samples, dtype=np.int64) if all(s is not None for s in samples) else None
    return MotionSet(name or Path(path).stem, [sd.clips[k] for k in main], [sd.captions[k] for k in main],
                     sample=sample, mm_groups=[g for g in groups.values() if len(g) > 1],
                     mm_clips=[sd.clips[k] for k in mm], joints=[joints[k] for k in main],
                     extra={"num_joints": J, "motions_file": str(path)})


# --------------------------------------------------------------------------- the protocol

def t2m(evaluator: Path, data: Path, cfg: T2MConfig, tokenizer: Path | None = None, gpt: Path | None = None,
        motions: list[Path] = (), save_generated: Path | None = None, real: bool = True) -> dict:
    """Evaluate every requested row; returns the JSON-ready report."""
    import torch
    t0 = time.perf_counter()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    ev = load_evaluator(evaluator)
    ref, info = real_set(Path(data), cfg.split)
    ex = ev.meta["extra"]
    if int(ex["feature_dim"]) != ref.clips[0].shape[1]:
        raise EvaluatorError(f"{data} has {ref.clips[0].shape[1]}-d features; {evaluator} was trained on "
                             f"{ex['feature_dim']}-d ones")
    rows = [ref] if real else []
    if tokenizer is not None:
        rows.append(recon_set(ref, Path(tokenizer), info["num_joints"]))
    if gpt is not None:
        from motok.eval.generate import generated_set
        rows.append(generated_set(Path(gpt), tokenizer, ref, cfg, save_generated))
    rows += [motion_set(Path(p)) for p in motions]
    if not rows:
        raise EvaluatorError("nothing to evaluate: give --tokenizer, --gpt or --motions (or keep the real row)")
    results = evaluate_rows(ev, ref, rows, cfg)
    if cfg.physical:
        for res, row in zip(results, rows):
            res["physical"] = physical_of(row, info["fps"], info["feet"])
    return {"protocol": "Guo et al. 2022 / T2M-GPT Table 1", "config": dict(cfg.__dict__),
            "evaluator": str(evaluator), "evaluator_sha256": ev.meta.get("model_sha256"),
            "text_encoder": ev.meta["config"]["text_encoder"], "data": str(data), "split": cfg.split,
            "clips": len(ref.clips), "rows": results, "seconds": round(time.perf_counter() - t0, 1)}


COLUMNS = [("R@1", "R@1 ↑"), ("R@2", "R@2 ↑"), ("R@3", "R@3 ↑"), ("FID", "FID ↓"), ("MM-Dist", "MM-Dist ↓"),
           ("Diversity", "Diversity →"), ("MModality", "MModality ↑")]
PHYSICAL = [("skate_cm_s", "Skate cm/s"), ("penetration_cm", "Penetr. cm"), ("floating_cm", "Float cm"),
            ("jitter_m_s3", "Jitter m/s³")]


def _t2m_cells(res: dict) -> list[str]:
    cells = []
    for key, _ in COLUMNS:
        m = res["metrics"].get(key)
        # FID of unit-norm embeddings is small: one more digit keeps the real row readable.
        fmt = ".1e" if key == "FID" and m is not None and m["mean"] < 1e-3 else (".4f" if key == "FID" else ".3f")
        cells.append("-" if m is None else f"{m['mean']:{fmt}}±{m['ci']:{fmt}}")
    return cells


def _other_cells(res: dict) -> list[str]:
    phys = res.get("physical", {})
    cells = ["-" if k not in phys else f"{phys[k]:.2f}" for k, _ in PHYSICAL]
    recon = res.get("recon")
    return cells + ["-" if recon is None else f"{recon['mpjpe_mm']:.1f}"]


def _cells(res: dict) -> list[str]:
    return _t2m_cells(res) + _other_cells(res)


def headers() -> list[str]:
    return ["Motion"] + [h for _, h in COLUMNS] + [h for _, h in PHYSICAL] + ["MPJPE mm"]


def markdown(report: dict) -> str:
    """A table ready for docs/results.md (mean ± 95% CI over the repeats)."""
    h = headers()
    lines = ["| " + " | ".join(h) + " |", "|" + "---|" * len(h)]
    lines += ["| " + " | ".join([r["name"]] + _cells(r)) + " |" for r in report["rows"]]
    c = report["config"]
    lines.append("")
    lines.append(f"{report['split']} split of `{report['data']}`, {report['clips']} clips, {c['repeats']} repeats "
                 f"(mean ± 1.96 std/sqrt({c['repeats']})); evaluator `{report['evaluator']}` "
                 f"({report['text_encoder']} text encoder).")
    return "\n".join(lines)


def rich_table(report: dict):
    """Two rich tables (the T2M metrics, then physical and reconstruction) so each fits a terminal."""
    from rich.console import Group
    from rich.table import Table
    first = Table(title=f"t2m protocol: {report['split']} split, {report['config']['repeats']} repeats (mean ± 95% CI)")
    second = Table(title="physical plausibility and reconstruction")
    for table, names in ((first, [h for _, h in COLUMNS]), (second, [h for _, h in PHYSICAL] + ["MPJPE mm"])):
        table.add_column("Motion")
        for name in names:
            table.add_column(name, justify="right")
    for r in report["rows"]:
        first.add_row(r["name"], *_t2m_cells(r))
        second.add_row(r["name"], *_other_cells(r))
    return Group(first, second)


def recon(data: Path, split: str = "test", tokenizer: Path | None = None, motions: Path | None = None,
          num_codebooks: int | None = None) -> dict:
    """MPJPE (mm, root-relative and global) and acceleration error of a reconstruction: the split
    through ``tokenizer``, or the clips of a ``motion`` artifact matched to the data set by name
    (each pair cut to the shorter length: a tokenizer drops the frames past its last token)."""
    ref, info = real_set(Path(data), split)
    if tokenizer is not None:
        ms = recon_set(ref, Path(tokenizer), info["num_joints"], num_codebooks)
        return {"data": str(data), "split": split, "tokenizer": str(tokenizer), "clips": len(ms.clips),
                **ms.extra["recon"]}
    if motions is None:
        raise EvaluatorError("recon needs --tokenizer or --motions")
    by_name = dict(zip(info["names"], ref.joints))
    errs = {"mpjpe": [], "mpjpe_global": [], "accel": []}
    with MotionFile(motions) as mf:
        pairs = [(i, by_name[n]) for i, n in enumerate(mf.names) if n in by_name]
        if not pairs:
            raise KeyError(f"{motions}: no clip named like a {split} clip of {data} (first: {mf.names[:3]})")
        for i, gt in pairs:
            pred = mf.frames("joints", i)
            T = min(len(pred), len(gt))
            errs["mpjpe"].append(M.mpjpe(pred[:T], gt[:T]))
            errs["mpjpe_global"].append(M.mpjpe(pred[:T], gt[:T], root_relative=False))
            if T >= 3:
                errs["accel"].append(M.acceleration_error(pred[:T], gt[:T]))
    return {"data": str(data), "split": split, "motions": str(motions), "clips": len(pairs),
            "mpjpe_mm": float(np.concatenate(errs["mpjpe"]).mean()),
            "mpjpe_global_mm": float(np.concatenate(errs["mpjpe_global"]).mean()),
            "accel_error_mm": float(np.concatenate(errs["accel"]).mean()) if errs["accel"] else float("nan")}
