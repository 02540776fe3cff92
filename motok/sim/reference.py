"""The reference library: a dataset's clips as humanoid states at the control rate.

Each clip is retargeted to qpos at the control rate (:func:`motok.sim.retarget.clip_qpos`: inverse
kinematics against the humanoid's fixed rest geometry, then resampling); qvel is the central
difference of qpos (``mj_differentiatePos``); body positions, rotations, linear and angular
velocities come from MuJoCo's forward kinematics (:func:`motok.sim.kinematics.body_states`). The
library is cached in one ``.npz`` keyed by the dataset's hash, the MJCF text and the rate, so it
is built once.

The way back, :func:`simulated_clip`, turns simulated body positions into a motion clip at the
dataset's frame rate (tracking and generation write their results with it).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from motok.arrays import is_tensor, xp
from motok.artifacts import sha256_file
from motok.atomic import atomic_path
from motok.data.dataset import Clip, MotionFile, clip_index
from motok.errors import MotokError
from motok.features.humanml3d import extract_features
from motok.features.resample import resample_positions
from motok.sim.humanoid import Humanoid, HumanoidConfig, from_mj, load_humanoid, to_mj
from motok.sim.kinematics import body_states
from motok.sim.mjcf import build_humanoid
from motok.sim.retarget import clip_qpos

LIB_VERSION = 1


class ReferenceError(MotokError, KeyError):
    pass


def _qvel(model, qpos: np.ndarray, dt: float) -> np.ndarray:
    import mujoco

    T = len(qpos)
    out = np.zeros((T, model.nv))
    if T < 2:
        return out
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        mujoco.mj_differentiatePos(model, out[t], (b - a) * dt, qpos[a], qpos[b])
    return out


@dataclass
class ReferenceLibrary:
    """Reference clips at the control rate, concatenated along frames with a clip offset index."""

    names: list[str]
    fps: float
    starts: np.ndarray  # (C+1,) frame offsets
    qpos: np.ndarray  # (F, nq)
    qvel: np.ndarray  # (F, nv)
    body_pos: np.ndarray  # (F, J, 3)
    body_quat: np.ndarray  # (F, J, 4)
    body_vel: np.ndarray
    body_angvel: np.ndarray
    lowest: np.ndarray  # (F,) lowest geom point, for lifting reference states off the floor
    joints: np.ndarray  # (F, J, 3) the dataset's canonical joints, resampled, MuJoCo coordinates

    ARRAYS = ("qpos", "qvel", "body_pos", "body_quat", "body_vel", "body_angvel", "lowest", "joints")

    def __len__(self) -> int:
        return len(self.names)

    def __post_init__(self):
        self.lengths = self.starts[1:] - self.starts[:-1]  # frames per clip

    def to(self, device, dtype=None) -> "ReferenceLibrary":
        """The library as torch tensors on ``device`` (floats as ``dtype``, float32 by default:
        MuJoCo Warp's precision), for a rollout that stays on the device; the look-ups below and
        the reset and reward terms then run there (:mod:`motok.arrays`)."""
        import torch

        dtype = dtype or torch.float32
        arrays = {k: torch.as_tensor(getattr(self, k), dtype=dtype, device=device) for k in self.ARRAYS}
        return ReferenceLibrary(names=self.names, fps=self.fps,
                                starts=torch.as_tensor(self.starts, dtype=torch.int64, device=device), **arrays)

    def index(self, clip) -> int:
        return clip_index(self.names, clip, within=" in the reference library", error=ReferenceError)

    def frame_index(self, clips, frames) -> np.ndarray:
        """Rows of the concatenated arrays for ``frames`` of ``clips`` (clip indices, broadcast
        together), each clamped to its clip's last frame: a lookahead past the end of a clip (the
        next frame, a goal horizon) repeats the last reference state instead of reading the next clip."""
        clips = clips if is_tensor(clips) else np.asarray(clips)
        return xp(self.starts).minimum(self.starts[clips] + frames, self.starts[clips + 1] - 1)

    def clip(self, clip) -> dict[str, np.ndarray]:
        i = self.index(clip)
        sl = slice(self.starts[i], self.starts[i + 1])
        return {k: getattr(self, k)[sl] for k in self.ARRAYS}

    def sample(self, n: int, rng: np.random.Generator, horizon: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Random clips (weighted by usable length) and start frames that leave ``horizon`` frames ahead."""
        usable = np.maximum(self.lengths - horizon, 0)
        if usable.sum() == 0:
            raise ReferenceError(f"every clip is shorter than {horizon + 1} frames at {self.fps:g} Hz")
        clips = rng.choice(len(self), size=n, p=usable / usable.sum())
        frames = np.floor(rng.random(n) * usable[clips]).astype(np.int64)
        return clips, frames

    def save(self, path: Path) -> None:
        with atomic_path(path) as tmp:  # keeps the .npz suffix, so savez does not append one
            np.savez(tmp, names=np.array(self.names), fps=self.fps, starts=self.starts, version=LIB_VERSION,
                     **{k: getattr(self, k).astype(np.float64) for k in self.ARRAYS})

    @classmethod
    def from_file(cls, path: Path) -> "ReferenceLibrary":
        with np.load(path) as z:
            if int(z["version"]) != LIB_VERSION:
                raise ValueError("stale cache")
            return cls(names=[str(s) for s in z["names"]], fps=float(z["fps"]), starts=z["starts"],
                       **{k: z[k] for k in cls.ARRAYS})


