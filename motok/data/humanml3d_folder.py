"""HumanML3D's folder layout, both ways: ``motok export humanml3d`` writes a motion artifact as
the folder that HumanML3D's own scripts, T2M-GPT, MoMask and Guo et al.'s evaluator load, and
``motok preprocess -d FOLDER`` reads such a folder (one of ours, or HumanML3D itself) back into
a ``motion-dataset``::

    FOLDER/
      new_joint_vecs/NAME.npy   (T, 12J-1) float32 features
      new_joints/NAME.npy       (T, J, 3) float32 joints (what recover_from_ric gives back)
      texts/NAME.txt            caption#word/POS ...#start#end, one caption a line
      train.txt val.txt test.txt all.txt   clip names, one a line
      Mean.npy Std.npy          (12J-1,) float32: HumanML3D's cal_mean_variance over one split
      motok.json                what the layout cannot say (skeleton, bone offsets, fps, the
                                feature convention, labels and sources per clip, provenance);
                                the official loaders open named files only and never see it

Features are never recomputed on the way in or out, so a round trip gives back the same
features, joints, captions and splits. Local rotations are not part of the layout: the reader
derives them from the joints by inverse kinematics (motok's default convention).
"""

from __future__ import annotations

import json
import re
from fnmatch import fnmatchcase
from pathlib import Path

import numpy as np

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.atomic import atomic_folder, write_json
from motok.data.annotations import SPLITS, Annotations
from motok.data.bvh import MotionFormatError
from motok.data.dataset import NO_SPLIT, Clip, MotionFile, select_clips, write_motion
from motok.data.inputs import BadInput, check_inputs, labels_from_name, resolve_input
from motok.errors import UserError
from motok.features.humanml3d import mean_std, recover_from_ric, skeleton_offsets
from motok.features.kinematics import inverse_kinematics
from motok.progress import info, make_progress
from motok.skeleton import Skeleton, detect_skeleton, load_skeleton

FEATURES, JOINTS, TEXTS, SIDECAR = "new_joint_vecs", "new_joints", "texts", "motok.json"
FORMAT = "motok humanml3d folder"  # the sidecar's "format": what tells our folders from others
SCHEMA_VERSION = 1
# Official HumanML3D's own rate and feature convention, assumed for a folder without motok.json.
HUMANML3D_LEGACY = True
STATS_SPLITS = ("train", "all")


def is_humanml3d_folder(path) -> bool:
    """A folder in HumanML3D's layout: it has ``new_joint_vecs/``."""
    return Path(path).is_dir() and (Path(path) / FEATURES).is_dir()


# --------------------------------------------------------------------------- captions

def fallback_tokens(text: str) -> str:
    """``word/OTHER`` for each lower-cased word. The official loaders split every token at its
    ``/`` into a word (looked up in GloVe) and a part of speech, and OTHER is the part of speech
    they give words they do not know; motok has no tagger, so captions that came without
    tokens get this instead of HumanML3D's spaCy tags."""
    words = re.findall(r"[a-z0-9']+", text.lower())
    return " ".join(f"{w}/OTHER" for w in words) or "unk/OTHER"


def caption_line(text: str, tokens: str, start: float, end: float, where: str) -> str:
    """One line of ``texts/NAME.txt``: ``caption#tokens#start#end`` (seconds; 0 and 0: the whole clip)."""
    if any(c in text + tokens for c in "#\r\n"):
        raise UserError(f"{where}: caption {text!r} has a '#' or a line break, which the HumanML3D caption "
                        f"format (caption#tokens#start#end, one a line) cannot hold")
    return f"{text}#{tokens.strip() or fallback_tokens(text)}#{float(start)}#{float(end)}"


# --------------------------------------------------------------------------- export

def _file_name(name: str, data) -> str:
    if not name or name in (".", "..") or any(c in name for c in "/\\\0"):
        raise UserError(f"{data}: clip name {name!r} cannot be a file name in the HumanML3D layout")
    return name


