"""``motok preprocess``: mocap (BVH or joint-position arrays) to a ``motion-dataset`` artifact.

Two passes. Pass 1 streams the inputs (archives are read without extracting), parses each
clip, resamples it to the target fps (local rotations by slerp, translations linearly) and
runs forward kinematics to joint positions in metres. Pass 2 takes the target skeleton from
a reference clip's frame-0 bone lengths and extracts the HumanML3D features of every clip
(``motok.features.humanml3d``). Both passes fan out over ``jobs`` worker processes.
Nothing is written unless the whole run succeeds; with ``skip_bad`` bad clips are listed in
the artifact's provenance instead of stopping the run.

A folder in HumanML3D's layout (``new_joint_vecs/``, ``texts/``, split files, ``Mean.npy``) is
read as it is, features and all (``motok.data.humanml3d_folder``).

Captions and splits come from ``annotations``. By default (``auto``) only the default data set
gets its own: inputs that all lie in the data root's ``bandai-namco/`` folder use
``bandai-namco/annotations``; any other input (your own BVH or joint arrays) gets no captions
and the split ``none`` unless an annotations folder is named.
"""

from __future__ import annotations

import dataclasses
import math
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from multiprocessing import get_context
from pathlib import Path
from typing import ClassVar

import numpy as np

from motok import ranges
from motok.artifacts import Provenance, command_line, hash_inputs
from motok.atomic import check_writable
from motok.data.annotations import Annotations
from motok.data.bvh import MotionFormatError, parse_bvh
from motok.data.dataset import Clip, write_motion
from motok.data.inputs import BadInput, check_inputs, labels_from_name, resolve_annotations, resolve_input
from motok.data.sources import MotionSource, check_readable, iter_sources, load_npy_positions
from motok.errors import MissingFileError, UnknownNameError, UserError
from motok.features.humanml3d import (extract_features, mean_std, resample_positions, resample_quats,
                                      skeleton_offsets)
from motok.progress import info, make_progress
from motok.ranges import In
from motok.skeleton import Skeleton, SkeletonError, detect_skeleton, load_skeleton
from motok.workers import die_with_parent


@dataclass
class PreprocessConfig:
    # Keys are named as the options that set them (-d/--data, --clips).
    RENAMED_KEYS: ClassVar[dict[str, str]] = {"inputs": "data", "pattern": "clips"}
    # Inputs (-d): BVH or .npy files, folders, archives (.zip, .tar.*) or one HumanML3D-layout
    # folder; a relative path that does not exist here is taken relative to the data root.
    data: list[str] = field(default_factory=lambda: ["bandai-namco/bandai-namco-2.tar.xz"])
    # "auto": the Bandai-Namco annotations for Bandai-Namco inputs only; "none" (or None): no
    # captions, split "none"; else a HumanML3D-layout folder (relative to the data root or not).
    annotations: str | None = "auto"
    clips: str = "*"  # clip-name glob; also decides which split entries must be present
    skeleton: str | None = None  # built-in name or YAML path; None: detect from joint names
    fps: In[float, "> 0"] = 20.0  # target frame rate every clip is resampled to (HumanML3D: 20)
    # The frame rate of .npy joint arrays, which store none (HumanML3D's new_joints are 20 fps);
    # they are resampled from it to ``fps``. A note says which rate was assumed.
    npy_fps: In[float, "> 0"] = 20.0
    scale: In[float | None, "> 0"] = None  # source units to metres; None: guess from the leg length
    legacy: bool = False  # reproduce the official HumanML3D numbers, quirks included (docs/features.md)
    reference_clip: str | None = None  # target bone lengths; None: first train clip by name
    skip_bad: bool = False  # list bad clips in the artifact's provenance and go on, instead of stopping at one
    jobs: In[int, ">= 1"] = 1  # worker processes for parsing and feature extraction
    limit: In[int | None, ">= 1"] = None  # keep the first N matching clips (smoke runs); skips the split check
    min_frames: In[int, ">= 2"] = 4  # at the target fps, after resampling (features are frame differences)


