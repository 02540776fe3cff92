"""Reset terms: where a new episode starts.

Reference state initialisation (Peng et al. 2018, used by the hybrid-latent paper's expert):
start from a state of the reference motion, at a random clip and frame or at given ones.
"""

from __future__ import annotations

import numpy as np

from motok.errors import UserError
from motok.sim.obs import Bodies
from motok.sim.reference import ReferenceLibrary

RESET_CLEARANCE = 0.002  # m: a reference pose whose geometry dips below the floor is lifted to this height


def check_rate(lib: ReferenceLibrary, control_hz: float) -> None:
    """A reference task steps one reference frame per control step, so the two rates must agree."""
    if abs(lib.fps - control_hz) > 1e-6:
        raise UserError(f"the reference library is at {lib.fps:g} Hz but the control rate is {control_hz:g} Hz")


def reference_state(lib: ReferenceLibrary, clips: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(qpos, qvel)`` of the reference at ``clips``/``frames``, lifted clear of the floor."""
    g = lib.starts[clips] + frames
    qpos, qvel = lib.qpos[g].copy(), lib.qvel[g].copy()
    qpos[:, 2] += np.maximum(RESET_CLEARANCE - lib.lowest[g], 0.0)
    return qpos, qvel


def check_start_frames(lib: ReferenceLibrary, clips: np.ndarray, frames: np.ndarray, ahead: int) -> None:
    """Given start frames must leave at least one step with ``ahead`` reference frames after it."""
    bad = (frames < 0) | (frames + ahead + 2 > lib.lengths[clips])
    if bad.any():
        raise UserError(f"start frames {frames[bad].tolist()} leave no step with {ahead} reference frames ahead "
                         f"(clip lengths {lib.lengths[clips[bad]].tolist()} at {lib.fps:g} Hz)")


def sample_starts(lib: ReferenceLibrary, n: int, rng: np.random.Generator, ahead: int,
                  clip_p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Random start clips and frames leaving ``ahead`` frames after them: clips in proportion to
    their usable length (``clip_p=None``) or to given probabilities (difficulty sampling,
    ``motok.control.sampling``); frames uniform within the clip."""
    if clip_p is None:
        return lib.sample(n, rng, horizon=ahead)
    usable = np.maximum(lib.lengths - ahead, 0)
    clips = rng.choice(len(lib), size=n, p=clip_p)
    frames = np.floor(rng.random(n) * usable[clips]).astype(np.int64)
    return clips, frames


def reference_bodies(lib: ReferenceLibrary, clips: np.ndarray, frames: np.ndarray) -> Bodies:
    """Reference body states at ``frames`` of ``clips`` (broadcast together; clamped to each clip's
    last frame by ``frame_index``)."""
    g = lib.frame_index(clips, frames)
    return Bodies(lib.body_pos[g], lib.body_vel[g], lib.body_angvel[g], quat=lib.body_quat[g])


def given_starts(lib: ReferenceLibrary, clips, frames, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Clip indices and start frames ``(n,)`` from given ``clips`` (names or indices) and ``frames``
    (0 by default), each broadcast to ``n`` environments."""
    c = np.array([lib.index(x) for x in np.broadcast_to(np.asarray(clips, dtype=object), (n,))], dtype=np.int64)
    return c, np.broadcast_to(np.asarray(0 if frames is None else frames, dtype=np.int64), (n,)).copy()
