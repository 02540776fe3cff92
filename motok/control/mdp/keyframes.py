"""Motion in-betweening terms (hybrid-latent paper, appendix C.1, Eq. 12-14).

A 4 s window of a reference clip holds ``K`` keyframes; the character starts in the first and must
pass through the others at their frames, the last being the window's last frame.

* :func:`sample_keyframes`: the window's first and last frames plus ``K - 2`` sorted random frames
  between them, consecutive keyframes at least ``min_gap`` frames apart (the fork's
  ``full_random_long`` style, its default for training and the one it forces for testing;
  ``min_gap`` = 15 frames there, 0.5 s at 30 Hz);
* :func:`still_frames` / :func:`sample_still_keyframes`: the paper's keyframes are zero-velocity
  poses (C.1). Captured motion is never exactly still, so the interior keyframes are drawn among
  the frames where the pose comes to rest: local minima of the pose speed (:func:`pose_speed`, the
  bodies' speed relative to the root, so that walking on is no motion of the pose), in order, each at least ``min_gap`` frames after the one before
  and leaving room for the rest; a stretch with no such frame gives its slowest frame. The first
  keyframe is the start state and the last the window's last frame, as in the fork;
* :func:`next_keyframe`: which keyframe is the next to reach, and :func:`time_encoding`, the
  sinusoidal encoding of the frames left until it (Eq. 13);
* :func:`keyframe_goal`, Eq. 12: for each goal keyframe and every body, the position and rotation
  (6D) differences keyframe - simulation in the heading frame. It is Eq. 9's difference
  (``observations.imitation_goal``) without the velocity parts, so the rotation difference is
  conjugated into the heading frame as there; the fork left-multiplies only;
* :func:`inbetween_errors` / :func:`inbetween_reward`, Eq. 14: the fork's "deepmimic" reward,
  a weighted **sum** ``0.65 exp(-2 e_q) + 0.1 exp(-0.1 e_qd) + 0.15 exp(-40 e_ee) + 0.1 exp(-10 e_root)``
  with means over hinges and end effectors and *global* end-effector positions, against the
  reference at **every frame** of the window, not only at the keyframes (the fork's
  ``_compute_reward`` compares with the reference buffer at the current frame on every step). It
  is not Eq. 10's product: the fork's in-betweening recipe selects ``imitationRewStyle: deepmimic``.
  The fork also rescales the reward by ``T / (k_last - k_0 + 1)``, which is 1 for these keyframes.

The time encoding (fork: ``PositionalEncoding: time``, after Harvey et al. 2020, "Robust motion
in-betweening"): ``E[t, 2i] = sin(t w_i)``, ``E[t, 2i + 1] = cos(t w_i)``, ``w_i = 10000^(-2i / d)``,
of the same dimension ``d`` as the keyframe goal and **added** to it, constant for ``t >= T - 4``
(``T`` the window's frames; the fork copies row ``T - 4`` into the table's last four rows).

Sources: the formulas and constants are read from the fork's code (``humanoid_imitate_keyframes.py``,
``humanoid_imitate.py``, ``LafanInbetweening.yaml``); the equation numbers are the paper's. Its
``MINIMUM_KEYFRAME_INTERVAL = 15`` is commented "1s" but is 0.5 s at its 30 Hz control rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.arrays import is_tensor, like, xp
from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.rewards import check_non_negative
from motok.errors import UserError
from motok.ranges import In
from motok.sim.obs import Bodies

KEYFRAME_FEATURES = 9  # per body: position difference (3) + rotation difference (6D)


def check_keyframe_count(count: int, window: int, min_gap: int, where: str = "inbetween task") -> None:
    """``count`` keyframes ``min_gap`` frames apart must fit in a ``window``-frame window."""
    if count < 2:
        raise UserError(f"{where}: num_keyframes must be >= 2 (the start and the window's end), got {count}")
    if min_gap < 1:
        raise UserError(f"{where}: min_keyframe_gap_seconds must give at least one frame, got {min_gap} frames")
    if (count - 1) * min_gap > window - 1:
        raise UserError(f"{where}: {count} keyframes {min_gap} frames apart do not fit in a {window}-frame "
                        f"window; lower num_keyframes or min_keyframe_gap_seconds, or raise window_seconds")


def sample_keyframes(rng, n: int, count: int, window: int, min_gap: int):
    """``(n, count)`` keyframe offsets within a ``window``-frame window: ``0``, ``count - 2`` random
    frames, ``window - 1``; increasing, consecutive ones at least ``min_gap`` apart. ``rng``: numpy's
    generator (host arrays) or a ``torch.Generator`` (tensors on its device).

    The interior ones are sorted uniform draws from the slack ``window - 1 - (count - 1) min_gap``,
    shifted by ``min_gap`` per rank, which keeps every gap (the last one too) >= ``min_gap``."""
    check_keyframe_count(count, window, min_gap)
    slack = window - 1 - (count - 1) * min_gap
    if isinstance(rng, np.random.Generator):
        draws = np.sort(rng.integers(0, slack + 1, size=(n, count - 2)), axis=1).astype(np.int64)
    else:
        import torch

        draws = torch.randint(0, slack + 1, (n, count - 2), generator=rng, device=rng.device).sort(1).values
    x, ends = xp(draws), np.array([[0, window - 1]], dtype=np.int64).repeat(n, 0)
    ends = like(draws, ends)
    return x.concatenate([ends[:, :1], draws + like(draws, min_gap * np.arange(1, count - 1)), ends[:, 1:]], 1)


def pose_speed(body_vel):
    """``(...,)`` the pose's speed (m/s) from world body velocities ``(..., J, 3)``, the root first:
    the mean over the other bodies of their speed relative to the root. On the walks of set 2's
    walk_normal slice its local minima fall at 0.32 m/s against 0.47 at any frame, where those of
    the world speed, dominated by the root's travel, fall at 1.12 against 1.19."""
    x = xp(body_vel)
    rel = body_vel[..., 1:, :] - body_vel[..., :1, :]
    return x.sqrt((rel ** 2).sum(-1)).mean(-1)


