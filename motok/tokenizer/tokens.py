"""Motion <-> tokens with a trained tokenizer, the ``tokens`` artifact, and reconstruction metrics.

A token covers ``rate = 2**down_t`` frames (T2M-GPT Sec. 3.1: ``T/l`` codes for ``T`` frames),
so a clip of ``T`` frames is cut to its first ``T // rate * rate`` frames before encoding: the
trailing ``T mod rate`` frames (under 0.2 s at 20 fps) are dropped, never padded, so decoding
gives back exactly ``tokens * rate`` frames aligned with the source. ``clips/source_frames``
keeps ``T``. Layout in docs/tokenizer.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from motok import progress as _progress
from motok.artifacts import (ArtifactError, Provenance, command_line, hash_inputs, read_strings, write_artifact,
                             write_strings)
from motok.checkpoint import relative_to
from motok.data.dataset import Clip, ClipFile, MotionFile, write_motion
from motok.features.humanml3d import recover_from_ric, recover_local_quats
from motok.features.kinematics import acceleration_error, mpjpe
from motok.skeleton import Skeleton
from motok.tokenizer.model import VQVAE, TokenizerError, load_tokenizer

KIND = "tokens"


@dataclass(repr=False)
class Tokenizer:
    """A trained tokenizer with what its bundle says about the motion it reads and writes: the
    skeleton, rest offsets, frame rate and feature convention of its training data. Encoding and
    decoding here are the ones ``tokenize encode``, ``tokenize decode`` and ``gpt sample`` run."""

    run: Path
    model: VQVAE
    meta: dict

    def __repr__(self) -> str:
        q = self.model.quantizer
        return (f"Tokenizer({str(self.run)!r}, {q.num_codebooks} codebook(s) of {q.codebook_size} codes, "
                f"{self.rate} frames per code, {self.meta['extra']['num_joints']} joints at {self.fps:g} fps)")

    @property
    def skeleton(self) -> Skeleton:
        return Skeleton.from_dict(self.meta["extra"]["skeleton"], source=f"{self.run}/bundle.json")

    @property
    def offsets(self) -> np.ndarray:
        return np.asarray(self.meta["extra"]["offsets"], dtype=np.float32)

    @property
    def fps(self) -> float:
        return float(self.meta["extra"]["fps"])

    @property
    def legacy(self) -> bool:
        return bool(self.meta["extra"]["legacy"])

    @property
    def rate(self) -> int:
        """Frames per token."""
        return self.model.rate

    def encode(self, features: np.ndarray, num_codebooks: int) -> np.ndarray:
        """Raw features ``(T, D)`` -> codes ``(T // rate, num_codebooks)`` int32 (the trailing
        ``T mod rate`` frames dropped)."""
        idx = self.model.encode_features(torch.from_numpy(np.asarray(features))[None], num_codebooks)
        return idx[0, :, :num_codebooks].numpy().astype(np.int32)

    def decode(self, name: str, codes, num_codebooks: int, skeleton: Skeleton | None = None, **clip_fields) -> Clip:
        """Codes ``(L, N)`` (their first ``num_codebooks`` columns) -> a clip of ``L * rate``
        frames on the tokenizer's skeleton; ``clip_fields``: the clip's split, labels, captions."""
        idx = torch.as_tensor(np.asarray(codes), dtype=torch.int64).reshape(1, len(codes), -1)[:, :, :num_codebooks]
        feats = self.model.decode_features(idx, num_codebooks)[0].numpy()
        return features_to_clip(name, feats, skeleton or self.skeleton, self.legacy, **clip_fields)


def open_tokenizer(run: str | Path) -> Tokenizer:
    """The tokenizer run at ``run``, loaded for encoding and decoding (weights checked)."""
    model, meta = load_tokenizer(run)
    return Tokenizer(Path(run), model, meta)


def _tokenizer_id(run: Path, meta: dict, out: Path) -> dict:
    # Relative to the tokens file, as bundles store their references (motok.checkpoint).
    return {"tokenizer": relative_to(run, Path(out).parent), "tokenizer_sha256": meta["model_sha256"],
            "tokenizer_config": json.dumps(meta["config"], sort_keys=True)}


def check_codebooks(model, num_codebooks: int | None, codes: tuple | None = None) -> int:
    """The number of codebooks to use: ``num_codebooks`` (1 to the tokenizer's), else all of them;
    ``codes``: ``(where, columns)`` of codes to decode, which must hold that many codebooks too."""
    n = model.num_codebooks
    if num_codebooks is not None and not 1 <= num_codebooks <= n:
        raise TokenizerError(f"--codebooks {num_codebooks}: the tokenizer has {n} codebook(s)")
    if codes is not None and (num_codebooks or n) > codes[1]:
        raise TokenizerError(f"--codebooks {num_codebooks or n}: {codes[0]} has codes of {codes[1]} codebook(s) only")
    return num_codebooks or n


def check_codes_fit(model, run, codes_from, codebook_size: int, rate: int, codebooks: int = 1,
                    error: type[Exception] = ArtifactError) -> None:
    """Refuse a tokenizer (``run``, even one allowed to differ) that cannot decode the codes of
    ``codes_from``: codes of another codebook size (some past its codebook), another rate (a code
    would span another number of frames), or more codebooks than it has."""
    have = (int(model.quantizer.codebook_size), int(model.rate), int(model.num_codebooks))
    if have[0] != codebook_size or have[1] != rate or have[2] < codebooks:
        raise error(f"{run} decodes {have[2]} codebook(s) of {have[0]} codes, {have[1]} frames per code; the codes of "
                    f"{codes_from} need {codebooks}+ codebook(s) of {codebook_size} codes, {rate} frames per code")


def _check_data(mf: MotionFile, meta: dict) -> None:
    check_motion(meta, mf.path, int(mf.h5["frames/features"].shape[1]), mf.fps, mf.skeleton.joints, mf.legacy)


def check_motion(meta: dict, where, feature_dim: int, fps: float | None = None, joints=None,
                 legacy: bool | None = None) -> None:
    """Refuse motion unlike the tokenizer's training data: features of another width (another
    skeleton), another frame rate (the features hold per-frame velocities, and a code covers a
    fixed number of frames), other joints, or the other feature convention (``--legacy``)."""
    ex = meta["extra"]
    if feature_dim != int(ex["feature_dim"]):
        raise ArtifactError(f"{where}: features have {feature_dim} dims, the tokenizer expects {ex['feature_dim']} "
                            f"(trained on a {ex['num_joints']}-joint skeleton)")
    if fps is not None and abs(float(fps) - float(ex["fps"])) > 1e-6:
        raise ArtifactError(f"{where}: motion at {float(fps):g} fps, the tokenizer was trained at {float(ex['fps']):g} "
                            f"fps; preprocess it with --fps {float(ex['fps']):g}")
    theirs = [row[0] for row in ex["skeleton"]["joints"]]
    if joints is not None and list(joints) != theirs:
        raise ArtifactError(f"{where}: its joints are not those of the tokenizer's skeleton "
                            f"{ex['skeleton']['name']!r} ({', '.join(theirs[:3])}, ...)")
    if legacy is not None and bool(legacy) != bool(ex["legacy"]):
        made = "with" if ex["legacy"] else "without"
        raise ArtifactError(f"{where}: features made {'with' if legacy else 'without'} --legacy, the tokenizer's "
                            f"{made} it; preprocess it {made} --legacy")


# --------------------------------------------------------------------------- encode

def encode(run: str | Path, data: str | Path, out: str | Path, num_codebooks: int | None = None,
           split: str | None = None, command: str | None = None) -> dict:
    """Every clip (or one split) of a motion(-dataset) artifact -> a ``tokens`` artifact."""
    run, data = Path(run), Path(data)
    tok = open_tokenizer(run)
    model, meta = tok.model, tok.meta
    m = check_codebooks(model, num_codebooks)
    rate = model.rate
    kept, indices, skipped = [], [], []
    with MotionFile(data) as mf:
        _check_data(mf, meta)
        which = mf.split_indices(split) if split else range(len(mf))
        if not which:
            raise TokenizerError(f"{data}: no clip in split {split!r} (splits: {sorted(set(mf.splits))})")
        total = sum(int(mf.frame_offsets[i + 1] - mf.frame_offsets[i]) for i in which)
        with _progress.make_progress("frames") as bar:
            task = bar.add_task("encode", total=total)
            for i in which:
                feats = mf.frames("features", i)
                if len(feats) < rate:
                    skipped.append({"input": mf.names[i], "error": f"{len(feats)} frames < one token ({rate})"})
                    continue
                kept.append((i, len(feats)))
                indices.append(tok.encode(feats, m))
                bar.advance(task, len(feats))
        if not kept:
            raise ArtifactError(f"{data}: no clip has at least {rate} frames to encode")
        g = mf.h5["captions"]
        cap = {k: g[k][()] for k in ("clip", "start", "end")}
        cap_text, cap_tok = read_strings(g["text"]), read_strings(g["tokens"])
        labels = read_strings(mf.h5["clips/labels"])
        prov_in = hash_inputs([data])
        prov_in[f"{run}#weights"] = meta["model_sha256"]  # tensor hash, as bundle.json model_sha256
        prov = Provenance(command=command or command_line(),
                          config={"tokenizer": str(run), "data": str(data), "num_codebooks": m, "split": split},
                          inputs=prov_in, skipped=skipped)
        lengths = np.array([len(x) for x in indices], dtype=np.int64)
        remap = {i: k for k, (i, _) in enumerate(kept)}
        sel = [r for r in range(len(cap["clip"])) if int(cap["clip"][r]) in remap]
        with write_artifact(out, KIND, prov) as f:
            for k, v in {**_tokenizer_id(run, meta, Path(out)), "rate": rate, "num_codebooks": m,
                         "codebook_size": int(model.quantizer.codebook_size), "fps": mf.fps,
                         "num_joints": int(mf.skeleton.num_joints), "feature_dim": model.feature_dim,
                         "source": str(data), "source_sha256": prov_in[str(data)]}.items():
                f.attrs[k] = v
            sk = f.create_group("skeleton")
            sk.attrs["definition"] = json.dumps(mf.skeleton.to_dict())
            sk.create_dataset("offsets", data=np.asarray(mf.offsets, dtype=np.float32))
            c = f.create_group("clips")
            write_strings(c, "name", [mf.names[i] for i, _ in kept])
            write_strings(c, "split", [mf.splits[i] for i, _ in kept])
            write_strings(c, "labels", [labels[i] for i, _ in kept])
            c.create_dataset("offset", data=np.concatenate([[0], np.cumsum(lengths)]))
            c.create_dataset("frames", data=lengths * rate)
            c.create_dataset("source_frames", data=np.array([n for _, n in kept], dtype=np.int64))
            gc = f.create_group("captions")
            gc.create_dataset("clip", data=np.array([remap[int(cap["clip"][r])] for r in sel], dtype=np.int64))
            write_strings(gc, "text", [cap_text[r] for r in sel])
            write_strings(gc, "tokens", [cap_tok[r] for r in sel])
            gc.create_dataset("start", data=np.array([cap["start"][r] for r in sel], dtype=np.float64))
            gc.create_dataset("end", data=np.array([cap["end"][r] for r in sel], dtype=np.float64))
            f.create_dataset("tokens", data=np.concatenate(indices))
    return {"output": str(out), "clips": len(kept), "tokens": int(lengths.sum()), "num_codebooks": m,
            "rate": rate, "frames_dropped": int(sum(n % rate for _, n in kept)), "skipped": skipped}


class TokenFile(ClipFile):
    """Read access to a ``tokens`` artifact: per-clip indices ``(L, N)`` and captions."""

    REQUIRED = (*ClipFile.REQUIRED, "clips/frames", "clips/source_frames")
    ROWS = ("tokens",)

    def __init__(self, path: str | Path):
        super().__init__(path, KIND)
        a = self.h5.attrs
        self.rate, self.num_codebooks = int(a["rate"]), int(a["num_codebooks"])
        self.codebook_size, self.fps = int(a["codebook_size"]), float(a["fps"])
        self.tokenizer_sha256 = str(a["tokenizer_sha256"])
        self.offsets = self.h5["clips/offset"][()]
        self.skeleton_offsets = self.h5["skeleton/offsets"][()]

    def indices(self, i: int) -> np.ndarray:
        return self.h5["tokens"][self.offsets[i]:self.offsets[i + 1]]

    def captions(self, clip) -> list[tuple]:
        """``[(text, tokens, start, end)]`` of a clip, its annotations' tokens included."""
        return super().captions(clip, tokens=True)


