"""Reset terms: where a new episode starts.

Reference state initialisation (Peng et al. 2018, used by the hybrid-latent paper's expert):
start from a state of the reference motion, at a random clip and frame or at given ones.

The terms take a host library (numpy) or one moved to a device (``ReferenceLibrary.to``, torch):
random starts then come from a ``torch.Generator`` on that device instead of a numpy one, so an
on-device rollout draws its resets where its state lives (:mod:`motok.arrays`).
"""

from __future__ import annotations

import numpy as np

from motok.arrays import is_tensor, like, xp
from motok.errors import UserError
from motok.sim.obs import Bodies
from motok.sim.reference import ReferenceLibrary

RESET_CLEARANCE = 0.002  # m: a reference pose whose geometry dips below the floor is lifted to this height


class ClipProbabilities:
    """A task's start-clip probabilities (``None``: by usable length), given as host numbers (the
    difficulty sampler's) and kept where the task's library is, so a device draw reads them there."""

    def __set_name__(self, owner, name):
        self.attr = "_" + name

    def __get__(self, task, owner=None):
        return self if task is None else getattr(task, self.attr, None)

    def __set__(self, task, p) -> None:
        setattr(task, self.attr, None if p is None else like(task.lib.qpos, p))


def host_lengths(lib: ReferenceLibrary) -> np.ndarray:
    """Frames per clip as host numbers, to check given starts without reading a device library each time."""
    s = lib.starts
    return np.diff(s.cpu().numpy() if is_tensor(s) else s)


def check_rate(lib: ReferenceLibrary, control_hz: float) -> None:
    """A reference task steps one reference frame per control step, so the two rates must agree."""
    if abs(lib.fps - control_hz) > 1e-6:
        raise UserError(f"the reference library is at {lib.fps:g} Hz but the control rate is {control_hz:g} Hz")


def reference_state(lib: ReferenceLibrary, clips, frames):
    """``(qpos, qvel)`` of the reference at ``clips``/``frames``, lifted clear of the floor."""
    g = lib.starts[clips] + frames
    qpos, qvel = lib.qpos[g], lib.qvel[g]  # gathered by an index array: copies
    qpos[:, 2] += xp(qpos).clip(RESET_CLEARANCE - lib.lowest[g], 0.0, None)
    return qpos, qvel


def check_start_frames(lib: ReferenceLibrary, clips: np.ndarray, frames: np.ndarray, ahead: int,
                       lengths: np.ndarray | None = None) -> None:
    """Given start frames (host arrays) must leave at least one step with ``ahead`` reference frames
    after it; ``lengths``: the clip lengths on the host, for a library on a device."""
    lengths = lib.lengths if lengths is None else lengths
    bad = (frames < 0) | (frames + ahead + 2 > lengths[clips])
    if bad.any():
        raise UserError(f"start frames {frames[bad].tolist()} leave no step with {ahead} reference frames ahead "
                         f"(clip lengths {lengths[clips[bad]].tolist()} at {lib.fps:g} Hz)")


def sample_starts(lib: ReferenceLibrary, n: int, rng, ahead: int, clip_p=None):
    """Random start clips and frames leaving ``ahead`` frames after them: clips in proportion to
    their usable length (``clip_p=None``) or to given probabilities (difficulty sampling,
    ``motok.control.rl.sampling``); frames uniform within the clip. ``rng``: a numpy generator for a
    host library, a ``torch.Generator`` on the library's device for a device one."""
    if is_tensor(lib.starts):
        import torch

        usable = (lib.lengths - ahead).clamp(min=0)
        p = usable.to(torch.float32) if clip_p is None else clip_p
        clips = torch.multinomial(p, n, replacement=True, generator=rng)
        u = torch.rand(n, generator=rng, device=usable.device, dtype=torch.float64)
        return clips, (u * usable[clips]).floor().to(torch.int64)
    if clip_p is None:
        return lib.sample(n, rng, horizon=ahead)
    usable = np.maximum(lib.lengths - ahead, 0)
    clips = rng.choice(len(lib), size=n, p=clip_p)
    frames = np.floor(rng.random(n) * usable[clips]).astype(np.int64)
    return clips, frames


def reference_bodies(lib: ReferenceLibrary, clips, frames) -> Bodies:
    """Reference body states at ``frames`` of ``clips`` (broadcast together; clamped to each clip's
    last frame by ``frame_index``)."""
    g = lib.frame_index(clips, frames)
    return Bodies(lib.body_pos[g], lib.body_vel[g], lib.body_angvel[g], quat=lib.body_quat[g])


def given_starts(lib: ReferenceLibrary, clips, frames, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Clip indices and start frames ``(n,)`` from given ``clips`` (names or indices) and ``frames``
    (0 by default), each broadcast to ``n`` environments."""
    c = np.array([lib.index(x) for x in np.broadcast_to(np.asarray(clips, dtype=object), (n,))], dtype=np.int64)
    return c, np.broadcast_to(np.asarray(0 if frames is None else frames, dtype=np.int64), (n,)).copy()


def free_starts(lib: ReferenceLibrary, n: int, rng, clips=None, frames=None, who: str = "task"):
    """Start clips and frames ``(n,)`` of a task that reads no reference ahead (navigation,
    steering): drawn from ``rng`` (:func:`sample_starts`) unless ``clips`` are given
    (:func:`given_starts`), whose ``frames`` must lie inside them (``who``, the task, begins the
    refusal); where the library is."""
    if clips is None:
        return sample_starts(lib, n, rng, 1)
    c, f = given_starts(lib, clips, frames, n)
    lengths = host_lengths(lib)
    bad = (f < 0) | (f >= lengths[c])
    if bad.any():
        raise UserError(f"{who}: start frames {f[bad].tolist()} are outside their clips "
                        f"(lengths {lengths[c[bad]].tolist()})")
    return like(lib.starts, c), like(lib.starts, f)