@dataclass
class _Loaded:
    name: str
    origin: str
    source_fps: float
    source_frames: int
    positions: np.ndarray  # (T, J, 3) metres at the target fps
    labels: dict


def check_config(cfg: PreprocessConfig) -> PreprocessConfig:
    """Refuse values that would fail late or mean nothing, before any input is read."""
    problems = ranges.check_config(cfg)  # a config made in code, not by load_config, is checked too
    if not cfg.data:
        problems.append("no data (-d/--data: mocap files, folders or archives)")
    if problems:
        raise UserError("; ".join(problems))
    return cfg


def snap_fps(fps: float) -> float:
    """BVH frame times are printed with few digits (0.0333333 s is 30.00003 fps); a rate within
    1e-4 relative of a whole number is that number, or 30 -> 20 fps would lose a frame."""
    r = round(fps)
    return float(r) if r > 0 and abs(fps - r) < 1e-4 * r else float(fps)


def guess_scale(positions: np.ndarray, sk: Skeleton) -> float:
    """Source units to metres, judged from the leg (thigh + shin) length of frame 0."""
    legs = [np.linalg.norm(positions[0, j] - positions[0, sk.parents[j]]) for j in sk.leg_joints]
    leg = float(sum(legs))
    if leg > 300:  # millimetres
        return 0.001
    if leg > 3:  # centimetres (an adult leg is about 80 cm)
        return 0.01
    return 1.0


def _load(src: MotionSource, skeleton: Skeleton | None, cfg: PreprocessConfig) -> tuple[_Loaded, Skeleton]:
    """Pass 1 for one clip: parse, resample to cfg.fps, FK to positions in metres."""
    if src.kind == "bvh":
        m = parse_bvh(src.data, src.origin)
        sk = skeleton or detect_skeleton(joint_names=m.names)
        missing = [n for n in sk.joints if n not in m.names]
        if missing:
            raise MotionFormatError(src.origin, f"joints {missing} of skeleton {sk.name!r} are not in the file")
        src_fps, n_src = snap_fps(m.fps), m.num_frames
        if n_src == 0:  # a valid BVH (a skeleton in its rest pose), but nothing to preprocess
            raise MotionFormatError(src.origin, "'Frames: 0': the file has a skeleton but no motion")
        if abs(src_fps - cfg.fps) > 1e-6:
            m = dataclasses.replace(m, rotations=resample_quats(m.rotations, src_fps, cfg.fps),
                                    translations=resample_positions(m.translations, src_fps, cfg.fps),
                                    frame_time=1.0 / cfg.fps)
        pos = m.global_positions()[:, [m.names.index(n) for n in sk.joints]]
    else:
        pos = load_npy_positions(src.data, src.origin)
        sk = skeleton or detect_skeleton(num_joints=pos.shape[1])
        if pos.shape[1] != sk.num_joints:
            raise MotionFormatError(src.origin, f"array has {pos.shape[1]} joints, skeleton {sk.name!r} has "
                                    f"{sk.num_joints}")
        src_fps, n_src = cfg.npy_fps, len(pos)
        if abs(src_fps - cfg.fps) > 1e-6:
            pos = resample_positions(pos, src_fps, cfg.fps)
    if not np.all(np.isfinite(pos)):
        raise MotionFormatError(src.origin, "joint positions contain NaN or infinity")
    if len(pos) < cfg.min_frames:
        raise MotionFormatError(src.origin, f"clip has {len(pos)} frame(s) at {cfg.fps:g} fps ({n_src} at the "
                                f"source's {src_fps:g}); at least {cfg.min_frames} are needed")
    scale = cfg.scale if cfg.scale is not None else guess_scale(pos, sk)
    pos = pos * scale
    return _Loaded(src.name, src.origin, float(src_fps), int(n_src), pos, labels_from_name(src.name)), sk