def still_frames(speed):
    """``(n, T)`` bool from pose speeds ``(n, T)``: the interior frames ``0 < t < T - 1`` at a local
    minimum, ``speed[t] <= speed[t - 1]`` and ``speed[t] <= speed[t + 1]``: where the pose comes to
    rest, the zero-velocity poses captured motion has."""
    x = xp(speed)
    inner = (speed[:, 1:-1] <= speed[:, :-2]) & (speed[:, 1:-1] <= speed[:, 2:])
    edge = x.zeros_like(speed[:, :1], dtype=bool) if x is np else x.zeros_like(speed[:, :1], dtype=x.bool)
    return x.concatenate([edge, inner, edge], 1)


def sample_still_keyframes(rng, speed, count: int, min_gap: int):
    """``(n, count)`` keyframe offsets within windows of ``T`` frames whose pose speeds are
    ``speed`` ``(n, T)`` (:func:`pose_speed`): ``0``, ``count - 2`` zero-velocity frames, ``T - 1``
    (module docstring).
    Interior keyframe ``j`` is uniform over the :func:`still_frames` in ``[k_(j-1) + min_gap,
    T - 1 - (count - 1 - j) min_gap]``, or the slowest frame there when none is. ``rng``: numpy's
    generator (host arrays) or a ``torch.Generator`` (tensors on its device)."""
    n, T = speed.shape
    check_keyframe_count(count, T, min_gap)
    x = xp(speed)
    still, t = still_frames(speed), like(speed, np.arange(T, dtype=np.int64))[None]
    prev, keys = like(speed, np.zeros(n, dtype=np.int64)), [like(speed, np.zeros(n, dtype=np.int64))]
    for j in range(1, count - 1):
        inside = (t >= (prev + min_gap)[:, None]) & (t <= T - 1 - (count - 1 - j) * min_gap)
        if x is np:
            u = rng.random((n, T))
        else:
            u = x.rand((n, T), generator=rng, device=rng.device, dtype=speed.dtype)
        drawn = x.where(still & inside, u, -1.0).argmax(1)
        slowest = x.where(inside, speed, np.inf).argmin(1)
        prev = x.where((still & inside).any(1), drawn, slowest)
        keys.append(prev)
    keys.append(like(speed, np.full(n, T - 1, dtype=np.int64)))
    return x.stack(keys, 1)


def check_keyframes(keyframes: np.ndarray, window: int, where: str = "inbetween task") -> None:
    """Given keyframe offsets ``(n, K)`` must start at 0 (the start state), increase strictly and
    stay inside the window."""
    k = np.asarray(keyframes)
    if k.ndim != 2 or k.shape[1] < 2:
        raise UserError(f"{where}: keyframes must have shape (environments, K >= 2), got {k.shape}")
    if (k[:, 0] != 0).any() or (np.diff(k, axis=1) <= 0).any() or (k[:, -1] > window - 1).any():
        raise UserError(f"{where}: keyframes must be offsets 0 < ... <= {window - 1} within the window, "
                        f"strictly increasing and starting at 0, got {k.tolist()}")