# --------------------------------------------------------------------------- decode

def features_to_clip(name: str, feats: np.ndarray, skeleton: Skeleton, legacy: bool, **kw) -> Clip:
    """De-normalized features -> a renderable clip (joints by the position path, locals by the 6D path)."""
    feats = np.asarray(feats, dtype=np.float32)
    joints = recover_from_ric(feats, skeleton.num_joints).astype(np.float32)
    quats = recover_local_quats(feats, skeleton, legacy=legacy).astype(np.float32)
    return Clip(name, feats, joints, quats, joints[:, 0].copy(), **kw)


def decode(run: str | Path, tokens: str | Path, out: str | Path, num_codebooks: int | None = None,
           allow_mismatch: bool = False, command: str | None = None) -> dict:
    """A ``tokens`` artifact -> a ``motion`` artifact that ``motok render``/``export bvh`` accept."""
    run = Path(run)
    tok = open_tokenizer(run)
    model, meta = tok.model, tok.meta
    with TokenFile(tokens) as tf:
        if tf.tokenizer_sha256 != meta["model_sha256"] and not allow_mismatch:
            raise ArtifactError(f"{tokens} was encoded by another tokenizer ({tf.provenance.config.get('tokenizer')}, "
                                f"sha256 {tf.tokenizer_sha256[:12]}) than {run} ({meta['model_sha256'][:12]})")
        check_codes_fit(model, run, tokens, tf.codebook_size, tf.rate)
        m = check_codebooks(model, num_codebooks or min(tf.num_codebooks, model.num_codebooks),
                            (tokens, tf.num_codebooks))
        skeleton = tok.skeleton
        clips = []
        with _progress.make_progress("clips") as bar:
            task = bar.add_task("decode", total=len(tf))
            for i, name in enumerate(tf.names):
                clips.append(tok.decode(name, tf.indices(i), m, skeleton, split=tf.splits[i], captions=tf.captions(i)))
                bar.advance(task)
        prov = Provenance(command=command or command_line(),
                          config={"tokenizer": str(run), "tokens": str(tokens), "num_codebooks": m},
                          inputs={**hash_inputs([tokens]), f"{run}#weights": meta["model_sha256"]})
        write_motion(out, "motion", prov, clips, skeleton, tok.offsets, tok.fps, tok.legacy)
    return {"output": str(out), "clips": len(clips), "frames": int(sum(c.num_frames for c in clips)),
            "num_codebooks": m}


