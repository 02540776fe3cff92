"""The window of ``motok view``: MuJoCo's passive viewer (``mujoco.viewer.launch_passive``) showing
what :mod:`motok.view.playback` decides, frame by frame, for a :class:`motok.view.sources.Source`.

The viewer is passive: this loop owns the clock and the state (it writes the pose and calls
``sync``), the viewer draws on its own thread. Without a display there is no window to open, and
``launch_passive`` would wait forever for one that never comes (GLFW fails on the viewer's
thread), so the display and an OpenGL context are checked first and any failure is one line
that says how to get a window (:data:`NO_WINDOW`).
"""

from __future__ import annotations

import os
import queue
import sys
import threading
import time

import numpy as np

from motok import progress
from motok.errors import UserError
from motok.view.playback import HELP, FlagGuard, Playback, bones, key_action, overlay
from motok.view.sources import Source

NO_WINDOW = ("run it on a desktop, over ssh -X, or under a virtual display (xvfb-run -a motok view ...); "
             "for a video file instead use motok render or motok sim replay -o clip.mp4")
GHOST_RGBA = (0.3, 0.55, 0.95, 0.35)  # the offscreen videos' ghost colour (motok.sim.render)
GHOST_RADIUS = 0.035  # m: bones and joints of the ghost, thinner than the humanoid's limbs
POLL = 1.0 / 60.0  # s between loop turns: keys answered within a frame of a 60 Hz screen
OPEN_TIMEOUT = 30.0  # s to wait for the viewer's window once the display answered


class NoWindowError(UserError):
    """No window can be opened here (no display, no OpenGL context, macOS outside mjpython)."""


def check_display(environ=None, platform: str | None = None) -> None:
    """Fail at once, in one line, where no window can open: Linux and other X11 systems without
    ``$DISPLAY`` (or ``$WAYLAND_DISPLAY``). macOS and Windows have a desktop of their own."""
    environ = os.environ if environ is None else environ
    platform = platform or sys.platform
    if platform.startswith(("darwin", "win")):
        return
    if not (environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY")):
        raise NoWindowError(f"no display to open the viewer on ($DISPLAY is not set): {NO_WINDOW}")


def probe_gl() -> None:
    """Open and close a hidden GLFW window with an OpenGL context, on this thread, so a display
    that refuses (a wrong ``$DISPLAY``, no GLX) fails here in one line instead of on the viewer's
    thread."""
    try:
        import glfw
    except ImportError as e:  # mujoco.viewer needs it too
        raise NoWindowError(f"the viewer needs the glfw package ({e}): pip install glfw; {NO_WINDOW}") from None
    before = glfw.ERROR_REPORTING
    glfw.ERROR_REPORTING = "raise"
    try:
        if not glfw.init():
            raise glfw.GLFWError("glfwInit failed")
        glfw.window_hint(glfw.VISIBLE, glfw.FALSE)
        w = glfw.create_window(64, 64, "motok", None, None)
        if not w:
            raise glfw.GLFWError("no window")
        glfw.destroy_window(w)
        glfw.default_window_hints()
    except (glfw.GLFWError, OSError) as e:
        where = os.environ.get("DISPLAY", "")
        raise NoWindowError(f"cannot open an OpenGL window on display {where!r} ({str(e).strip()}): "
                            f"{NO_WINDOW}") from None
    finally:
        glfw.ERROR_REPORTING = before


def open_viewer(model, data, on_key, timeout: float = OPEN_TIMEOUT):
    """``mujoco.viewer.launch_passive`` with the menus hidden (Tab shows them), or a
    :class:`NoWindowError` when it fails or does not answer within ``timeout`` seconds."""
    import mujoco.viewer

    answer: queue.Queue = queue.Queue(1)
    before = set(threading.enumerate())

    def launch():
        try:
            answer.put(mujoco.viewer.launch_passive(model, data, key_callback=on_key, show_left_ui=False,
                                                    show_right_ui=False))
        except Exception as e:  # e.g. macOS outside mjpython: a RuntimeError that says so
            answer.put(e)

    threading.Thread(target=launch, daemon=True, name="motok-viewer-launch").start()
    try:
        got = answer.get(timeout=timeout)
    except queue.Empty:
        raise NoWindowError(f"the viewer's window did not open within {timeout:g} s: {NO_WINDOW}") from None
    if isinstance(got, Exception):
        macos = "mjpython" in str(got)
        hint = " (on macOS run it under mjpython: mjpython -m motok.cli.main view ...)" if macos else ""
        raise NoWindowError(f"the viewer did not start: {got}{hint}")
    got.motok_threads = [t for t in threading.enumerate() if t not in before]
    return got


def close_viewer(viewer, timeout: float = 10.0) -> None:
    """Close the window and wait for the threads the viewer started: the interpreter exiting while
    they still tear down their OpenGL context crashes it (a segmentation fault at exit)."""
    viewer.close()
    for t in getattr(viewer, "motok_threads", []):
        if t is not threading.current_thread():
            t.join(timeout)


def draw_ghost(scn, pos: np.ndarray | None, parents) -> None:
    """The reference as a translucent figure in the viewer's user scene: a capsule per bone and a
    sphere per joint at the reference's body positions ``pos`` ``(J, 3)``; nothing for None."""
    import mujoco

    scn.ngeom = 0
    if pos is None:
        return
    eye, rgba = np.eye(3).reshape(-1), np.array(GHOST_RGBA, dtype=np.float32)
    size = np.array([GHOST_RADIUS, 0.0, 0.0])
    for p in pos:
        if scn.ngeom >= scn.maxgeom:
            return
        mujoco.mjv_initGeom(scn.geoms[scn.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, size, p, eye, rgba)
        scn.ngeom += 1
    for a, b in zip(*bones(pos, parents)):
        if scn.ngeom >= scn.maxgeom:
            return
        g = scn.geoms[scn.ngeom]
        mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), eye, rgba)
        mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_CAPSULE, GHOST_RADIUS, a, b)
        scn.ngeom += 1


