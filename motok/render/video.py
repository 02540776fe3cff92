"""Frames to a file: ``.gif`` (Pillow, one shared palette) or ``.mp4`` (H.264 through imageio's
ffmpeg), written atomically. Used by the stick figure and by the MuJoCo rollout renderer."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

import numpy as np
from PIL import Image

from motok.atomic import atomic_path
from motok.errors import UserError
from motok.marks import MARK  # how motok knows its own video again

VIDEO_SUFFIXES = (".gif", ".mp4")


def gif_stride(fps: float) -> int:
    """Frames to skip so a GIF plays at most 50 frames/s: browsers clamp shorter delays to 100 ms."""
    return int(np.ceil(fps / 50.0))


def write_gif(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float) -> None:
    frames = list(frames)
    # One palette from a sample of frames: per-frame palettes make the colours flicker.
    sample = np.concatenate(frames[:: max(1, len(frames) // 8)][:8], axis=0)[::2, ::2]
    palette = Image.fromarray(sample).quantize(255, method=Image.Quantize.MEDIANCUT)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    # GIF delays are whole centiseconds: round the cumulative time so the mean rate is exact.
    ticks = np.round(np.arange(len(images) + 1) * 100.0 / fps)
    durations = [int(d) * 10 for d in np.maximum(np.diff(ticks), 1)]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], loop=0, comment=MARK.encode(),
                   duration=durations if len(images) > 1 else durations[0], optimize=False)


def write_mp4(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float) -> None:
    """H.264 in yuv420p, which every player reads; frame sizes must be even."""
    import imageio.v2 as imageio

    writer = imageio.get_writer(str(path), format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                pixelformat="yuv420p", macro_block_size=1, quality=7, ffmpeg_log_level="error",
                                output_params=["-metadata", f"comment={MARK}"])
    try:
        for frame in frames:
            writer.append_data(frame)
    finally:
        writer.close()


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float) -> Path:
    """Write ``(H, W, 3) uint8`` frames at ``fps`` to ``path`` by its suffix; the file appears
    only when complete. For a GIF, pass every ``gif_stride(fps)``-th frame and ``fps / stride``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise UserError(f"cannot write video to {path.name!r}: use one of {', '.join(VIDEO_SUFFIXES)}")
    with atomic_path(path) as tmp:
        (write_gif if suffix == ".gif" else write_mp4)(frames, tmp, fps)
    return path
