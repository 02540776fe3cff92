"""What the live viewer shows, and when: the clip and frame for a wall-clock time, what the keys
do (pause, next and previous clip, restart), the bones of the reference's ghost and the overlay
text. No MuJoCo and no window here, so all of it is tested without a display; the window
(:mod:`motok.view.window`) only asks these functions and draws the answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# GLFW key codes, as the passive viewer's key callback passes them (a letter is its upper-case
# ASCII code). Space and the arrows do nothing in MuJoCo's own passive viewer; N, P and R also
# flip one of its visual flags, which the window puts back (motok.view.window).
KEYS = {32: "pause", 78: "next", 262: "next", 80: "previous", 263: "previous", 82: "restart", 259: "restart"}
HELP = "Space pause   N next clip   P previous   R restart   Tab menus"  # arrows and Backspace too (KEYS)
# A clip's last frame stays this long before the clip starts over, so where a policy fell (or
# how a motion ends) can be seen before the loop.
HOLD_SECONDS = 1.0


def key_action(key: int) -> str | None:
    """The viewer's action for a GLFW key code (``pause``, ``next``, ``previous``, ``restart``),
    None for a key MuJoCo's viewer keeps (camera, visual flags, Tab for its menus)."""
    return KEYS.get(int(key))


@dataclass
class Playback:
    """Which clip of ``clips`` is shown and how far into it, on a clock the caller passes (seconds,
    any origin): frames advance in real time at ``fps`` unless paused."""

    clips: int  # how many clips there are to switch between
    fps: float  # frames per second of the clips shown
    clip: int = 0  # the clip shown
    paused: bool = False
    start: float = 0.0  # clock time at which the clip's frame 0 was (or would have been) shown
    paused_at: float = 0.0  # clock time of the pause, while paused

    def __post_init__(self):
        if self.clips < 1:
            raise ValueError("nothing to show: no clips")
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, not {self.fps}")
        self.clip %= self.clips

    def elapsed(self, now: float) -> float:
        """Seconds of the current clip played by clock time ``now`` (time stands still while paused)."""
        return (self.paused_at if self.paused else now) - self.start

    def frame(self, now: float, length: int) -> int:
        """The frame of a clip of ``length`` frames to show at ``now``: real time from its start,
        the last frame held :data:`HOLD_SECONDS`, then the clip again from its first frame."""
        if length < 1:
            raise ValueError("a clip to show has at least one frame")
        cycle = length + int(round(HOLD_SECONDS * self.fps))
        k = int(np.floor(max(self.elapsed(now), 0.0) * self.fps + 1e-9)) % cycle
        return min(k, length - 1)

    def press(self, action: str | None, now: float) -> bool:
        """Apply a key's ``action`` at ``now``; True when another clip is to be shown (the caller
        loads it). Switching or restarting while paused shows the first frame, still paused."""
        if action == "pause":
            if self.paused:
                self.start += now - self.paused_at  # the clip goes on where it stood
            else:
                self.paused_at = now
            self.paused = not self.paused
            return False
        if action in ("next", "previous", "restart"):
            before = self.clip
            if action != "restart":
                self.clip = (self.clip + (1 if action == "next" else -1)) % self.clips
            self.start = self.paused_at = now
            return self.clip != before
        return False


class FlagGuard:
    """Keeps MuJoCo's visual flags from following the viewer's keys: N, P and R are also MuJoCo's
    shortcuts for flags (islands, contact splits, reflections), which its window flips on the same
    key press, at the sync just before or just after the one at which the viewer sees the key. So
    for ``seconds`` after a key the flags are put back as they were two syncs before it. Flags are
    any values the caller compares and writes back (MuJoCo's scene and option flag arrays)."""

    def __init__(self, flags, seconds: float = 0.3):
        self.before = self.flags = flags
        self.seconds, self.until = seconds, float("-inf")

    def key(self, now: float) -> None:
        """One of the viewer's keys was seen at ``now``."""
        if now >= self.until:
            self.flags = self.before
        self.until = now + self.seconds

    def synced(self, flags, now: float):
        """The flags the window has after a sync at ``now``: None to keep them, else those to write back."""
        if now < self.until:
            return self.flags
        self.before, self.flags = self.flags, flags
        return None


def bones(pos: np.ndarray, parents) -> tuple[np.ndarray, np.ndarray]:
    """The ghost's bones: ``(from, to)`` world points ``(B, 3)``, one per joint with a parent, from
    the parent's position to the joint's in ``pos`` ``(J, 3)`` (skeleton order)."""
    parents = np.asarray(parents)
    child = np.flatnonzero(parents >= 0)
    pos = np.asarray(pos, dtype=np.float64)
    return pos[parents[child]], pos[child]


def overlay(name: str, clip: int, clips: int, frame: int, length: int, fps: float, paused: bool,
            note: str = "") -> list[tuple[str, str, str]]:
    """The viewer's text boxes as ``(corner, labels, values)``: the clip, its time and state (and
    ``note``, how a controller did) top left, the keys bottom left."""
    state = "paused" if paused else "playing"
    values = (f"{name} ({clip + 1}/{clips})\n{frame / fps:5.2f} / {(length - 1) / fps:.2f} s\n"
              f"{state}{' - ' + note if note else ''}")
    return [("top left", "clip\ntime\nstate", values), ("bottom left", "keys", HELP)]
