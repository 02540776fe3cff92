"""Where a stick-figure render puts things: input checks, the skeleton's tree and its sides,
the title layout, and the per-clip camera that projects metres to output pixels.

Drawing (:mod:`motok.render.stick`) only consumes what this module computes, so tests can ask
where a joint lands without drawing a frame.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from PIL import ImageFont

FOV = np.deg2rad(30.0)


def load_font(px: int):
    try:
        return ImageFont.load_default(size=px)
    except (TypeError, OSError):  # Pillow < 10.1 or no FreeType: fixed-size bitmap font
        return ImageFont.load_default()


def _wrap(text: str, font, width: float, max_lines: int = 3) -> list[str]:
    lines: list[str] = []
    for word in text.split():
        if lines and font.getlength(lines[-1] + " " + word) <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    if len(lines) > max_lines:
        lines = lines[:max_lines]
        while lines[-1] and font.getlength(lines[-1] + "...") > width:
            lines[-1] = lines[-1][:-1]
        lines[-1] += "..."
    return lines


class Layout:
    """Fonts, the wrapped title and the viewport left for the figure, in output pixels."""

    def __init__(self, size: tuple[int, int], title: str | None):
        w, h = int(size[0]), int(size[1])
        if w < 32 or h < 32:
            raise ValueError(f"size {size} is too small; need at least 32x32 pixels")
        self.size = (w, h)
        self.title_px = max(10, round(min(w, h) * 0.042))
        self.small_px = max(9, round(min(w, h) * 0.03))
        pad = round(self.title_px * 0.5)
        # At most a third of the height goes to the title, however long the caption.
        max_lines = max(1, min(3, int((h / 3 - 2 * pad) // round(self.title_px * 1.25))))
        self.lines = _wrap(title, load_font(self.title_px), w - 2 * pad, max_lines) if title else []
        self.band = (len(self.lines) * round(self.title_px * 1.25) + 2 * pad) if self.lines else 0
        self.pad = pad
        # Leave room at the bottom for the frame counter so it never covers the feet.
        self.viewport = (0.0, float(self.band), float(w), float(h - self.band - self.small_px * 1.6))


class Camera:
    """Per-clip camera: ``project(points, t)`` gives output-pixel coordinates and depth."""

    def __init__(self, joints: np.ndarray, root: int, fps: float, layout: Layout,
                 elevation: float = 20.0, azimuth: float = -60.0):
        el = np.deg2rad(np.clip(elevation, -89.0, 89.0))
        az = np.deg2rad(azimuth)
        self.eye_dir = np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
        f = -self.eye_dir
        r = np.cross(f, [0.0, 1.0, 0.0])
        r /= np.linalg.norm(r)
        self.basis = np.stack([r, np.cross(r, f), f])  # rows: right, up, forward
        track = _smooth(joints[:, root, [0, 2]], int(round(fps * 0.5)) | 1)
        ys = joints[..., 1]
        mid = 0.5 * (ys.min() + ys.max())
        self.targets = np.column_stack([track[:, 0], np.full(len(track), mid), track[:, 1]])
        reach = max(float(np.linalg.norm(joints - self.targets[:, None], axis=-1).max()), 0.25)
        self.dist = reach / np.sin(FOV / 2)
        self.eyes = self.targets + self.dist * self.eye_dir
        x0, y0, w, h = layout.viewport
        self.focal = 0.5 * min(w, h) / np.tan(FOV / 2)
        self.centre = np.array([x0 + w / 2, y0 + h / 2])
        # Tighten the sphere bound to the projected extent over the whole clip, then recentre.
        uv, _ = self.project(joints)
        lo, hi = uv.reshape(-1, 2).min(0) - self.centre, uv.reshape(-1, 2).max(0) - self.centre
        half = np.maximum((hi - lo) / 2, 1e-6)
        scale = 0.84 * min(w / 2 / half[0], h / 2 / half[1])
        self.focal *= scale
        self.centre -= scale * (hi + lo) / 2
        self.near = 0.15 * self.dist
        self.floor_radius = max(2.0, 3.0 * reach)

    def project(self, points: np.ndarray, t: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``points (T, ..., 3)`` for all frames, or ``(..., 3)`` seen from frame ``t``."""
        points = np.asarray(points, dtype=np.float64)
        if t is None:
            eye = self.eyes.reshape((len(self.eyes),) + (1,) * (points.ndim - 2) + (3,))
        else:
            eye = self.eyes[t]
        cam = (points - eye) @ self.basis.T
        depth = cam[..., 2]
        z = np.maximum(depth, 1e-6)
        uv = np.stack([cam[..., 0] / z, -cam[..., 1] / z], -1) * self.focal + self.centre
        return uv, depth

    @classmethod
    def fit(cls, joints, parents, *, fps: float = 20.0, title: str | None = None,
            size=(480, 480), elevation: float = 20.0, azimuth: float = -60.0) -> "Camera":
        """The camera :func:`render_frames` uses for the same arguments (tests use it)."""
        joints, _, root = check_motion(joints, parents)
        return cls(joints, root, fps, Layout(size, title), elevation, azimuth)


