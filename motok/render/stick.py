"""Stick-figure rendering of joint positions (metres, Y up) to GIF, MP4 or a PNG contact sheet.

Drawn with Pillow at 2x and box-downsampled, so edges are antialiased without any
per-pixel Python. The camera is a mild perspective (30 degree field of view) at a fixed
elevation and azimuth that follows the root horizontally, smoothed over half a second.
Framing the whole trajectory instead would shrink the figure to a few pixels for any clip
that travels a few metres; following keeps the body large, and the world-fixed checker
floor sliding underneath plus the trajectory line on the floor still show the travel.
The zoom is fixed per clip (fitted to every frame), so the figure never pumps in size.

Azimuth 0 looks at the character from +Z (its front at frame 0, HumanML3D convention);
negative azimuth moves the camera towards -X, the character's right.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from motok.atomic import atomic_path
from motok.render.video import gif_stride, write_video

SUFFIXES = (".gif", ".mp4", ".png")
SS = 2  # supersampling factor
FOV = np.deg2rad(30.0)

BACKGROUND = (246, 246, 243)
FLOOR_LIGHT = (214, 218, 224)
FLOOR_DARK = (190, 196, 205)
SHADOW = (160, 164, 172)
LEFT = (38, 110, 215)
RIGHT = (222, 68, 48)
CENTRE = (55, 58, 70)
TRAJ_PAST = (120, 70, 170)
TRAJ_FUTURE = (200, 188, 214)
CONTACT = (20, 170, 90)
TEXT = (40, 40, 48)
TEXT_DIM = (110, 110, 118)

BONE_WIDTH = 0.032  # metres; widths scale with perspective like the bones themselves
HEAD_RADIUS = 0.085
TILE = 0.5  # checker tile edge, metres


def _font(px: int):
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


class _Layout:
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
        self.lines = _wrap(title, _font(self.title_px), w - 2 * pad, max_lines) if title else []
        self.band = (len(self.lines) * round(self.title_px * 1.25) + 2 * pad) if self.lines else 0
        self.pad = pad
        # Leave room at the bottom for the frame counter so it never covers the feet.
        self.viewport = (0.0, float(self.band), float(w), float(h - self.band - self.small_px * 1.6))


class Camera:
    """Per-clip camera: ``project(points, t)`` gives output-pixel coordinates and depth."""

    def __init__(self, joints: np.ndarray, root: int, fps: float, layout: _Layout,
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
        joints, _, root = _check(joints, parents)
        return cls(joints, root, fps, _Layout(size, title), elevation, azimuth)


def _smooth(x: np.ndarray, win: int) -> np.ndarray:
    win = min(win, len(x) - (1 - len(x) % 2))
    if win <= 1:
        return x.astype(np.float64)
    xp = np.pad(x, ((win // 2, win // 2), (0, 0)), mode="edge")
    c = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(xp, 0)])
    return (c[win:] - c[:-win]) / win


def _check(joints, parents) -> tuple[np.ndarray, np.ndarray]:
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
    _bfs(parents)  # raises on a cycle or a missing root
    return joints, parents, int(np.flatnonzero(parents < 0)[0])


def _bfs(parents: np.ndarray) -> list[int]:
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
    order = _bfs(parents)
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


def _disc(draw: ImageDraw.ImageDraw, x: float, y: float, r: float, fill, outline=None, width: int = 0):
    draw.ellipse([x - r, y - r, x + r, y + r], fill=fill, outline=outline, width=width)


def _header(lay: _Layout) -> Image.Image | None:
    """The title band at supersampled resolution, drawn once per clip and pasted per frame."""
    if not lay.lines:
        return None
    img = Image.new("RGB", (lay.size[0] * SS, lay.band * SS), BACKGROUND)
    draw = ImageDraw.Draw(img)
    font = _font(lay.title_px * SS)
    y = lay.pad * SS
    for line in lay.lines:
        draw.text((img.width / 2, y), line, fill=TEXT, font=font, anchor="ma")
        y += round(lay.title_px * 1.25) * SS
    return img


class _Scene:
    def __init__(self, joints, parents, *, fps=20.0, title=None, size=(480, 480), trajectory=True,
                 contacts=None, foot_joints=None, max_frames=None, elevation=20.0, azimuth=-60.0,
                 colors=None):
        joints, self.parents, self.root = _check(joints, parents)
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        self.joints = joints[:max_frames]  # truncate rather than subsample: playback speed stays true
        self.T, J = self.joints.shape[:2]
        self.fps = float(fps)
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.layout = _Layout(size, title)
        self.cam = Camera(self.joints, self.root, self.fps, self.layout, elevation, azimuth)
        self.trajectory = trajectory
        side = joint_sides(self.joints[0], self.parents)
        cols = np.asarray([{1: LEFT, -1: RIGHT, 0: CENTRE}[int(s)] for s in side] if colors is None
                          else colors, dtype=np.float64)
        if cols.shape != (J, 3):
            raise ValueError(f"colors must be {J} RGB triples (0-255), got shape {cols.shape}")
        self.colors = [tuple(int(v) for v in c) for c in cols]
        self.dot_colors = [tuple(int(v) for v in c * 0.6) for c in cols]
        self.tints = [tuple(int(v) for v in 0.2 * c + 0.8 * 255) for c in cols]
        self.bones = np.array([(p, j) for j, p in enumerate(self.parents) if p >= 0], dtype=np.int64).reshape(-1, 2)
        leaves = [j for j in range(J) if side[j] == 0 and j not in self.parents and self.parents[j] >= 0]
        self.head = max(leaves, key=lambda j: self.joints[0, j, 1]) if leaves else None
        if (contacts is None) != (foot_joints is None):
            raise ValueError("contacts and foot_joints must be given together")
        self.contacts, self.feet = contacts, foot_joints
        if contacts is not None:
            self.contacts, self.feet = np.asarray(contacts).astype(bool), np.asarray(foot_joints).reshape(-1)
            if self.contacts.shape[0] < self.T or self.contacts.shape[1:] != self.feet.shape:
                raise ValueError(f"contacts must be (T={self.T}, {len(self.feet)}) to match "
                                 f"foot_joints, got {self.contacts.shape}")
            if ((self.feet < 0) | (self.feet >= J)).any():
                raise ValueError(f"foot_joints out of range for {J} joints: {self.feet.tolist()}")
        self.floor_traj = self.joints[:, self.root] * [1.0, 0.0, 1.0] + [0.0, 0.002, 0.0]
        self.font = _font(self.layout.small_px * SS)
        self.header = _header(self.layout)

    def _floor(self, draw: ImageDraw.ImageDraw, t: int) -> None:
        cam, rad = self.cam, self.cam.floor_radius
        tx, tz = cam.targets[t, 0], cam.targets[t, 2]
        i = np.arange(np.floor((tx - rad) / TILE), np.ceil((tx + rad) / TILE) + 1)
        k = np.arange(np.floor((tz - rad) / TILE), np.ceil((tz + rad) / TILE) + 1)
        gx, gz = np.meshgrid(i * TILE, k * TILE, indexing="ij")
        uv, depth = cam.project(np.stack([gx, np.zeros_like(gx), gz], -1), t)
        uv *= SS
        quads = np.stack([uv[:-1, :-1], uv[1:, :-1], uv[1:, 1:], uv[:-1, 1:]], 2)  # (ni, nk, 4, 2)
        near = np.minimum.reduce([depth[:-1, :-1], depth[1:, :-1], depth[1:, 1:], depth[:-1, 1:]])
        cx, cz = gx[:-1, :-1] + TILE / 2 - tx, gz[:-1, :-1] + TILE / 2 - tz
        # Fade tiles into the background with distance: a pool of floor, no visible edge.
        fade = np.clip(1.0 - (cx**2 + cz**2) / rad**2, 0.0, 1.0) ** 0.8
        dark = ((i[:-1, None] + k[None, :-1]) % 2).astype(bool)
        base = np.where(dark[..., None], FLOOR_DARK, FLOOR_LIGHT)
        col = (np.asarray(BACKGROUND) + (base - np.asarray(BACKGROUND)) * fade[..., None]).round().astype(int)
        for a, b in zip(*np.nonzero((fade > 0.02) & (near > cam.near))):
            draw.polygon([tuple(p) for p in quads[a, b].tolist()], fill=tuple(col[a, b].tolist()))

    def _polyline(self, draw, pts: np.ndarray, t: int, fill, width: int) -> None:
        uv, depth = self.cam.project(pts, t)
        ok = depth > self.cam.near
        uv = (uv * SS).tolist()
        # Split where points fall behind the near plane, so no segment wraps through the eye.
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
        for s, e in zip(edges[::2], edges[1::2]):
            if e - s >= 2:
                draw.line(uv[s:e], fill=fill, width=width, joint="curve")

    def draw(self, t: int) -> np.ndarray:
        w, h = self.layout.size
        img = Image.new("RGB", (w * SS, h * SS), BACKGROUND)
        draw = ImageDraw.Draw(img)
        cam = self.cam
        self._floor(draw, t)
        px_per_m = cam.focal * SS / cam.dist
        if self.trajectory and self.T > 1:
            lw = max(1, round(0.012 * px_per_m))
            self._polyline(draw, self.floor_traj[t:], t, TRAJ_FUTURE, lw)
            self._polyline(draw, self.floor_traj[: t + 1], t, TRAJ_PAST, 2 * lw)
        pose = self.joints[t]
        uv, depth = cam.project(pose, t)
        uv *= SS
        if len(self.bones):
            shadow, _ = cam.project(pose * [1.0, 0.0, 1.0], t)
            sw = max(1, round(0.7 * BONE_WIDTH * px_per_m))
            for p, j in (shadow[self.bones] * SS).tolist():
                draw.line([tuple(p), tuple(j)], fill=SHADOW, width=sw)
        # Painter's algorithm: bones by midpoint depth, far to near.
        mid = 0.5 * (depth[self.bones[:, 0]] + depth[self.bones[:, 1]])
        dot = depth.copy()  # a dot goes over every bone that meets it, else knees hide feet
        np.minimum.at(dot, self.bones.ravel(), np.repeat(mid, 2))
        items = [(d, 0, j, p) for d, (p, j) in zip(mid.tolist(), self.bones.tolist())]
        items += [(d - 1e-4, 1, j, -1) for j, d in enumerate(dot.tolist())]
        contact = set()
        if self.contacts is not None:
            contact = {int(f) for f, c in zip(self.feet, self.contacts[t]) if c}
        for d, kind, j, p in sorted(items, key=lambda it: -it[0]):
            if d <= cam.near:
                continue
            scale = cam.focal * SS / d
            bw = max(2.0, BONE_WIDTH * scale)
            x, y = uv[j]
            if kind == 0:
                x0, y0 = uv[p]
                draw.line([(x0, y0), (x, y)], fill=self.colors[j], width=round(bw))
                for cx, cy in ((x0, y0), (x, y)):  # round caps so joints do not look broken
                    _disc(draw, cx, cy, bw / 2, self.colors[j])
            elif j == self.head:
                _disc(draw, x, y, HEAD_RADIUS * scale, self.tints[j], self.colors[j], max(2, round(0.7 * bw)))
            elif j in contact:
                _disc(draw, x, y, 1.1 * bw, CONTACT, (255, 255, 255), SS)
            else:
                _disc(draw, x, y, 0.42 * bw, self.dot_colors[j])
        self._text(img, draw, t)
        return np.asarray(img.reduce(SS))

    def frames(self, indices=None) -> Iterator[np.ndarray]:
        for t in range(self.T) if indices is None else [int(i) for i in indices]:
            if not 0 <= t < self.T:
                raise IndexError(f"frame index {t} out of range for {self.T} frames")
            yield self.draw(t)

    def _text(self, img: Image.Image, draw: ImageDraw.ImageDraw, t: int) -> None:
        if self.header is not None:
            img.paste(self.header, (0, 0))
        w, h = img.size
        m = round(self.layout.small_px * 0.5) * SS
        draw.text((m, h - m), f"frame {t + 1}/{self.T}   {t / self.fps:.2f} s", fill=TEXT_DIM,
                  font=self.font, anchor="ld")
        x = w - m
        for label, col in (("right", RIGHT), ("left", LEFT)):
            draw.text((x, h - m), label, fill=col, font=self.font, anchor="rd")
            x -= self.font.getlength(label + "  ")


def render_frames(joints, parents, *, fps: float = 20.0, title: str | None = None,
                  size: tuple[int, int] = (480, 480), trajectory: bool = True, contacts=None,
                  foot_joints=None, max_frames: int | None = None, elevation: float = 20.0,
                  azimuth: float = -60.0, colors=None, indices: Sequence[int] | None = None) -> np.ndarray:
    """Render ``joints (T, J, 3)`` to ``(N, H, W, 3) uint8`` frames (all, or ``indices``).

    ``colors`` overrides the left/right/centre colouring: one RGB triple per joint, used for
    the bone from its parent and for its dot.
    """
    scene = _Scene(joints, parents, fps=fps, title=title, size=size, trajectory=trajectory,
                   contacts=contacts, foot_joints=foot_joints, max_frames=max_frames,
                   elevation=elevation, azimuth=azimuth, colors=colors)
    return np.stack(list(scene.frames(indices)))


def _write_sheet(scene: _Scene, path: str, n: int, title: str | None) -> None:
    idx = np.unique(np.linspace(0, scene.T - 1, max(1, min(n, scene.T))).round().astype(int))
    strip = np.concatenate(list(scene.frames(idx)), axis=1)
    w = scene.layout.size[0]
    strip[:, w - 1 :: w][:, :-1] = (200, 200, 200)  # hairline between panels
    img = Image.fromarray(strip)
    header = _header(_Layout((img.width, scene.layout.size[1]), title)) if title else None
    if header is not None:
        band = header.reduce(SS)
        sheet = Image.new("RGB", (img.width, band.height + img.height), BACKGROUND)
        sheet.paste(band, ((img.width - band.width) // 2, 0))
        sheet.paste(img, (0, band.height))
        img = sheet
    img.save(path, format="PNG", optimize=False)


def render_motion(joints, parents, out_path, *, fps: float = 20.0, title: str | None = None,
                  size: tuple[int, int] = (480, 480), trajectory: bool = True, contacts=None,
                  foot_joints=None, max_frames: int | None = None, elevation: float = 20.0,
                  azimuth: float = -60.0, colors=None, sheet_frames: int = 6) -> Path:
    """Render a motion to ``.gif`` (loops), ``.mp4`` (H.264, yuv420p) or ``.png``.

    The PNG is a contact sheet: ``sheet_frames`` evenly spaced frames side by side, each
    ``size``, with the title once above them. MP4 sizes are rounded up to even numbers
    (yuv420p needs them). The file appears atomically: it is written under a temporary
    name in the same directory and renamed on success.
    """
    out = Path(out_path)
    suffix = out.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"cannot render to {out.name!r}: unknown suffix {suffix or '(none)'!r}; "
                         f"accepted: {', '.join(SUFFIXES)}")
    if suffix == ".mp4":
        size = tuple(int(s) + int(s) % 2 for s in size)
    sheet_title = title if suffix == ".png" else None
    scene = _Scene(joints, parents, fps=fps, title=None if sheet_title else title, size=size,
                   trajectory=trajectory, contacts=contacts, foot_joints=foot_joints,
                   max_frames=max_frames, elevation=elevation, azimuth=azimuth, colors=colors)
    if suffix == ".png":
        with atomic_path(out) as tmp:
            _write_sheet(scene, tmp, sheet_frames, sheet_title)
        return out
    step = gif_stride(scene.fps) if suffix == ".gif" else 1
    return write_video(scene.frames(range(0, scene.T, step)), out, scene.fps / step)
