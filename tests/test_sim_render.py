"""MuJoCo videos show what a task asks for: markers far from the character (a navigation target
5-10 m away) are framed with it, drawn in their colour, in every frame."""

from __future__ import annotations

import numpy as np
import pytest

from motok.errors import UserError
from motok.sim.render import (CAM_AZIMUTH, CAM_DISTANCE, CAM_ELEVATION, framing, render_trajectory,
                                trajectory_frames)

GREEN = (0.1, 0.9, 0.1, 1.0)  # a colour neither the humanoid, the floor nor the sky has


def green_pixels(frame: np.ndarray) -> int:
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return int(((g > 150) & (r < 110) & (b < 110)).sum())


def test_framing_without_markers_is_the_follow_camera():
    look, dist, elev = framing(np.array([1.0, -2.0, 0.95]))
    assert np.allclose(look, [1.0, -2.0, 0.9]) and dist == CAM_DISTANCE and elev == CAM_ELEVATION
    # a marker beside the character (a head target, a keyframe pose) changes nothing
    assert framing(np.array([1.0, -2.0, 0.95]), np.array([[1.2, -2.1, 1.6]]))[1] == CAM_DISTANCE


def in_view(p, look, dist, elev, azimuth=CAM_AZIMUTH, fovy=45.0, aspect=4 / 3) -> bool:
    """Whether world point ``p`` projects inside the picture of MuJoCo's free camera."""
    el, az = np.radians(elev), np.radians(azimuth)
    fwd = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    v = np.asarray(p) - (look - dist * fwd)
    depth, t = v @ fwd, np.tan(np.radians(fovy) / 2)
    return depth > 0 and abs(v @ up / depth) < t and abs(v @ right / depth) < t * aspect


@pytest.mark.parametrize("target", [(8.0, 6.0), (-9.0, 2.0), (0.0, -10.0), (3.0, 3.0)])
def test_framing_keeps_a_distant_target_in_view(target):
    root = np.array([0.0, 0.0, 0.9])
    marker = np.array([[*target, 0.1]])
    look, dist, elev = framing(root, marker)
    assert np.allclose(look[:2], np.array(target) / 2)  # between them
    assert elev <= CAM_ELEVATION
    for p in ([*target, 0.1], [0.0, 0.0, 0.0], [0.0, 0.0, 1.8]):  # the target, the feet, the head
        assert in_view(p, look, dist, elev), p
    # the follow camera alone would have lost it
    assert not in_view([*target, 0.1], *framing(root))
    assert framing(root, np.array([[np.nan, np.nan, np.nan]]))[1] == CAM_DISTANCE  # non-finite rows ignored


@pytest.mark.parametrize("where", [(8.0, 0.0), (-5.0, 7.0)])
def test_a_distant_marker_is_drawn_in_every_frame(hum, tmp_path, where):
    import imageio.v3 as iio

    qpos = np.repeat(hum.model.qpos0[None], 3, 0)
    marks = np.array([[[where[0], where[1], 0.1]]] * 3)
    out, backend = render_trajectory(hum, qpos, tmp_path / "m.mp4", 30.0, markers=marks, marker_rgba=GREEN,
                                     marker_radius=0.25)
    assert backend == "mujoco"
    frames = iio.imread(out)
    assert all(green_pixels(f) >= 40 for f in frames), [green_pixels(f) for f in frames]
    # and the same video without the marker has none of its colour
    plain, _ = render_trajectory(hum, qpos, tmp_path / "p.mp4", 30.0)
    assert all(green_pixels(f) == 0 for f in iio.imread(plain))


def test_markers_of_the_wrong_shape_are_refused_before_anything_is_made(hum, tmp_path):
    """``(T, 3)`` points (one marker per frame without its K axis) would broadcast into three markers
    per frame; both entry points refuse them at the call, naming the shape, and no folder is made."""
    qpos = np.repeat(hum.model.qpos0[None], 3, 0)
    flat = np.zeros((3, 3))
    out = tmp_path / "videos" / "m.mp4"
    with pytest.raises(UserError, match=r"markers must have shape \(T, K, 3\), not \(3, 3\)"):
        render_trajectory(hum, qpos, out, 30.0, markers=flat)
    assert not out.parent.exists()
    with pytest.raises(UserError, match=r"markers must have shape \(T, K, 3\), not \(3, 3\)"):
        trajectory_frames(hum, qpos, markers=flat)  # at the call, not at the first frame drawn


def test_a_ball_model_renders_as_its_humanoid(hum, tmp_path):
    """The parked balls (1 km away) must not change the picture: MuJoCo scales its clipping planes
    with the model's extent, which the balls would stretch to 1 km and clip the nearest 10 m."""
    import imageio.v3 as iio

    from motok.sim.balls import build_ball_model, find_balls
    from motok.sim.humanoid import load_humanoid

    balls = load_humanoid(build_ball_model(hum, tmp_path / "balls.xml", 4))
    assert balls.model.stat.extent == pytest.approx(hum.model.stat.extent, rel=1e-6)
    q = np.repeat(hum.model.qpos0[None], 2, 0)
    qb = np.repeat(balls.model.qpos0[None], 2, 0)
    assert find_balls(balls.model).count == 4
    a = iio.imread(render_trajectory(hum, q, tmp_path / "plain.mp4", 30.0)[0]).astype(float)
    b = iio.imread(render_trajectory(balls, qb, tmp_path / "balls.mp4", 30.0)[0]).astype(float)
    assert np.abs(a - b).mean() < 1.0  # grey levels of 255: the same picture up to video coding


def test_without_gl_the_stick_figure_stands_in_unless_mujoco_is_asked_for(hum, tmp_path, monkeypatch):
    import motok.sim.render as render

    def no_gl(*args, **kwargs):
        raise OSError("no EGL display")
        yield  # a generator, as the MuJoCo one is

    monkeypatch.setattr(render, "_frames_mujoco", no_gl)
    qpos = np.repeat(hum.model.qpos0[None], 3, 0)
    out, backend = render_trajectory(hum, qpos, tmp_path / "auto.gif", 30.0)
    assert backend == "stick" and out.is_file()
    with pytest.raises(RuntimeError, match=r"failed \(no EGL display\); set MUJOCO_GL"):
        render_trajectory(hum, qpos, tmp_path / "mujoco.gif", 30.0, backend="mujoco")
    assert not (tmp_path / "mujoco.gif").exists()
    assert render_trajectory(hum, qpos, tmp_path / "stick.gif", 30.0, backend="stick")[1] == "stick"
