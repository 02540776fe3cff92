"""``motok view``: the viewer's logic without a window (clock, keys, clips, ghost), the clips it
shows from a motion file and from an expert run, the one-line error without a display, and a
real window under Xvfb, screenshot checked."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import unavailable
from typer.testing import CliRunner

from motok.cli.main import app
from motok.data.dataset import MotionFile
from motok.view.playback import HOLD_SECONDS, FlagGuard, Playback, bones, key_action, overlay
from motok.view.window import NoWindowError, check_display

pytestmark = pytest.mark.usefixtures("one_thread")
ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- logic, no window

def test_frames_follow_the_clock_hold_the_end_and_loop():
    pb = Playback(clips=3, fps=10.0, start=100.0)
    assert [pb.frame(100.0 + t, 20) for t in (0.0, 0.05, 0.1, 1.0, 1.95)] == [0, 0, 1, 10, 19]
    assert pb.frame(100.0 + 2.0 + HOLD_SECONDS - 0.05, 20) == 19  # the last frame is held
    assert pb.frame(100.0 + 2.0 + HOLD_SECONDS, 20) == 0  # then the clip starts over
    assert pb.frame(99.0, 20) == 0  # a clock before the start shows the first frame
    with pytest.raises(ValueError):
        pb.frame(100.0, 0)


def test_pause_freezes_the_frame_and_resume_goes_on_from_it():
    pb = Playback(clips=2, fps=10.0)
    assert not pb.press("pause", 0.5) and pb.paused
    assert pb.frame(0.5, 100) == pb.frame(7.0, 100) == 5
    pb.press("pause", 7.0)
    assert not pb.paused and pb.frame(7.0, 100) == 5 and pb.frame(7.3, 100) == 8


def test_next_previous_wrap_and_restart_starts_the_clip_over():
    pb = Playback(clips=3, fps=10.0, clip=2)
    assert pb.press("next", 4.0) and pb.clip == 0 and pb.frame(4.0, 50) == 0
    assert pb.press("previous", 5.0) and pb.clip == 2
    assert pb.press("previous", 5.0) and pb.clip == 1
    assert not pb.press("restart", 6.0) and pb.clip == 1 and pb.frame(6.2, 50) == 2
    pb.press("pause", 6.2)
    pb.press("next", 9.0)  # switching while paused shows the new clip's first frame, still paused
    assert pb.paused and pb.clip == 2 and pb.frame(20.0, 50) == 0
    assert not Playback(clips=1, fps=30.0).press("next", 1.0)  # one clip: nothing to switch to
    assert not pb.press(None, 1.0)
    with pytest.raises(ValueError):
        Playback(clips=0, fps=30.0)


def test_keys_map_to_actions_and_leave_mujocos_own_alone():
    assert [key_action(k) for k in (32, ord("N"), 262, ord("P"), 263, ord("R"), 259)] == \
        ["pause", "next", "next", "previous", "previous", "restart", "restart"]
    assert key_action(ord("S")) is None and key_action(258) is None  # shadows; Tab (MuJoCo's menus)


def test_a_flag_mujoco_flips_on_one_of_our_keys_is_put_back_and_others_stay():
    g = FlagGuard("base", seconds=0.3)
    assert g.synced("base", 1.0) is None
    assert g.synced("R flipped", 1.1) is None  # MuJoCo's flip reached the sync before the key did
    g.key(1.12)
    assert g.synced("R flipped", 1.2) == "base" and g.synced("base", 1.3) == "base"
    assert g.synced("base", 1.5) is None
    g.key(2.0)  # the key first, MuJoCo's flip at the next sync
    assert g.synced("P flipped", 2.1) == "base"
    assert g.synced("base", 2.5) is None and g.synced("S flipped", 3.0) is None  # S is MuJoCo's own
    assert g.synced("S flipped", 3.5) is None
    g.key(4.0)
    assert g.synced("S and R flipped", 4.1) == "S flipped"  # the user's S stays, our R does not


def test_ghost_bones_join_each_joint_to_its_parent():
    pos = np.arange(12, dtype=float).reshape(4, 3)
    a, b = bones(pos, [-1, 0, 1, 1])
    assert a.shape == b.shape == (3, 3)
    np.testing.assert_array_equal(a, pos[[0, 1, 1]])
    np.testing.assert_array_equal(b, pos[[1, 2, 3]])


def test_overlay_names_the_clip_time_state_and_keys():
    (c1, left, right), (c2, keys, help_) = overlay("walk_001", 1, 4, 30, 61, 30.0, True, "failed after 1.0 of 2.0 s")
    assert (c1, c2) == ("top left", "bottom left") and left.count("\n") == right.count("\n")
    assert "walk_001 (2/4)" in right and "1.00 / 2.00 s" in right and "paused - failed after" in right
    assert "Space" in help_ and "restart" in help_


def test_check_display_needs_a_display_on_x11_only():
    with pytest.raises(NoWindowError, match="xvfb-run"):
        check_display({}, "linux")
    check_display({"DISPLAY": ":0"}, "linux")
    check_display({"WAYLAND_DISPLAY": "wayland-0"}, "linux")
    check_display({}, "darwin")


# --------------------------------------------------------------------------- what is shown

def test_a_motion_file_shows_each_clip_frame_for_frame(small_dataset, hum_path):
    from motok.errors import UserError
    from motok.view.sources import MotionSource

    src = MotionSource(small_dataset, hum_path, clips="dataset-2_walk_normal_00[2-4]")
    with MotionFile(small_dataset) as mf:
        assert src.fps == mf.fps
        frames = len(mf.clip("dataset-2_walk_normal_003").joints)
    assert src.names == [f"dataset-2_walk_normal_00{i}" for i in (2, 3, 4)]
    i = src.index("dataset-2_walk_normal_003")
    assert i == src.index("1") == 1
    shown = src.shown(i)
    assert shown.qpos.shape == (frames, src.hum.model.nq) and shown.ghost is None
    assert src.shown(i) is shown  # computed once
    with pytest.raises(UserError, match="no clip named 'walk_009' among the clips to view"):
        src.index("walk_009")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, hum, lib, small_dataset):
    """An untrained expert and a prior distilled from it: real run folders with all their loaders read."""
    from tiny_runs import tiny_prior_bundle

    root = tmp_path_factory.mktemp("view")
    return {"prior": tiny_prior_bundle(root, hum, lib, small_dataset), "expert": root / "expert"}


def test_an_expert_run_shows_the_evaluations_playback_with_the_reference_as_ghost(runs, small_dataset):
    from motok.view.sources import ControlSource, control_api

    src = ControlSource(expert=runs["expert"], data=small_dataset, clips="dataset-2_walk_normal_00[12]")
    assert src.names == ["dataset-2_walk_normal_001", "dataset-2_walk_normal_002"] and src.fps == 30.0
    shown = src.shown(1)
    # The evaluation's own playback of that clip, frame for frame.
    api = control_api()
    ref = api.play(src.hum, src.policy, src.lib, np.array([1]), src.cfg.env, src.task, src.cfg.action,
                   keep_qpos=True)
    n = int(ref["played"][0]) + 1
    assert len(shown.qpos) == len(shown.ghost) == n
    np.testing.assert_allclose(shown.qpos, ref["qpos"][:n])
    np.testing.assert_allclose(shown.ghost, src.lib.body_pos[src.lib.starts[1]:src.lib.starts[1] + n])
    assert shown.note.startswith(("tracked to the end", "failed after"))


def test_a_prior_is_viewed_on_its_own_clips_and_its_codebooks_are_checked(runs):
    from motok.errors import UserError
    from motok.view.sources import ControlSource

    src = ControlSource(prior=runs["prior"], codebooks=2)
    assert len(src.names) == 24 and src.policy.num_codebooks == 2
    shown = src.shown(0)
    assert len(shown.qpos) == len(shown.ghost) >= 1 and shown.ghost.shape[1:] == (src.hum.skeleton.num_joints, 3)
    with pytest.raises(UserError, match="--codebooks must be in 1..4"):
        ControlSource(prior=runs["prior"], codebooks=5)


# --------------------------------------------------------------------------- no display

def test_without_a_display_view_fails_in_one_line_that_says_how_to_get_a_window(small_dataset, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    r = CliRunner().invoke(app, ["view", "-d", str(small_dataset)])
    assert r.exit_code == 2, r.output
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: no display")
    assert "xvfb-run" in lines[0] and "motok render" in lines[0]
    r = CliRunner().invoke(app, ["view"])
    assert r.exit_code == 2 and "give something to view" in r.output
    r = CliRunner().invoke(app, ["view", "-d", str(small_dataset), "--seconds", "0"])
    assert r.exit_code == 2 and "--seconds" in r.output


# --------------------------------------------------------------------------- a real window

@pytest.fixture(scope="module")
def xvfb():
    """A virtual X display (Xvfb on a free display number) for the module, or a skip that says why."""
    if shutil.which("Xvfb") is None:
        unavailable("Xvfb is not installed (apt-get install xvfb; .ci/run installs it)")
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", "800x600x24", "-nolisten", "tcp"],
                            pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(w)
    with os.fdopen(r) as f:
        number = f.readline().strip()
    if not number:
        proc.kill()
        unavailable("Xvfb was found but did not start (no display number on -displayfd)")
    yield f":{number}"
    proc.terminate()
    proc.wait(10)


def read_xwd(data: bytes) -> np.ndarray:
    """An X window dump (``xwd``, TrueColor) as an RGB array ``(H, W, 3)``."""
    h = struct.unpack(">25I", data[:100])
    size, width, height, lsb_first, bits, line, ncolors = h[0], h[4], h[5], h[7] == 0, h[11], h[12], h[19]
    start, step = size + 12 * ncolors, bits // 8
    px = np.frombuffer(data[start:start + height * line], np.uint8).reshape(height, line)[:, :width * step]
    px = px.reshape(height, width, step)
    return px[..., [2, 1, 0]] if lsb_first else px[..., step - 3:]


def test_a_real_window_under_xvfb_shows_the_humanoid(xvfb, small_dataset, hum_path, tmp_path):
    env = {**os.environ, "DISPLAY": xvfb, "MOTOK_NO_PROGRESS": "1"}
    env.pop("MUJOCO_GL", None)
    cmd = [sys.executable, "-m", "motok.cli.main", "view", "-d", str(small_dataset), "--humanoid", str(hum_path),
           "--clip", "dataset-2_walk_normal_002", "--seconds", "8", "--json"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        started = proc.stderr.readline()  # "viewing N clip(s) ...", once the window is open
        assert "viewing" in started, started + proc.stderr.read()
        time.sleep(2.0)
        if shutil.which("xwd"):
            shot = subprocess.run(["xwd", "-root", "-silent", "-display", xvfb], capture_output=True, check=True)
            rgb = read_xwd(shot.stdout)
            from PIL import Image
            Image.fromarray(np.ascontiguousarray(rgb)).save(tmp_path / "view.png")  # to look at by hand
            drawn = rgb[rgb.reshape(-1, 3).any(1).reshape(rgb.shape[:2])]  # the window, not the black root
            assert len(drawn) > 100_000, "no window on the display"
            assert drawn.std() > 20 and len(np.unique(drawn.reshape(-1, 3), axis=0)) > 200, "a blank window"
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    res = json.loads(out)
    assert res["shown"] == ["dataset-2_walk_normal_002"] and res["clips"] == 24
    assert res["frames_drawn"] > 5 and 8.0 <= res["seconds"] < 20.0