def next_keyframe(keyframes, t):
    """Index of the next keyframe to reach at window offset ``t``: the first one after ``t`` (so the
    goal moves on at the frame a keyframe is reached), the last one once every keyframe is past."""
    return xp(keyframes).clip((keyframes <= t[:, None]).sum(1), None, keyframes.shape[1] - 1)


def time_encoding(tta, dim: int, cap: int, dtype=None):
    """Eq. 13, ``(n, dim)`` sinusoidal encoding of the frames ``tta`` until the next keyframe,
    constant for ``tta >= cap`` (see the module docstring). Host float64, or tensors of ``dtype``
    (float32 by default) where ``tta`` is."""
    if is_tensor(tta):
        import torch

        t = tta.clamp(max=cap).to(dtype or torch.float32)[:, None]
    else:
        t = np.minimum(np.asarray(tta, dtype=np.float64), cap)[:, None]
    x = xp(t)
    w = like(t, np.exp(np.arange(0, dim, 2) * (-np.log(10000.0) / dim)))
    # sin and cos interleaved: E[:, 2i] = sin(t w_i), E[:, 2i + 1] = cos(t w_i); an odd dim ends on a sine.
    return x.stack([x.sin(t * w), x.cos(t * w)], -1).reshape(len(t), -1)[:, :dim]


def keyframe_goal(sim: Bodies, keys: Bodies):
    """Eq. 12, ``(N, K * J * 9)`` from sim bodies ``(N, J, .)`` and keyframe bodies ``(N, K, J, .)``:
    per keyframe and body the position and 6D rotation differences in the heading frame."""
    N, K, J = keys.pos.shape[:3]
    return imitation_goal(sim, keys).reshape(N, K, J, 15)[..., :KEYFRAME_FEATURES].reshape(N, -1)


@dataclass
class InbetweenRewardConfig:
    """Eq. 14 weights and exponents (the fork's ``compute_deepmimic_reward``)."""

    w_q: In[float, ">= 0"] = 0.65  # weight of exp(-k_q e_q)
    k_q: In[float, ">= 0"] = 2.0  # exponent on e_q, the mean squared hinge angle error (rad^2)
    w_qd: In[float, ">= 0"] = 0.1  # weight of exp(-k_qd e_qd)
    k_qd: In[float, ">= 0"] = 0.1  # exponent on e_qd, the mean squared hinge velocity error ((rad/s)^2)
    w_ee: In[float, ">= 0"] = 0.15  # weight of exp(-k_ee e_ee)
    k_ee: In[float, ">= 0"] = 40.0  # exponent on e_ee, the mean squared end-effector position error (m^2)
    w_root: In[float, ">= 0"] = 0.1  # weight of exp(-k_root e_root)
    k_root: In[float, ">= 0"] = 10.0  # exponent on e_root, the squared root position error (m^2)

    def __post_init__(self):
        check_non_negative(self, "inbetween reward")


def inbetween_errors(pos, ref_pos, q, q_ref, qd, qd_ref, ee) -> dict:
    """Eq. 14's errors ``(N,)``: mean squared hinge angle and velocity errors, mean over the end
    effectors ``ee`` of their squared (global) position errors, squared root position error."""
    ee = list(ee)
    return {"q": ((q - q_ref) ** 2).mean(-1), "qd": ((qd - qd_ref) ** 2).mean(-1),
            "ee": ((pos[:, ee] - ref_pos[:, ee]) ** 2).sum(-1).mean(-1),
            "root": ((pos[:, 0] - ref_pos[:, 0]) ** 2).sum(-1)}


def inbetween_reward(err: dict, cfg: InbetweenRewardConfig) -> dict:
    """Eq. 14: ``r_task = sum_k w_k exp(-k_k e_k)`` and its unweighted terms ``r_q``, ``r_qd``, ``r_ee``, ``r_root``."""
    x = xp(err["q"])
    r = {f"r_{k}": x.exp(-getattr(cfg, f"k_{k}") * err[k]) for k in ("q", "qd", "ee", "root")}
    r["r_task"] = sum(getattr(cfg, f"w_{k}") * r[f"r_{k}"] for k in ("q", "qd", "ee", "root"))
    return r
