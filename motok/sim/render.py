"""Offscreen video of humanoid trajectories: MuJoCo's renderer (EGL or OSMesa on headless
machines), else the stick figure of ``motok.render.stick`` drawn from the body positions.

MuJoCo chooses its GL backend once, from ``MUJOCO_GL``, when ``mujoco`` is first imported; its
default (GLFW) needs a display. The ``motok`` command sets ``MUJOCO_GL=egl`` at start when there
is no display and the user did not choose (:func:`motok.cli.common.choose_mujoco_gl`); importing
motok never changes the environment. Library users on a headless machine set it themselves
before anything imports mujoco (``os.environ.setdefault("MUJOCO_GL", "egl")``, or ``osmesa``);
without a working backend :func:`render_trajectory` falls back to the stick figure. A ``ghost``
trajectory (the reference) can be drawn as a translucent second body.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from motok.errors import UserError
from motok.render.video import gif_stride, write_video
from motok.sim.humanoid import Humanoid, from_mj
from motok.sim.kinematics import body_states

SUFFIXES = (".mp4", ".gif")


def _add_markers(scn, pos: np.ndarray, rgba: np.ndarray, radius: np.ndarray) -> None:
    """Spheres at world positions ``(K, 3)`` with colours ``(K, 4)`` and radii ``(K,)``, as far as
    the scene has room; non-finite positions are not drawn."""
    import mujoco

    eye = np.eye(3).reshape(-1)
    for p, c, r in zip(pos, rgba, radius):
        if scn.ngeom >= scn.maxgeom or not np.isfinite(p).all():
            continue
        mujoco.mjv_initGeom(scn.geoms[scn.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, np.array([r, 0, 0]),
                            np.asarray(p, dtype=np.float64), eye, np.asarray(c, dtype=np.float32))
        scn.ngeom += 1


# The follow camera: 3.4 m from what it frames, 12 degrees down; it backs off and tilts down to keep
# distant markers (a navigation target 5-10 m away) in the picture with the character.
CAM_DISTANCE, CAM_ELEVATION, CAM_AZIMUTH = 3.4, -12.0, 120.0
CAM_FOVY_MARGIN = 2.2  # distance per metre of the framed radius: MuJoCo's 45-degree fovy, with room
LOOK_HEIGHT = 0.9


def framing(root: np.ndarray, points: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Camera look-at point, distance and elevation (degrees) that frame the character's ``root``
    ``(3,)`` and the finite rows of ``points`` ``(K, 3)`` (MuJoCo world, z up): the centre of
    their ground-plane bounding box at chest height, far enough back that the box's half-diagonal
    stays inside the view, and more downward the farther back, so points on the floor show."""
    xy = root[None, :2]
    if points is not None and len(points):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(1)]
        xy = np.concatenate([xy, pts[:, :2]], 0)
    lo, hi = xy.min(0), xy.max(0)
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    dist = max(CAM_DISTANCE, CAM_FOVY_MARGIN * radius + 1.0)
    elevation = CAM_ELEVATION - 18.0 * min(1.0, (dist - CAM_DISTANCE) / 10.0)
    return np.array([centre[0], centre[1], LOOK_HEIGHT]), dist, elevation


def _frames_mujoco(hum: Humanoid, qpos: np.ndarray, size, ghost: np.ndarray | None, title: str | None,
                   markers=None):
    import mujoco

    m = hum.model
    d = mujoco.MjData(m)
    dg = mujoco.MjData(m) if ghost is not None else None
    renderer = mujoco.Renderer(m, height=size[1], width=size[0])
    # Software GL (llvmpipe behind EGL) spends most of a frame on shadow maps and reflections.
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.azimuth = CAM_AZIMUTH
    opt = mujoco.MjvOption()
    view = None
    try:
        for t in range(len(qpos)):
            d.qpos[:] = qpos[t]
            mujoco.mj_forward(m, d)
            root = d.xpos[hum.body_ids[0]]
            aim = framing(root, markers[0][min(t, len(markers[0]) - 1)] if markers is not None else None)
            # A camera that follows smoothly: look-at, distance and elevation all eased.
            view = aim if view is None else tuple(0.9 * v + 0.1 * a for v, a in zip(view, aim))
            cam.lookat[:], cam.distance, cam.elevation = view[0], float(view[1]), float(view[2])
            renderer.update_scene(d, camera=cam, scene_option=opt)
            if dg is not None:
                dg.qpos[:] = ghost[min(t, len(ghost) - 1)]
                mujoco.mj_forward(m, dg)
                scn = renderer.scene
                start = scn.ngeom
                mujoco.mjv_addGeoms(m, dg, opt, mujoco.MjvPerturb(), mujoco.mjtCatBit.mjCAT_DYNAMIC, scn)
                for i in range(start, scn.ngeom):
                    scn.geoms[i].rgba[:] = (0.3, 0.55, 0.95, 0.35)
            if markers is not None:
                pos, rgba, radius = markers
                k = min(t, len(pos) - 1)
                _add_markers(renderer.scene, pos[k], rgba[k], radius)
            yield _caption(renderer.render(), title if title is None or isinstance(title, str)
                           else title[min(t, len(title) - 1)])
    finally:
        renderer.close()


