"""What ``motok view`` shows: the clips of a motion file played kinematically on the humanoid, or a
controller (an expert run, a distilled prior) tracking the clips of its reference library, each
clip as the humanoid's poses per frame with the reference as a ghost.

A controller's clip is simulated the way the imitation evaluation plays it (its own ``play``:
frame 0 of the reference, the most likely action each control step, until the clip ends or the
tracking fails), when the clip is first shown, then played back in real time; so what the window
shows is what ``motok control expert eval`` and ``control eval`` measure, frame for frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from motok import progress
from motok.data.dataset import MotionFile, clip_index, select_clips
from motok.errors import UserError


def control_api() -> SimpleNamespace:
    """The control stage's functions the viewer calls, imported in this one place: the loader of
    an expert or prior, the evaluation's playback of a clip, and a run's reference library."""
    from motok.control import runs
    from motok.control.priors.load import load_controller
    from motok.control.tasks.imitation import play

    return SimpleNamespace(load_controller=load_controller, play=play, run_library=runs.run_library)


@dataclass
class Shown:
    """One clip as the window draws it."""

    qpos: np.ndarray  # (T, nq) the humanoid's pose at each frame
    ghost: np.ndarray | None = None  # (T, J, 3) the reference's body positions (MuJoCo world), or None
    note: str = ""  # how the clip went, for the overlay (a controller's outcome)


class Source:
    """Clips to show: ``names``, their frame rate ``fps``, the humanoid ``hum`` and :meth:`shown`,
    which computes a clip once and keeps it (switching back to a clip is instant)."""

    names: list[str]
    fps: float
    hum: object

    def __init__(self):
        self._cache: dict[int, Shown] = {}

    def shown(self, i: int) -> Shown:
        if i not in self._cache:
            self._cache[i] = self._make(i)
        return self._cache[i]

    def _make(self, i: int) -> Shown:
        raise NotImplementedError

    def index(self, clip) -> int:
        """The position of ``clip`` (a name, or an index as a string or int) among :attr:`names`."""
        key = int(clip) if isinstance(clip, str) and clip.isdigit() else clip
        return clip_index(self.names, key, within=" among the clips to view")


class MotionSource(Source):
    """The clips of a motion or motion-dataset artifact (those matching ``clips``, a glob), each
    retargeted to the humanoid at the file's own frame rate, so frame ``t`` is the file's frame ``t``.
    The humanoid is the file's default one (built from its skeleton and cached, as ``motok sim``
    builds it) unless ``humanoid`` names an MJCF."""

    def __init__(self, data, humanoid=None, clips: str | None = None):
        super().__init__()
        from motok.sim.humanoid import load_humanoid
        from motok.sim.reference import humanoid_for

        self.data = data
        with MotionFile(data) as mf:
            self.fps = float(mf.fps)
        self.names = select_clips(data, clips)
        self.hum = load_humanoid(humanoid) if humanoid else humanoid_for(data)

    def _make(self, i: int) -> Shown:
        from motok.sim.reference import build_library

        # One clip at a time, never cached on disk: a dataset of thousands of clips opens at once.
        lib = build_library(self.hum, self.data, control_hz=self.fps, clips=[self.names[i]])
        return Shown(qpos=lib.qpos)


class ControlSource(Source):
    """A controller tracking the clips of its reference library: an expert run or a distilled
    prior (its posterior and decoder; ``codebooks``: the first M only), on its own training clips
    unless ``data`` (another motion artifact) and/or ``clips`` (a glob) say otherwise."""

    def __init__(self, expert=None, prior=None, codebooks: int | None = None, data=None, clips: str | None = None):
        super().__init__()
        api = control_api()
        self._play = api.play
        ctl = api.load_controller(expert, prior, codebooks)  # checks --codebooks against the prior
        self.cfg, self.hum, self.policy, meta = ctl.cfg, ctl.humanoid, ctl.policy, ctl.meta
        hz = self.cfg.env.control_hz or self.hum.control_hz
        _, self.lib = api.run_library(expert or prior, meta, self.hum, hz, data, clips)
        self.names, self.fps = list(self.lib.names), float(self.lib.fps)
        # As the evaluation plays: no episode time limit, a clip ends at its last frame or a failure.
        self.task = replace(self.cfg.task, max_episode_seconds=1e9)

    def _make(self, i: int) -> Shown:
        progress.info(f"simulating {self.names[i]} ...")
        res = self._play(self.hum, self.policy, self.lib, np.array([i]), self.cfg.env, self.task, self.cfg.action,
                         keep_qpos=True)
        n = int(res["played"][0]) + 1
        return Shown(qpos=res["qpos"][:n], ghost=res["ref"][0, :n],
                     note=outcome(bool(res["success"][0]), (n - 1) / self.fps,
                                  (self.lib.lengths[i] - 1 - self.task.goal_frames) / self.fps))


def outcome(success: bool, seconds: float, clip_seconds: float) -> str:
    """How a controller did on a clip, in a few words for the overlay."""
    if success:
        return f"tracked to the end ({clip_seconds:.1f} s)"
    return f"failed after {seconds:.1f} of {clip_seconds:.1f} s"