def _load_job(args):
    src, skeleton, cfg = args
    try:
        return _load(src, skeleton, cfg)
    except (MotionFormatError, SkeletonError, ValueError) as e:
        return BadInput(src.origin, e)


def _feature_job(args):
    origin, positions, sk, offsets, cfg = args
    try:
        return extract_features(positions, sk, target_offsets=offsets, fps=cfg.fps, legacy=cfg.legacy)
    except (ValueError, FloatingPointError) as e:
        return BadInput(origin, MotionFormatError(origin, f"feature extraction failed: {e}"))


def _pool(jobs: int):
    if jobs <= 1:
        return None
    # Workers die with this process, even by kill -9 (they would otherwise wait on their queue forever).
    return ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("fork"), initializer=die_with_parent,
                               initargs=(os.getpid(),))


def readable(inputs: list[Path], bad) -> list[Path]:
    """The inputs whose archives open; each other one is ``bad`` (raised, or skipped and reported)."""
    kept = []
    for p in inputs:
        try:
            check_readable(p)
        except MotionFormatError as e:
            bad(BadInput(str(p), e))
            continue
        kept.append(p)
    return kept


def _map(pool, fn, items, progress, task):
    """Map in order, inline or over the pool, advancing the progress bar by one per item."""
    if pool is None:
        for it in items:
            out = fn(it)
            progress.advance(task)
            yield out
        return
    pending = []
    window = 16
    for it in items:
        pending.append(pool.submit(fn, it))
        while len(pending) > window:
            out = pending.pop(0).result()
            progress.advance(task)
            yield out
    for fut in pending:
        out = fut.result()
        progress.advance(task)
        yield out