# --------------------------------------------------------------------------- metrics

def reconstruction_errors(pred: np.ndarray, gt: np.ndarray, num_joints: int) -> dict[str, np.ndarray]:
    """Per-frame errors (mm) of de-normalized features ``(T, D)``, both through ``recover_from_ric``.

    ``mpjpe``: joints relative to the root of the same frame (the MoMask/HumanML3D convention);
    ``mpjpe_global``: with the integrated root trajectory (drift included); ``accel``: norm of
    the difference of second differences of global joints (mm/frame^2, jitter).
    """
    p = recover_from_ric(np.asarray(pred, np.float64), num_joints)
    g = recover_from_ric(np.asarray(gt, np.float64), num_joints)
    return {"mpjpe": mpjpe(p, g), "mpjpe_global": mpjpe(p, g, root_relative=False), "accel": acceleration_error(p, g)}


def codebook_stats(counts: np.ndarray) -> list[dict]:
    """Per codebook from code counts ``(N, K)``: usage (fraction used), perplexity exp(H), dead codes."""
    out = []
    for n, c in enumerate(counts):
        p = c / max(c.sum(), 1)
        nz = p[p > 0]
        out.append({"codebook": n, "usage": float((c > 0).mean()), "perplexity": float(np.exp(-(nz * np.log(nz)).sum())),
                    "dead": int((c == 0).sum()), "used": int((c > 0).sum())})
    return out


