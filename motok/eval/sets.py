"""Motion sets: the rows the T2M protocol (:mod:`motok.eval.protocol`) measures, read from
artifacts. The real motion of a split, a tokenizer's reconstruction of it, and any ``motion``
artifact (GPT samples from :mod:`motok.eval.generate` included) all become a
:class:`MotionSet`: raw features per clip, each clip's captions, and how repeats use them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from motok.data.dataset import NO_SPLIT, TRACKED_TO_END, MotionFile
from motok.eval import metrics as M
from motok.eval.evaluator import UNIT, EvaluatorError, load_split
from motok.features.humanml3d import recover_from_ric


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
    labels: list[str] | None = None  # per clip, canonical JSON of the dataset labels (real motion)
    mm_texts: list[str] = field(default_factory=list)  # the caption of each MModality group
    names: list[str] | None = None  # per clip, its name in the file it came from

    def for_repeat(self, r: int) -> list[int]:
        if self.sample is None:
            return list(range(len(self.clips)))
        return list(np.flatnonzero(self.sample == r % (int(self.sample.max()) + 1)))

    def subset(self, keep: list[int], **changes) -> MotionSet:
        """The clips ``keep`` (indices, in order) with everything per clip that goes with them;
        MModality clips and groups are left as they are unless ``changes`` says otherwise."""
        def pick(col):
            return None if col is None else [col[i] for i in keep]
        cols = {"clips": pick(self.clips), "captions": pick(self.captions), "joints": pick(self.joints),
                "labels": pick(self.labels), "names": pick(self.names),
                "sample": None if self.sample is None else self.sample[np.asarray(keep, dtype=np.int64)]}
        return replace(self, **{**cols, **changes})


def real_set(data: Path, split: str) -> tuple[MotionSet, dict]:
    """The captioned clips of ``split`` and what the other rows need of the dataset (fps, feet, names)."""
    with MotionFile(data, "motion-dataset") as mf:
        sd = load_split(mf, split)
        if len(sd.clips) < 2:
            raise EvaluatorError(f"{data}: split {split!r} has {len(sd.clips)} captioned clip(s) "
                                 f"(splits: {sorted(set(mf.splits))})")
        idx = [mf.index(n) for n in sd.names]
        joints = [mf.frames("joints", i) for i in idx]
        sk = mf.skeleton
        info = {"fps": mf.fps, "feet": (tuple(sk.feet_left), tuple(sk.feet_right)), "num_joints": sk.num_joints,
                "names": sd.names, "labels": sd.labels, "path": str(data), "joints": list(sk.joints),
                "legacy": mf.legacy, "feature_dim": int(mf.h5["frames/features"].shape[1])}
    return MotionSet("real motion", sd.clips, sd.captions, joints=joints, extra={"num_joints": sk.num_joints},
                     labels=sd.labels, names=list(sd.names)), info


def recon_set(ref: MotionSet, tokenizer: Path, info: dict, num_codebooks: int | None = None) -> MotionSet:
    """Every clip through the tokenizer (cut to a multiple of its rate, as ``tokenize eval``);
    ``info``: what :func:`real_set` says of the data, which the tokenizer must have been trained on
    the like of (feature width, frame rate, joints, convention)."""
    import torch

    from motok.tokenizer.model import load_tokenizer
    from motok.tokenizer.tokens import check_codebooks, check_motion
    model, meta = load_tokenizer(tokenizer)
    check_motion(meta, info["path"], info["feature_dim"], info["fps"], info["joints"], info["legacy"])
    m = check_codebooks(model, num_codebooks)
    num_joints = info["num_joints"]
    clips, caps, kept, err = [], [], [], {"mpjpe": [], "mpjpe_global": [], "accel": []}
    with torch.no_grad():
        for k, (c, cap, j) in enumerate(zip(ref.clips, ref.captions, ref.joints)):
            T = len(c) // model.rate * model.rate
            if T < UNIT:
                continue
            kept.append(k)
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
                     names=None if ref.names is None else [ref.names[k] for k in kept],
                     extra={"num_joints": num_joints, "recon": recon, "tokenizer": str(tokenizer),
                            "tokenizer_sha256": meta["model_sha256"]})


def motion_set(path: Path, name: str | None = None, split: str | None = None,
               tracked_to_end: bool = False) -> MotionSet:
    """Any ``motion`` artifact. Clips labelled ``role: mm`` (or, without roles, several ``sample``
    labels per caption) feed MModality; ``sample`` labels spread the others over the repeats.

    With ``split``, clips that carry another split are left out (a tracked dataset keeps its
    clips' splits); clips in no split (:data:`~motok.data.dataset.NO_SPLIT`: GPT samples) stay.
    With ``tracked_to_end``, so are the clips a tracking played only to its failure (their
    :data:`~motok.data.dataset.TRACKED_TO_END` label is false; clips without the label stay).
    How many were left out is in ``extra``."""
    with MotionFile(path) as mf:
        sd = load_split(mf, None)
        if not sd.clips:
            raise EvaluatorError(f"{path}: no clip has a caption; the t2m metrics need the text of every motion")
        idx = [mf.index(n) for n in sd.names]
        other = [k for k, i in enumerate(idx) if split and mf.splits[i] not in (*NO_SPLIT, split)]
        if other:
            if len(other) == len(idx):
                raise EvaluatorError(f"{path}: none of its {len(idx)} captioned clips is in split {split!r} "
                                     f"(its splits: {sorted(set(mf.splits[i] for i in idx))})")
            sd, idx, _ = _without(sd, idx, other)
        labels = [json.loads(x) if x else {} for x in sd.labels]
        tracked = sum(TRACKED_TO_END in lab for lab in labels)
        failed = [k for k, lab in enumerate(labels) if tracked_to_end and lab.get(TRACKED_TO_END) is False]
        if failed:
            if len(failed) == len(idx):
                raise EvaluatorError(f"{path}: none of its {len(idx)} captioned clips was tracked to the end")
            sd, idx, keep = _without(sd, idx, failed)
            labels = [labels[k] for k in keep]
        joints = [mf.frames("joints", i) for i in idx]
        J = mf.skeleton.num_joints
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
    multi = [(key[1], g) for key, g in groups.items() if len(g) > 1]
    return MotionSet(name or Path(path).stem, [sd.clips[k] for k in main], [sd.captions[k] for k in main],
                     sample=sample, mm_groups=[g for _, g in multi], mm_texts=[t for t, _ in multi],
                     mm_clips=[sd.clips[k] for k in mm], joints=[joints[k] for k in main],
                     names=[sd.names[k] for k in main],
                     extra={"num_joints": J, "motions_file": str(path),
                            **({"other_split_left_out": len(other)} if other else {}),
                            **({"tracked_clips": tracked} if tracked_to_end else {}),
                            **({"not_tracked_to_end_left_out": len(failed)} if failed else {})})


def _without(sd, idx: list[int], drop: list[int]) -> tuple:
    """A loaded split ``sd`` and its file indices ``idx`` without the positions ``drop``, and the kept positions."""
    gone = set(drop)
    keep = [k for k in range(len(idx)) if k not in gone]
    sd = type(sd)(*[[col[k] for k in keep] for col in (sd.clips, sd.captions, sd.labels, sd.names)])
    return sd, [idx[k] for k in keep], keep


def common_clips(rows: list[MotionSet]) -> list[MotionSet]:
    """Rows that hold clips of the same names (a tracked file and what it tracked, the real split
    and a tracked copy of it) each restricted to the names all of them hold, so that they are
    scored on the same clips: tracking writes no clip that fails at once, and keeps a failing one
    only to its failure. Rows are grouped by shared names, transitively; a row that shares no
    name keeps every clip. MModality clips are left as they are (it compares a row with itself).
    How many clips each row left out is in ``extra["common_clips_left_out"]``."""
    names = [set(r.names or ()) for r in rows]
    groups: list[list[int]] = []  # rows joined by shared names, transitively
    for i in range(len(rows)):
        touching = [g for g in groups if any(names[i] & names[j] for j in g)]
        groups = [g for g in groups if g not in touching] + [sum(touching, []) + [i]]
    shared = {i: set.intersection(*(names[j] for j in g)) for g in groups if len(g) > 1 for i in g}
    out = []
    for i, row in enumerate(rows):
        if i not in shared:
            out.append(row)
            continue
        keep = [k for k, n in enumerate(row.names) if n in shared[i]]
        if len(keep) < 2:
            raise EvaluatorError(f"{row.name}: {len(keep)} clip(s) in common with the rows that share its clip "
                                 f"names; --common-clips needs 2+")
        out.append(row.subset(keep, extra={**row.extra, "common_clips_left_out": len(row.clips) - len(keep)}))
    return out