def build_library(hum: Humanoid, data_path, control_hz: float | None = None, clips=None) -> ReferenceLibrary:
    """Build the library for ``clips`` (names or indices; all by default) of a motion artifact
    (its path, or an open one: a :class:`MotionFile`, clips in memory)."""
    hz = float(control_hz or hum.control_hz)
    if not hasattr(data_path, "frames"):
        with MotionFile(data_path) as mf:  # a dataset, decoded tokens, GPT samples: any motion artifact
            return build_library(hum, mf, hz, clips)
    mf = data_path
    if list(mf.skeleton.joints) != list(hum.skeleton.joints):
        raise ReferenceError(f"{mf.path}: skeleton {mf.skeleton.name!r} does not match the humanoid's "
                             f"{hum.skeleton.name!r}; build the humanoid from this dataset")
    try:
        idx = list(range(len(mf))) if clips is None else [mf.index(c) for c in clips]
    except KeyError as e:
        raise ReferenceError(e.args[0]) from None
    return library_from_joints(hum, [mf.names[i] for i in idx], (mf.frames("joints", i) for i in idx), mf.fps, hz)


def library_from_joints(hum: Humanoid, names: list[str], joints, fps: float, control_hz: float) -> ReferenceLibrary:
    """The library of clips given as joint positions ``(T, J, 3)`` (dataset coordinates, at
    ``fps``), one per name: what :func:`build_library` does with a file's clips, for motion held
    in memory (the plans of a closed loop)."""
    hz = float(control_hz)
    parts = {k: [] for k in ReferenceLibrary.ARRAYS}
    for j in joints:
        j = np.asarray(j, dtype=np.float64)
        qpos = clip_qpos(j, hum, fps, hz)
        res = resample_positions(j, fps, hz) if fps != hz else j
        qvel = _qvel(hum.model, qpos, 1.0 / hz)
        st = body_states(hum, qpos, qvel)
        for k, v in dict(qpos=qpos, qvel=qvel, joints=to_mj(res), **st).items():
            parts[k].append(v)
    lengths = [len(p) for p in parts["qpos"]]
    return ReferenceLibrary(names=list(names), fps=hz, starts=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
                            **{k: np.concatenate(v) for k, v in parts.items()})


def concat_libraries(libs: list[ReferenceLibrary]) -> ReferenceLibrary:
    """One library holding the clips of ``libs`` in order (host arrays, one rate)."""
    lengths = np.concatenate([lb.lengths for lb in libs])
    return ReferenceLibrary(names=[n for lb in libs for n in lb.names], fps=libs[0].fps,
                            starts=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
                            **{k: np.concatenate([getattr(lb, k) for lb in libs]) for k in ReferenceLibrary.ARRAYS})


def default_cache_dir() -> Path:
    return Path(os.environ.get("MOTOK_CACHE", Path.home() / ".cache" / "motok")) / "sim-reference"


def load_library(hum: Humanoid, data_path, control_hz: float | None = None, clips=None,
                 cache_dir=None, use_cache: bool = True) -> ReferenceLibrary:
    """The reference library, from the cache when the dataset, MJCF, rate and clip list match."""
    hz = float(control_hz or hum.control_hz)
    if not use_cache:
        return build_library(hum, data_path, hz, clips)
    h = hashlib.sha256()
    h.update(sha256_file(data_path).encode())
    h.update(hum.path.read_bytes() if hum.path else repr(hum.meta).encode())
    h.update(f"{hz:.6f}|{LIB_VERSION}|{clips!r}".encode())
    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    path = cache / f"{Path(data_path).stem}-{h.hexdigest()[:16]}.npz"
    if path.exists():
        try:
            return ReferenceLibrary.from_file(path)
        except (ValueError, KeyError, OSError):
            pass  # a stale or truncated cache is rebuilt below
    lib = build_library(hum, data_path, hz, clips)
    cache.mkdir(parents=True, exist_ok=True)
    lib.save(path)
    return lib


def humanoid_for(data_path, cache_dir=None, cfg: HumanoidConfig | None = None):
    """The humanoid of a dataset built with ``cfg`` (the builder's defaults unless given), built once
    and cached next to the reference libraries. The cache key holds the configuration, so a new
    default, or another configuration, builds a new file."""
    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    cfg = cfg or HumanoidConfig()
    key = hashlib.sha256(json.dumps(asdict(cfg), sort_keys=True).encode()).hexdigest()[:8]
    path = cache / f"{Path(data_path).stem}-{sha256_file(data_path)[:16]}-{key}.xml"
    if not path.exists():
        with atomic_path(path) as tmp:
            build_humanoid(data_path, tmp, cfg)
    return load_humanoid(path)


def simulated_clip(name: str, sim_pos: np.ndarray, control_hz: float, fps: float, skeleton, offsets,
                   legacy: bool, source: str, **clip_fields) -> Clip:
    """Simulated body positions ``(T, J, 3)`` (MuJoCo frame, at the control rate) as a clip at the
    motion's rate ``fps``, with features, joints, rotations and root translation recomputed from
    them, so every motok tool reads it; ``clip_fields``: the Clip's split, labels, captions."""
    pos = from_mj(sim_pos)
    if abs(control_hz - fps) > 1e-6:
        pos = resample_positions(pos, control_hz, fps)
    f = extract_features(pos, skeleton, target_offsets=offsets, fps=fps, legacy=legacy)
    return Clip(name, f.features, f.joints, f.local_quats, f.root_translation, source=source, source_fps=fps,
                **clip_fields)