def preprocess(cfg: PreprocessConfig, out: str | Path, data_root: str | Path | None = None,
               command: str | None = None) -> dict:
    """Run the whole preprocessing; returns a summary dict (also stored in provenance)."""
    check_config(cfg)
    check_writable(out)
    inputs = [resolve_input(p, data_root) for p in cfg.data]
    for p in inputs:
        if not p.exists():
            raise MissingFileError(f"input {p} does not exist")
    from motok.data.humanml3d_folder import FEATURES, import_humanml3d, is_humanml3d_folder
    folders = [p for p in inputs if is_humanml3d_folder(p)]
    if folders:  # features already made: read, not recomputed
        if len(inputs) > 1:
            raise UserError(f"{folders[0]} is a HumanML3D folder ({FEATURES}/): read it on its own, as the only -d")
        return import_humanml3d(cfg, folders[0], out, data_root, command)
    ann_root = resolve_annotations(cfg, inputs, data_root)
    ann = Annotations.load(ann_root) if ann_root is not None else None
    skeleton = load_skeleton(cfg.skeleton) if cfg.skeleton else None
    skipped: list[dict] = []

    def bad(b: BadInput):
        if not cfg.skip_bad:
            raise b.error
        skipped.append({"input": b.origin, "error": b.reason()})

    def nothing_left(stage: str):
        where = ", ".join(map(str, inputs))
        if skipped:  # --skip-bad dropped everything: say why, not only that nothing is left
            first = skipped[0]
            raise MotionFormatError(where, f"all {len(skipped)} clip(s) matching {cfg.clips!r} were bad ({stage}); "
                                    f"the first: {first['input']}: {first['error']}")
        raise MotionFormatError(where, f"no clip matching {cfg.clips!r} could be loaded")

    # Everything that can be known before a clip is parsed is checked now, not after minutes of work.
    inputs = readable(inputs, bad)
    if not inputs:
        nothing_left("opening the inputs")
    broken: set[str] = set()  # archives found damaged while listing or streaming them (skip_bad)
    total, captions, excluded = check_inputs(cfg, inputs, ann, bad, broken)

    def selected():
        n = 0
        for path in (p for p in inputs if str(p) not in broken):
            try:
                for src in iter_sources(path):
                    if not fnmatchcase(src.name, cfg.clips):
                        continue
                    if cfg.limit is not None and n >= cfg.limit:
                        return
                    n += 1
                    if src.name not in excluded:
                        yield src
            except MotionFormatError as e:
                if e.source != str(path):
                    raise
                bad(BadInput(str(path), e))  # the archive itself: its clips go with it
                broken.add(str(path))

    loaded: list[_Loaded] = []
    pool = _pool(cfg.jobs)
    try:
        with make_progress("clips") as progress:
            task = progress.add_task("parse", total=total)
            gen = ((s, skeleton, cfg) for s in selected())
            for res in _map(pool, _load_job, gen, progress, task):
                if isinstance(res, BadInput):
                    bad(res)
                    continue
                clip, sk = res
                if skeleton is None:
                    skeleton = sk
                elif sk.name != skeleton.name:
                    bad(BadInput(clip.origin, SkeletonError(f"{clip.origin}: skeleton {sk.name!r} differs from "
                                                        f"{skeleton.name!r} of earlier clips")))
                    continue
                loaded.append(clip)
            loaded = [c for c in loaded if not any(c.origin.startswith(b + ":") for b in broken)]
            if not loaded:
                nothing_left("reading")
            loaded.sort(key=lambda c: c.name)
            names = [c.name for c in loaded]
            if len(set(names)) != len(names):
                dup = sorted({n for n in names if names.count(n) > 1})[:5]
                raise MotionFormatError(", ".join(map(str, inputs)), f"clip names occur twice: {dup}")

            split_of = ann.split_of() if ann is not None else {}
            if any(c.origin.lower().endswith(".npy") for c in loaded):
                info(f".npy joint arrays carry no frame rate: read as {cfg.npy_fps:g} fps (--npy-fps)")

            ref = cfg.reference_clip or next((c.name for c in loaded if split_of.get(c.name) == "train"),
                                             loaded[0].name)
            ref_clip = next((c for c in loaded if c.name == ref), None)
            if ref_clip is None:
                raise UnknownNameError(f"reference_clip {ref!r} is not among the loaded clips")
            offsets = skeleton_offsets(ref_clip.positions[0], skeleton)

            task2 = progress.add_task("features", total=len(loaded))
            jobs = ((c.origin, c.positions, skeleton, offsets, cfg) for c in loaded)
            clips: list[Clip] = []
            for c, res in zip(loaded, _map(pool, _feature_job, jobs, progress, task2)):
                if isinstance(res, BadInput):
                    bad(res)
                    continue
                clips.append(Clip(c.name, res.features, res.joints, res.local_quats, res.root_translation,
                                  source=c.origin, source_fps=c.source_fps, split=split_of.get(c.name, "none"),
                                  labels=c.labels, captions=captions.get(c.name, [])))
            if not clips:
                nothing_left("features")
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)

    train = [c for c in clips if c.split == "train"]
    stats_split = "train" if train else "all"
    if ann is None:
        info("no annotations: no captions, every clip in split 'none', statistics over all clips "
             "(--annotations DIR adds captions and splits)")
    elif not train:
        info("[yellow]no clip is in the train split: statistics are over all clips[/]")
    mean, std = mean_std(np.concatenate([c.features for c in (train or clips)]), skeleton.num_joints)

    from motok.config import to_dict
    prov = Provenance(command=command or command_line(), config=to_dict(cfg),
                      inputs=hash_inputs(inputs + ([ann.root] if ann else [])), skipped=skipped)
    write_motion(out, "motion-dataset", prov, clips, skeleton, offsets, cfg.fps, cfg.legacy,
                 stats=(mean, std, stats_split))
    counts = {s: sum(c.split == s for c in clips) for s in ("train", "val", "test", "none")}
    return {
        "output": str(out), "clips": len(clips), "frames": int(sum(c.num_frames for c in clips)),
        "source_frames": int(sum(c.source_frames for c in loaded)),
        "fps": cfg.fps, "skeleton": skeleton.name, "feature_dim": skeleton.feature_dim,
        "reference_clip": ref, "annotations": str(ann_root) if ann_root else None, "splits": counts,
        "skipped": skipped,
    }