def _flags(viewer) -> tuple[np.ndarray, np.ndarray]:
    """The window's rendering and visual flags, copied."""
    return viewer.user_scn.flags.copy(), viewer.opt.flags.copy()


def _corners() -> dict:
    import mujoco

    return {"top left": mujoco.mjtGridPos.mjGRID_TOPLEFT, "bottom left": mujoco.mjtGridPos.mjGRID_BOTTOMLEFT}


def _setup(viewer, root_body: int) -> None:
    """A camera that follows the character as the offscreen videos frame it (MuJoCo's tracking
    camera), and no shadows or reflections: with software OpenGL (a virtual display, a remote X
    server, a VM) they make a frame about five times slower (16 against 84 ms measured under Xvfb on
    2 busy cores). S turns shadows back on; the menus (Tab) have both."""
    import mujoco

    from motok.sim.render import CAM_AZIMUTH, CAM_DISTANCE, CAM_ELEVATION

    cam = viewer.cam
    cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    cam.trackbodyid = root_body
    cam.distance, cam.elevation, cam.azimuth = CAM_DISTANCE, CAM_ELEVATION, CAM_AZIMUTH
    with viewer.lock():
        viewer.user_scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        viewer.user_scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False


def view(source: Source, start: int = 0, seconds: float | None = None, clock=time.monotonic) -> dict:
    """Show ``source`` from clip ``start`` until the window is closed (or for ``seconds``); returns
    what was shown (clips, frames drawn, seconds open)."""
    import mujoco

    check_display()
    probe_gl()
    hum = source.hum
    model = hum.model
    data = mujoco.MjData(model)
    parents = hum.skeleton.parents
    corners = _corners()
    pb = Playback(len(source.names), source.fps, clip=start)
    shown = source.shown(pb.clip)  # before the window: a controller's first clip takes a moment
    keys: queue.SimpleQueue = queue.SimpleQueue()
    viewer = open_viewer(model, data, keys.put)
    seen, drawn = [source.names[pb.clip]], 0
    progress.info(f"viewing {len(source.names)} clip(s) at {source.fps:g} fps; {HELP}")
    try:
        _setup(viewer, int(hum.body_ids[0]))
        t0 = pb.start = pb.paused_at = clock()
        guard = FlagGuard(_flags(viewer))
        while viewer.is_running():
            now = clock()
            if seconds is not None and now - t0 >= seconds:
                break
            while not keys.empty():
                action = key_action(keys.get())
                if action is None:
                    continue
                guard.key(now)
                if pb.press(action, now):
                    shown = source.shown(pb.clip)
                    now = clock()
                    pb.press("restart", now)  # a new clip (a rollout) took time: it starts now
                    guard.key(now)
                    seen.append(source.names[pb.clip])
            k = pb.frame(now, len(shown.qpos))
            with viewer.lock():
                data.qpos[:hum.nq] = shown.qpos[k]
                mujoco.mj_forward(model, data)
                draw_ghost(viewer.user_scn, None if shown.ghost is None else shown.ghost[k], parents)
            boxes = overlay(source.names[pb.clip], pb.clip, pb.clips, k, len(shown.qpos), source.fps, pb.paused,
                            shown.note)
            # set_texts waits for the viewer's next frame: it also paces this loop to the screen.
            viewer.set_texts([(None, corners[corner], left, right) for corner, left, right in boxes])
            viewer.sync()
            drawn += 1
            restore = guard.synced(_flags(viewer), clock())
            if restore is not None:  # pushed to the window at the next sync
                with viewer.lock():
                    viewer.user_scn.flags[:], viewer.opt.flags[:] = restore
            time.sleep(POLL)
    finally:
        close_viewer(viewer)
    return {"clips": len(source.names), "shown": seen, "frames_drawn": drawn, "seconds": round(clock() - t0, 2)}
