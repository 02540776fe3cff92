"""Physical plausibility of kinematic motion: what the Guo et al. evaluator does not punish.

Computed from global joint positions (metres, Y up, floor at y = 0 as every motok motion
artifact stores them), so they apply to real motion, reconstructions and generated motion alike:

- foot skating: horizontal speed (cm/s) of a foot's contact joint while it is on the floor. The
  contact joint is the foot joint with the lowest resting height (the toe; its resting height is
  the 5th percentile of its height over the clip), in contact when within ``contact_tolerance``
  (1 cm) of it; speed counts only between two contact frames, so lift-off and landing do not.
  The ankle is left out: it travels ~30-50 cm/s on real walking while the foot rolls over the
  heel, and a 5 cm floor threshold catches swinging toes (both measured on Bandai set 2).
  ``skate_ratio`` is the fraction of contact steps faster than ``skate_speed`` (0.5 m/s).
  The definition follows the height-based skating measures of GMD (Karunratanakul et al. 2023)
  and PhysDiff (Yuan et al. 2023), with thresholds stated here instead of per-frame distances.
- ground penetration: mean depth (cm) of the lowest foot joint below the floor, per frame;
- floating: mean height (cm) of the lowest foot joint above ``float_tolerance``, per frame
  (jumps count too: real motion gives the baseline);
- floating, placed (``floating_placed_cm``): the same after the clip is moved vertically, as a
  whole, so that its lowest joint over the clip is at y = 0: how the feature pipeline places real
  and simulated motion (so their penetration is 0 by construction). A generator's own heights can
  sink a foot in one frame and float it in another; this column compares them with real and
  tracked motion on equal terms;
- jitter: mean jerk, the norm of the third time derivative of every joint (m/s^3).

Contact comes from heights, never from the features' contact channels: a generator predicts
those channels itself, and a sliding foot would be labelled as not in contact by a velocity test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CONTACT_TOLERANCE = 0.01  # m: a toe this close to its resting height is on the floor
REST_PERCENTILE = 5  # a joint's resting height: this percentile of its height over the clip
SKATE_SPEED = 0.5  # m/s: faster than this while in contact counts as a skating step
FLOAT_TOLERANCE = 0.05  # m: the lowest foot joint may be this high without floating


@dataclass
class PhysicalSums:
    """Running sums over clips, so a dataset's result weighs every frame equally."""
    skate: float = 0.0
    skate_fast: int = 0
    contact_steps: int = 0
    penetration: float = 0.0
    floating: float = 0.0
    floating_placed: float = 0.0
    frames: int = 0
    jerk: float = 0.0
    jerk_frames: int = 0
    clips: int = 0
    feet: int = 0  # feet per frame (the same in every clip)

    def add(self, other: "PhysicalSums") -> None:
        for k in self.__dataclass_fields__:
            setattr(self, k, getattr(self, k) + getattr(other, k))
        self.feet = other.feet

    def result(self) -> dict:
        div = lambda a, b: float(a) / b if b else float("nan")  # noqa: E731
        return {"skate_cm_s": 100 * div(self.skate, self.contact_steps),
                "skate_ratio": div(self.skate_fast, self.contact_steps),
                "contact_fraction": div(self.contact_steps, max(self.frames - self.clips, 0) * self.feet),
                "penetration_cm": 100 * div(self.penetration, self.frames),
                "floating_cm": 100 * div(self.floating, self.frames),
                "floating_placed_cm": 100 * div(self.floating_placed, self.frames),
                "jitter_m_s3": div(self.jerk, self.jerk_frames),
                "clips": self.clips, "frames": self.frames}


def clip_sums(joints: np.ndarray, fps: float, feet: tuple[tuple[int, ...], tuple[int, ...]],
              contact_tolerance: float = CONTACT_TOLERANCE, skate_speed: float = SKATE_SPEED,
              float_tolerance: float = FLOAT_TOLERANCE) -> PhysicalSums:
    """Sums for one clip of ``(T, J, 3)`` joints; ``feet`` = (left foot joints, right foot joints)."""
    x = np.asarray(joints, np.float64)
    T = len(x)
    s = PhysicalSums(frames=T, clips=1, feet=len(feet))
    for foot in feet:
        rest = np.percentile(x[:, list(foot), 1], REST_PERCENTILE, axis=0)
        # The foot touches the floor at its lowest joint (the toe); the ankle above it moves while
        # the foot rolls over the heel, which is no skating.
        j = foot[int(rest.argmin())]
        contact = x[:, j, 1] < rest.min() + contact_tolerance
        both = contact[:-1] & contact[1:]
        speed = np.linalg.norm(np.diff(x[:, j][:, [0, 2]], axis=0), axis=-1) * fps
        s.skate += float(speed[both].sum())
        s.skate_fast += int((speed[both] > skate_speed).sum())
        s.contact_steps += int(both.sum())
    all_feet = list(feet[0]) + list(feet[1])
    lowest = x[:, all_feet, 1].min(1)
    s.penetration = float(np.maximum(-lowest, 0.0).sum())
    s.floating = float(np.maximum(lowest - float_tolerance, 0.0).sum())
    s.floating_placed = float(np.maximum(lowest - x[..., 1].min() - float_tolerance, 0.0).sum())
    if T >= 4:
        jerk = np.diff(x, n=3, axis=0) * fps ** 3
        s.jerk = float(np.linalg.norm(jerk, axis=-1).mean(-1).sum())
        s.jerk_frames = T - 3
    return s


def physical_metrics(joints: np.ndarray, fps: float, feet, **kw) -> dict:
    """The metrics of one clip (see the module docstring for definitions and units)."""
    return clip_sums(joints, fps, feet, **kw).result()


def artifact_physical(path, split: str | None = None, clips=None, **kw) -> dict:
    """Physical metrics of a motion or motion-dataset artifact, frame-weighted over its clips.

    ``split`` keeps one split (only meaningful for datasets); ``clips`` a list of names or indices.
    """
    from motok.data.dataset import MotionFile
    from motok.errors import UnknownNameError
    from motok.progress import make_progress

    total = PhysicalSums()
    with MotionFile(path) as mf:
        which = mf.split_indices(split) if split else list(range(len(mf)))
        if clips is not None:
            which = [mf.index(c) for c in clips]
        if not which:
            raise UnknownNameError(f"{path}: no clip to measure (split {split!r}; splits: {sorted(set(mf.splits))})")
        sk = mf.skeleton
        feet = (tuple(sk.feet_left), tuple(sk.feet_right))
        with make_progress("clips") as bar:
            task = bar.add_task("physical", total=len(which))
            for i in which:
                total.add(clip_sums(mf.frames("joints", i), mf.fps, feet, **kw))
                bar.advance(task)
    out = total.result()
    out.update({"motion": str(path), "split": split})
    return out
