"""Stick-figure rendering of joint positions (metres, Y up) to GIF, MP4 or a PNG contact sheet.

Drawn with Pillow at 2x and box-downsampled, so edges are antialiased without any
per-pixel Python. The camera is a mild perspective (30 degree field of view) at a fixed
elevation and azimuth that follows the root horizontally, smoothed over half a second.
Framing the whole trajectory instead would shrink the figure to a few pixels for any clip
that travels a few metres; following keeps the body large, and the world-fixed checker
floor sliding underneath plus the trajectory line on the floor still show the travel.
The zoom is fixed per clip (fitted to every frame), so the figure never pumps in size.

Azimuth 0 looks at the character from +Z (its front at frame 0, HumanML3D convention);
negative azimuth moves the camera towards -X, the character's right. The camera, the title
layout and the input checks are in :mod:`motok.render.layout`; this module draws.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from PIL import Image, ImageDraw

from motok.atomic import atomic_path
from motok.errors import UserError
from motok.render.layout import Camera, Layout, check_motion, joint_sides, load_font
from motok.render.video import gif_stride, write_video

__all__ = ["Camera", "joint_sides", "render_frames", "render_motion"]

SUFFIXES = (".gif", ".mp4", ".png")
SS = 2  # supersampling factor

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


def _disc(draw: ImageDraw.ImageDraw, x: float, y: float, r: float, fill, outline=None, width: int = 0):
    draw.ellipse([x - r, y - r, x + r, y + r], fill=fill, outline=outline, width=width)


def _header(lay: Layout) -> Image.Image | None:
    """The title band at supersampled resolution, drawn once per clip and pasted per frame."""
    if not lay.lines:
        return None
    img = Image.new("RGB", (lay.size[0] * SS, lay.band * SS), BACKGROUND)
    draw = ImageDraw.Draw(img)
    font = load_font(lay.title_px * SS)
    y = lay.pad * SS
    for line in lay.lines:
        draw.text((img.width / 2, y), line, fill=TEXT, font=font, anchor="ma")
        y += round(lay.title_px * 1.25) * SS
    return img


class _Scene:
    def __init__(self, joints, parents, *, fps=20.0, title=None, size=(480, 480), trajectory=True,
                 contacts=None, foot_joints=None, max_frames=None, elevation=20.0, azimuth=-60.0,
                 colors=None):
        joints, self.parents, self.root = check_motion(joints, parents)
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        self.joints = joints[:max_frames]  # truncate rather than subsample: playback speed stays true
        self.T, J = self.joints.shape[:2]
        self.fps = float(fps)
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.layout = Layout(size, title)
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
        self.font = load_font(self.layout.small_px * SS)
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
    header = _header(Layout((img.width, scene.layout.size[1]), title)) if title else None
    if header is not None:
        band = header.reduce(SS)
        sheet = Image.new("RGB", (img.width, band.height + img.height), BACKGROUND)
        sheet.paste(band, ((img.width - band.width) // 2, 0))
        sheet.paste(img, (0, band.height))
        img = sheet
    from PIL.PngImagePlugin import PngInfo
    from motok.marks import MARK  # how motok knows its own picture again
    info = PngInfo()
    info.add_text("Comment", MARK)
    img.save(path, format="PNG", optimize=False, pnginfo=info)


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
        raise UserError(f"cannot render to {out.name!r}: unknown suffix {suffix or '(none)'!r}; "
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