def _even(size) -> tuple[int, ...]:
    """``(width, height)`` rounded up to even numbers, which video encoders (yuv420p) need."""
    return tuple(int(s) + int(s) % 2 for s in size)


def _markers(markers, rgba, radius) -> tuple | None:
    """``(pos (T, K, 3), rgba (T, K, 4), radius (K,))`` of the marker arguments of
    :func:`render_trajectory`, or None without markers."""
    if markers is None:
        return None
    pos = np.asarray(markers, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise UserError(f"markers must have shape (T, K, 3), not {pos.shape}")
    return (pos, np.broadcast_to(np.asarray(rgba, dtype=np.float32), pos.shape[:2] + (4,)),
            np.broadcast_to(np.asarray(radius, dtype=np.float64), pos.shape[1:2]))


def trajectory_frames(hum: Humanoid, qpos: np.ndarray, *, size=(640, 480), ghost: np.ndarray | None = None,
                      title=None, markers: np.ndarray | None = None, marker_rgba=(0.9, 0.2, 0.2, 0.8),
                      marker_radius: float | np.ndarray = 0.08):
    """The MuJoCo frames ``(H, W, 3) uint8`` of :func:`render_trajectory`, one per row of ``qpos``,
    as an iterator (for composing videos: two runs side by side); raises where there is no GL."""
    return _frames_mujoco(hum, qpos, _even(size), ghost, title, _markers(markers, marker_rgba, marker_radius))


def _caption(img: np.ndarray, title: str | None) -> np.ndarray:
    if not title:
        return img
    from PIL import Image, ImageDraw, ImageFont

    im = Image.fromarray(img)
    try:
        font = ImageFont.load_default(size=max(12, img.shape[0] // 32))
    except TypeError:  # Pillow < 10.1: fixed-size bitmap font
        font = ImageFont.load_default()
    ImageDraw.Draw(im).text((10, 8), title, fill=(40, 40, 48), font=font)
    return np.asarray(im)


def render_trajectory(hum: Humanoid, qpos: np.ndarray, out, fps: float, *, title=None,
                      ghost: np.ndarray | None = None, size=(640, 480), backend: str = "auto",
                      markers: np.ndarray | None = None, marker_rgba=(0.9, 0.2, 0.2, 0.8),
                      marker_radius: float | np.ndarray = 0.08) -> tuple[Path, str]:
    """Render ``qpos (T, nq)`` to ``out`` (.mp4 or .gif); returns the path and the backend used
    (``mujoco`` or ``stick``). ``backend="stick"`` forces the fallback. ``markers`` ``(T, K, 3)``
    are world points drawn as spheres (a task's targets, keyframe joints, a head target), coloured
    by ``marker_rgba``: one colour, ``(K, 4)`` or ``(T, K, 4)``, of ``marker_radius`` (m, one or
    ``(K,)``); non-finite points are not drawn (markers of a goal not in use); the stick figure
    leaves them out.
    ``title``: one for the whole video, or one per frame (a closed loop's prompt of each moment;
    the stick figure draws the first)."""
    out = Path(out)
    if out.suffix.lower() not in SUFFIXES:
        raise UserError(f"cannot render to {out.name!r}: use one of {', '.join(SUFFIXES)}")
    mk = _markers(markers, marker_rgba, marker_radius)  # refused before anything is made
    out.parent.mkdir(parents=True, exist_ok=True)
    size = _even(size)
    mujoco = backend in ("auto", "mujoco")
    frames = _mujoco_frames(hum, qpos, size, ghost, title, mk, required=backend == "mujoco") if mujoco else None
    if frames is None:  # asked for, or MuJoCo cannot draw here: the stick figure of the body positions
        from motok.render.stick import render_motion

        joints = from_mj(body_states(hum, qpos, np.zeros((len(qpos), hum.model.nv)))["body_pos"])
        render_motion(joints, hum.skeleton.parents, out, fps=fps,
                      title=title if title is None or isinstance(title, str) else title[0], size=size)
        return out, "stick"
    step = gif_stride(fps) if out.suffix.lower() == ".gif" else 1
    write_video(itertools.islice(frames, 0, None, step), out, fps / step)
    return out, "mujoco"


def _mujoco_frames(hum: Humanoid, qpos: np.ndarray, size, ghost, title, markers, required: bool):
    """The frames of :func:`render_trajectory` drawn by MuJoCo, the first one drawn now so that a
    machine without a GL backend (no EGL/OSMesa, no display) shows before any file is written: then
    None, for the stick figure to stand in, or an error where MuJoCo is ``required``."""
    try:
        frames = _frames_mujoco(hum, qpos, size, ghost, title, markers)
        first = next(frames)
    except Exception as e:  # whatever the GL stack raises, the stick figure can still draw
        if required:
            raise RuntimeError(f"MuJoCo offscreen rendering failed ({e}); set MUJOCO_GL=egl or osmesa") from e
        return None
    return itertools.chain([first], frames)