def _smooth(x: np.ndarray, win: int) -> np.ndarray:
    win = min(win, len(x) - (1 - len(x) % 2))
    if win <= 1:
        return x.astype(np.float64)
    xp = np.pad(x, ((win // 2, win // 2), (0, 0)), mode="edge")
    c = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(xp, 0)])
    return (c[win:] - c[:-win]) / win


def check_motion(joints, parents) -> tuple[np.ndarray, np.ndarray, int]:
    joints = np.asarray(joints, dtype=np.float64)
    parents = np.asarray(parents).astype(np.int64)
    if joints.ndim != 3 or joints.shape[-1] != 3 or len(joints) == 0:
        raise ValueError(f"joints must be (T, J, 3) with T >= 1, got shape {joints.shape}")
    if parents.shape != (joints.shape[1],):
        raise ValueError(f"parents must be ({joints.shape[1]},) to match joints, got {parents.shape}")
    if (parents >= len(parents)).any() or (parents < -1).any() or (parents == np.arange(len(parents))).any():
        raise ValueError(f"parents must be -1 or another joint's index, got {parents.tolist()}")
    if not np.isfinite(joints).all():
        raise ValueError("joints contain NaN or infinite values")
    tree_order(parents)  # raises on a cycle or a missing root
    return joints, parents, int(np.flatnonzero(parents < 0)[0])


def tree_order(parents: np.ndarray) -> list[int]:
    children = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    order = [int(j) for j in np.flatnonzero(parents < 0)]
    for j in order:
        order.extend(children[j])
    if len(order) != len(parents) or not order:
        raise ValueError(f"parents must form a tree with a -1 root, got {parents.tolist()}")
    return order


def joint_sides(rest: np.ndarray, parents: Sequence[int]) -> np.ndarray:
    """+1 left, -1 right, 0 centre per joint, from one pose ``rest (J, 3)`` facing +Z.

    Mirror limbs are found from the tree, not from thresholds: at a centre joint, two
    children whose subtrees have the same size are a left/right pair, and the one whose
    subtree lies further towards +X is the left. This survives a leaning or twisted first
    frame, where per-joint x thresholds would put the head on one side. Joints below a
    sided joint inherit its side.
    """
    parents = np.asarray(parents, dtype=np.int64)
    order = tree_order(parents)
    members = [[j] for j in range(len(parents))]
    for j in reversed(order):
        if parents[j] >= 0:
            members[parents[j]].extend(members[j])
    side = np.zeros(len(parents), dtype=np.int64)
    for u in order:
        kids = [int(c) for c in np.flatnonzero(parents == u)]
        if side[u] != 0:
            side[kids] = side[u]
            continue
        by_size: dict[int, list[int]] = {}
        for c in kids:
            by_size.setdefault(len(members[c]), []).append(c)
        for group in by_size.values():
            if len(group) >= 2:
                xs = [rest[members[c], 0].mean() for c in group]
                lo, hi = group[int(np.argmin(xs))], group[int(np.argmax(xs))]
                if max(xs) - min(xs) > 1e-6:
                    side[hi], side[lo] = 1, -1
    return side