def evaluate(run: str | Path, data: str | Path, split: str = "test", num_codebooks: int | None = None) -> dict:
    """Reconstruct every clip of ``split`` through the tokens and measure it against the source."""
    run = Path(run)
    model, meta = load_tokenizer(run)
    m = check_codebooks(model, num_codebooks)
    K = int(model.quantizer.codebook_size)
    counts = np.zeros((m, K), dtype=np.int64)
    sums = {"mpjpe": 0.0, "mpjpe_global": 0.0, "accel": 0.0, "feature_l1": 0.0}
    frames = accel_frames = clips = 0
    with MotionFile(data) as mf:
        _check_data(mf, meta)
        idx_clips = mf.split_indices(split)
        if not idx_clips:
            raise TokenizerError(f"{data}: no clip in split {split!r} (splits: {sorted(set(mf.splits))})")
        J = mf.skeleton.num_joints
        with _progress.make_progress("clips") as bar:
            task = bar.add_task(f"eval {split}", total=len(idx_clips))
            for i in idx_clips:
                gt = np.asarray(mf.frames("features", i))
                T = len(gt) // model.rate * model.rate
                bar.advance(task)
                if T < 3:
                    continue
                gt = gt[:T]
                codes = model.encode_features(torch.from_numpy(gt)[None], m)[..., :m]
                pred = model.decode_features(codes, m)[0].numpy()
                for n in range(m):
                    c = codes[0, :, n].numpy()
                    counts[n] += np.bincount(c[c >= 0], minlength=K)
                err = reconstruction_errors(pred, gt, J)
                sums["mpjpe"] += err["mpjpe"].sum()
                sums["mpjpe_global"] += err["mpjpe_global"].sum()
                sums["accel"] += err["accel"].sum()
                sums["feature_l1"] += float(np.abs((pred - gt) / model.std.numpy()).mean(-1).sum())
                frames += T
                accel_frames += T - 2
                clips += 1
    if not clips:
        raise TokenizerError(f"{data}: no clip of split {split!r} is long enough to evaluate")
    cb = codebook_stats(counts)
    return {
        "tokenizer": str(run), "iteration": meta["extra"].get("iteration"), "data": str(data), "split": split,
        "clips": clips, "frames": frames, "num_codebooks": m, "codebook_size": K,
        "mpjpe_mm": sums["mpjpe"] / frames, "mpjpe_global_mm": sums["mpjpe_global"] / frames,
        "accel_error_mm": sums["accel"] / accel_frames, "feature_l1": sums["feature_l1"] / frames,
        "usage": float(np.mean([c["usage"] for c in cb])), "perplexity": float(np.mean([c["perplexity"] for c in cb])),
        "dead": int(sum(c["dead"] for c in cb)), "codebooks": cb,
    }