def export_humanml3d(data, out, *, clips: str | None = None, stats: str = "train",
                     command: str | None = None) -> dict:
    """Write the clips of the motion artifact ``data`` (those matching the glob ``clips``) as a HumanML3D
    folder ``out`` (new, or empty), whole or not at all. ``stats``: the split ``Mean.npy`` and
    ``Std.npy`` are computed over, ``train`` (as motok's own statistics; all clips when none is
    in train) or ``all`` (every exported clip, as HumanML3D's script does over its folder)."""
    if stats not in STATS_SPLITS:
        raise UserError(f"--stats {stats!r}: choose one of {', '.join(STATS_SPLITS)}")
    names = select_clips(data, clips)
    out = Path(out)
    with MotionFile(data) as mf, atomic_folder(out) as tmp, make_progress("clips") as progress:
        J, sk = mf.skeleton.num_joints, mf.skeleton
        for sub in (FEATURES, JOINTS, TEXTS):
            (tmp / sub).mkdir()
        task = progress.add_task("export", total=len(names))
        per_clip, stat_rows, splits, captioned = {}, [], {s: [] for s in SPLITS}, 0
        for name in names:
            c = mf.clip(name)
            fname = _file_name(c.name, data)
            np.save(tmp / FEATURES / f"{fname}.npy", np.asarray(c.features, dtype=np.float32))
            np.save(tmp / JOINTS / f"{fname}.npy", np.asarray(c.joints, dtype=np.float32))
            if c.captions:
                lines = [caption_line(t, tok, s, e, f"{data}: clip {c.name!r}") for t, tok, s, e in c.captions]
                (tmp / TEXTS / f"{fname}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
                captioned += 1
            if c.split in splits:
                splits[c.split].append(c.name)
            if stats == "all" or c.split == "train":
                stat_rows.append(c.features)
            per_clip[c.name] = {"split": c.split, "labels": c.labels, "source": c.source, "source_fps": c.source_fps}
            progress.advance(task)
        stats_split = stats
        if not stat_rows:
            info("[yellow]no exported clip is in the train split: Mean.npy/Std.npy are over all of them[/]")
            stat_rows, stats_split = [mf.frames("features", n) for n in names], "all"
        mean, std = mean_std(stat_rows, J)
        np.save(tmp / "Mean.npy", mean)
        np.save(tmp / "Std.npy", std)
        for split, members in [*splits.items(), ("all", names)]:
            (tmp / f"{split}.txt").write_text("".join(n + "\n" for n in members), encoding="utf-8")
        if not captioned:
            (tmp / TEXTS).rmdir()  # no captions at all: the reader then gives every clip the split none
        prov = Provenance(command=command or command_line(),
                          config={"data": str(data), "clips": clips, "stats": stats}, inputs=hash_inputs([data]))
        write_json(tmp / SIDECAR, {
            "format": FORMAT, "schema_version": SCHEMA_VERSION, "kind": mf.kind, "skeleton": sk.to_dict(),
            "offsets": np.asarray(mf.offsets, dtype=float).tolist(), "fps": mf.fps, "legacy": mf.legacy,
            "feature_dim": 12 * J - 1, "stats_split": stats_split, "clips": per_clip,
            "provenance": json.loads(prov.to_json())})
    counts = {s: len(v) for s, v in splits.items()} | {"none": sum(v["split"] in NO_SPLIT for v in per_clip.values())}
    return {"output": str(out), "clips": len(names), "feature_dim": 12 * J - 1, "skeleton": sk.name,
            "fps": mf.fps, "splits": counts, "stats_split": stats_split, "captioned": captioned}


# --------------------------------------------------------------------------- import

def read_sidecar(folder: Path) -> dict | None:
    p = folder / SIDECAR
    if not p.exists():
        return None
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise MotionFormatError(str(p), f"not JSON ({e})") from None
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise MotionFormatError(str(p), f"not a motok sidecar (expected \"format\": \"{FORMAT}\")")
    if d.get("schema_version") != SCHEMA_VERSION:
        raise MotionFormatError(str(p), f"schema_version {d.get('schema_version')!r} is not {SCHEMA_VERSION}, the "
                                f"one this motok reads")
    return d


def _load_npy(path: Path, shape: tuple, what: str) -> np.ndarray:
    """A float array of ``shape`` (None: any length) with finite values, as float32."""
    try:
        a = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise MotionFormatError(str(path), f"not a readable .npy array ({e})") from None
    ok = isinstance(a, np.ndarray) and a.dtype.kind == "f" and a.ndim == len(shape) \
        and all(s is None or s == n for s, n in zip(shape, a.shape))
    if not ok:
        want = "(" + ", ".join("T" if s is None else str(s) for s in shape) + ")"
        raise MotionFormatError(str(path), f"expected {what} of shape {want}, found {getattr(a, 'dtype', '?')} "
                                f"{getattr(a, 'shape', '?')}")
    if not np.all(np.isfinite(a)):
        raise MotionFormatError(str(path), f"{what} contain NaN or infinity")
    return a.astype(np.float32)


def _skeleton(cfg, folder: Path, side: dict | None, dim: int) -> Skeleton:
    if cfg.skeleton:
        sk = load_skeleton(cfg.skeleton)
    elif side is not None:
        sk = Skeleton.from_dict(side["skeleton"], source=str(folder / SIDECAR))
    else:
        if (dim + 1) % 12:
            raise MotionFormatError(str(folder / FEATURES), f"features of {dim} dims are not HumanML3D's 12J-1")
        sk = detect_skeleton(num_joints=(dim + 1) // 12)
    if sk.feature_dim != dim:
        raise MotionFormatError(str(folder / FEATURES), f"features have {dim} dims; skeleton {sk.name!r} makes "
                                f"{sk.feature_dim}")
    return sk


def _stats(folder: Path, side: dict | None, dim: int):
    """Mean.npy and Std.npy as the folder has them, with the split they are over (HumanML3D's
    script takes every file of the folder, hence "all" without motok.json); None if absent."""
    if not ((folder / "Mean.npy").exists() and (folder / "Std.npy").exists()):
        return None
    mean = _load_npy(folder / "Mean.npy", (dim,), "feature means")
    std = _load_npy(folder / "Std.npy", (dim,), "feature standard deviations")
    if np.any(std <= 0):
        raise MotionFormatError(str(folder / "Std.npy"), f"standard deviation {std.min()} at dim {int(std.argmin())}; "
                                f"normalizing needs every one > 0")
    return mean, std, (side or {}).get("stats_split", "all")


def import_humanml3d(cfg, folder: Path, out, data_root=None, command: str | None = None) -> dict:
    """``motok preprocess -d FOLDER``: a HumanML3D folder to a ``motion-dataset``. Applies the
    preprocess config's ``clips``, ``limit``, ``annotations`` (``auto``: the folder's own
    ``texts/`` and split files), ``skeleton``, ``skip_bad``, ``reference_clip``, ``min_frames``;
    features are taken as they are, so ``fps`` must be the folder's rate (motok.json's, else
    ``npy_fps``, HumanML3D's 20). Everything is checked before the clips are read."""
    from motok.config import to_dict

    folder = Path(folder)
    side = read_sidecar(folder)
    if cfg.scale is not None:
        raise UserError(f"scale {cfg.scale}: a HumanML3D folder ({folder}) is in metres already; leave scale unset")
    fps = float(side["fps"]) if side else float(cfg.npy_fps)
    if abs(fps - cfg.fps) > 1e-6:
        said = f"its {SIDECAR} says" if side else "--npy-fps says (HumanML3D's is 20)"
        raise UserError(f"{folder}: the features are at {fps:g} fps ({said}) and cannot be resampled; "
                        f"give --fps {fps:g}")
    a = cfg.annotations
    if a is None or str(a).lower() == "none":
        ann_root = None
    elif str(a).lower() == "auto":
        ann_root = folder if (folder / TEXTS).is_dir() else None
    else:
        ann_root = resolve_input(str(a), data_root)
    ann = Annotations.load(ann_root) if ann_root is not None else None
    files = sorted((folder / FEATURES).glob("*.npy"))
    if not files:
        raise MotionFormatError(str(folder / FEATURES), "no .npy feature files")
    skipped: list[dict] = []

    def bad(b):
        if not cfg.skip_bad:
            raise b.error
        skipped.append({"input": b.origin, "error": b.reason()})

    total, captions, excluded = check_inputs(cfg, [folder / FEATURES], ann, bad)
    dim = _load_npy(files[0], (None, None), "features").shape[1]
    sk = _skeleton(cfg, folder, side, dim)
    J, per_clip = sk.num_joints, (side or {}).get("clips", {})
    split_of = ann.split_of() if ann is not None else {}
    clips: list[Clip] = []
    with make_progress("clips") as progress:
        task = progress.add_task("read", total=total)
        for f in [f for f in files if fnmatchcase(f.stem, cfg.clips)][:cfg.limit]:
            progress.advance(task)
            if f.stem in excluded:
                continue
            try:
                clips.append(_read_clip(folder, f, sk, dim, cfg, fps, per_clip.get(f.stem, {}),
                                        split_of.get(f.stem, "none"), captions.get(f.stem, [])))
            except MotionFormatError as e:
                bad(BadInput(str(f), e))
    if not clips:
        first = f"; the first bad one: {skipped[0]['input']}: {skipped[0]['error']}" if skipped else ""
        raise MotionFormatError(str(folder / FEATURES), f"no clip matching {cfg.clips!r} could be read{first}")
    if side is not None and cfg.reference_clip is None:
        offsets = np.asarray(side["offsets"], dtype=np.float64)
    else:
        ref = cfg.reference_clip or next((c.name for c in clips if c.split == "train"), clips[0].name)
        offsets = skeleton_offsets(next(c for c in clips if c.name == ref).joints[0].astype(np.float64), sk)
    st = _stats(folder, side, dim)
    stats_from = "Mean.npy, Std.npy"
    if st is None:
        train = [c.features for c in clips if c.split == "train"]
        st = (*mean_std(train or [c.features for c in clips], J), "train" if train else "all")
        stats_from = f"computed over {st[2]}"
    legacy = bool(side["legacy"]) if side else HUMANML3D_LEGACY
    prov = Provenance(command=command or command_line(), config=to_dict(cfg),
                      inputs=hash_inputs([folder] + ([ann.root] if ann and ann.root != folder else [])),
                      skipped=skipped)
    write_motion(out, "motion-dataset", prov, clips, sk, offsets, fps, legacy, stats=st)
    counts = {s: sum(c.split == s for c in clips) for s in ("train", "val", "test", "none")}
    return {"output": str(out), "clips": len(clips), "frames": int(sum(c.num_frames for c in clips)), "fps": fps,
            "skeleton": sk.name, "feature_dim": dim, "legacy": legacy, "annotations": str(ann_root) if ann else None,
            "splits": counts, "statistics": stats_from, "stats_split": st[2], "skipped": skipped}


def _read_clip(folder: Path, f: Path, sk: Skeleton, dim: int, cfg, fps: float, meta: dict, split: str,
               captions: list) -> Clip:
    feats = _load_npy(f, (None, dim), "features")
    if len(feats) < max(cfg.min_frames - 1, 1):
        raise MotionFormatError(str(f), f"{len(feats)} frame(s); at least {cfg.min_frames - 1} are needed")
    jp = folder / JOINTS / f.name
    if jp.exists():
        joints = _load_npy(jp, (len(feats), sk.num_joints, 3), "joint positions")
    else:  # HumanML3D's new_joints are recover_from_ric of the features; some copies ship without them
        joints = recover_from_ric(feats, sk.num_joints).astype(np.float32)
    quats = inverse_kinematics(joints, sk, smooth_forward=True).astype(np.float32)
    return Clip(f.stem, feats, joints, quats, joints[:, 0].copy(), source=meta.get("source", str(f)),
                source_fps=float(meta.get("source_fps", fps)), split=split,
                labels=meta.get("labels", labels_from_name(f.stem)), captions=captions)
