"""Stick-figure rendering (motok.render.stick) and training curves (motok.render.plot)."""

from __future__ import annotations

import json
import tarfile

import numpy as np
import pytest
from PIL import Image

from motok.render import stick
from motok.render.plot import _ema, _interp, plot_curves
from motok.render.stick import Camera, joint_sides, render_frames, render_motion
from motok.rotations import euler_to_quat, qmul, qrot

SIZE = (160, 128)  # deliberately not square, to catch width/height mix-ups


def walker(T: int = 40, fps: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """A 5-joint chain (ankle -> knee -> hip -> neck -> head), rooted at the ankle, that
    walks along +Z at 1.2 m/s with a forward-back sway and a small vertical bob."""
    t = np.arange(T) / fps
    heights = np.array([0.08, 0.5, 0.95, 1.5, 1.7])
    sway = 0.12 * np.sin(2 * np.pi * 1.0 * t)[:, None] * (heights / 1.7)[None]
    joints = np.zeros((T, 5, 3))
    joints[..., 1] = heights[None] + 0.03 * np.abs(np.sin(2 * np.pi * t))[:, None]
    joints[..., 2] = 1.2 * t[:, None] + sway
    return joints, np.array([-1, 0, 1, 2, 3])


def is_background(px) -> np.ndarray:
    return np.abs(np.asarray(px, dtype=int) - stick.BACKGROUND).sum(-1) <= 12


def test_render_frames_shape_and_change():
    joints, parents = walker()
    frames = render_frames(joints, parents, size=SIZE, title="a chain walks forward")
    assert frames.shape == (40, SIZE[1], SIZE[0], 3) and frames.dtype == np.uint8
    assert np.abs(frames[0].astype(int) - frames[20]).mean() > 1.0, "frames do not change over time"
    assert len(render_frames(joints, parents, size=SIZE, max_frames=7)) == 7
    assert len(render_frames(joints, parents, size=SIZE, indices=[0, 39])) == 2


def test_figure_is_where_the_projection_says():
    joints, parents = walker()
    frames = render_frames(joints, parents, size=SIZE)
    cam = Camera.fit(joints, parents, size=SIZE)
    uv, depth = cam.project(joints)
    assert (depth > 0).all()
    # Upright: the head is above the hip and the hip above the ankle, in every frame.
    assert (uv[:, 4, 1] < uv[:, 2, 1]).all() and (uv[:, 2, 1] < uv[:, 0, 1]).all()
    # Everything is inside the image.
    assert (uv[..., 0] > 0).all() and (uv[..., 0] < SIZE[0]).all()
    assert (uv[..., 1] > 0).all() and (uv[..., 1] < SIZE[1]).all()
    # The camera follows: the root stays near the middle although it travels 2.3 m.
    assert np.abs(uv[:, 2, 0] - SIZE[0] / 2).max() < 0.25 * SIZE[0]
    for t in (0, 25):
        for j in (2, 4):  # the hip (a bone) and the head (its circle)
            u, v = np.round(uv[t, j]).astype(int)
            patch = frames[t, v - 1 : v + 2, u - 1 : u + 2]
            assert (~is_background(patch)).mean() > 0.5, f"frame {t} joint {j} at {(u, v)} is not drawn"
    # Well above the head there is nothing but background.
    u, v = np.round(uv[0, 4]).astype(int)
    assert is_background(frames[0, max(0, v - 30), u])


def test_front_view_puts_the_characters_left_on_the_image_right():
    joints, parents = walker(T=2)
    joints[:, 3, 0] += 0.3  # push the neck towards +X, the character's left
    cam = Camera.fit(joints, parents, size=SIZE, azimuth=0.0, elevation=0.0)
    uv, _ = cam.project(joints)
    assert uv[0, 3, 0] > uv[0, 2, 0] + 5


def test_floor_checker_is_visible():
    joints, parents = walker()
    frame = render_frames(joints, parents, size=SIZE, indices=[0], trajectory=False)[0]
    cam = Camera.fit(joints, parents, size=SIZE)
    # Centres of two neighbouring tiles 1 m beyond the figure and 1 m to the image-left of it,
    # clear of the figure and its shadow.
    away = -cam.eye_dir * [1.0, 0.0, 1.0] / np.linalg.norm(cam.eye_dir[[0, 2]])
    spot = cam.targets[0] * [1.0, 0.0, 1.0] - 1.0 * cam.basis[0] + 1.0 * away
    cx, cz = (np.floor(spot[[0, 2]] / stick.TILE) + 0.5) * stick.TILE
    pts = np.array([[cx, 0.0, cz], [cx + stick.TILE, 0.0, cz]])
    uv, _ = cam.project(pts, 0)
    cols = [frame[int(v), int(u)].astype(int) for u, v in np.round(uv)]
    assert all(0 <= u < SIZE[0] and 0 <= v < SIZE[1] for u, v in uv)
    assert not is_background(cols[0]) and not is_background(cols[1]), cols
    assert np.abs(cols[0] - cols[1]).sum() > 20, f"neighbouring tiles look alike: {cols}"


def test_contacts_are_highlighted():
    joints, parents = walker(T=4)
    contacts = np.array([[1], [0], [1], [0]])
    frames = render_frames(joints, parents, size=SIZE, contacts=contacts, foot_joints=[0])
    uv, _ = Camera.fit(joints, parents, size=SIZE).project(joints)
    near_green = [np.abs(frames[t, int(uv[t, 0, 1]), int(uv[t, 0, 0])].astype(int) - stick.CONTACT).sum() < 60
                  for t in range(4)]
    assert near_green == [True, False, True, False]
    with pytest.raises(ValueError, match="together"):
        render_frames(joints, parents, size=SIZE, contacts=contacts)


def test_joint_sides_on_smpl(golden_joints):
    from motok.skeleton import load_skeleton

    skel = load_skeleton("smpl22")
    sides = joint_sides(golden_joints[0], skel.parents)
    for name, side in zip(skel.joints, sides):
        expected = 1 if name.startswith("left_") else -1 if name.startswith("right_") else 0
        assert side == expected, f"{name}: side {side}, expected {expected}"


def _bandai_first_clip(archive) -> tuple[np.ndarray, np.ndarray, float]:
    """Joint positions (metres) of the first BVH in the archive, without joint_Root."""
    with tarfile.open(archive, "r|xz") as tf:  # stream: stop at the first clip
        for member in tf:
            if member.name.endswith(".bvh"):
                text = tf.extractfile(member).read().decode()
                break
        else:
            pytest.fail(f"no .bvh in {archive}")
    head, motion = text.split("MOTION")
    parents, stack, last = [], [], -1
    toks = iter(head.split())
    for tok in toks:
        if tok in ("ROOT", "JOINT"):
            next(toks)
            parents.append(stack[-1] if stack else -1)
            last = len(parents) - 1
        elif tok == "End":  # an End Site block: skip it whole
            for tok in toks:
                if tok == "}":
                    break
            last = None
        elif tok == "{":
            stack.append(last)
        elif tok == "}" and stack:
            stack.pop()
    lines = motion.strip().splitlines()
    fps = 1.0 / float(lines[1].split(":")[1])
    data = np.array([ln.split() for ln in lines[2:]], dtype=np.float64).reshape(len(lines) - 2, len(parents), 6)
    local = euler_to_quat(data[..., 3:], "ZXY")  # channels: Xpos Ypos Zpos Zrot Xrot Yrot
    rot, pos = np.zeros(local.shape), np.zeros(data.shape[:2] + (3,))
    for j, p in enumerate(parents):
        if p < 0:
            rot[:, j], pos[:, j] = local[:, j], data[:, j, :3]
        else:
            rot[:, j] = qmul(rot[:, p], local[:, j])
            pos[:, j] = pos[:, p] + qrot(rot[:, p], data[:, j, :3])
    # Drop joint_Root (the ground projection): a bone from it would streak across the floor.
    return pos[:, 1:] * 0.01, np.array(parents[1:]) - 1, fps


@pytest.fixture(scope="module")
def bandai_clip(bandai2_archive):
    return _bandai_first_clip(bandai2_archive)


def test_bandai_clip_parses_to_a_standing_human(bandai_clip):
    joints, parents, fps = bandai_clip
    assert joints.shape[1:] == (21, 3) and parents[0] == -1 and abs(fps - 30.0) < 0.01
    assert 1.2 < joints[:, 4, 1].max() < 2.0, "head height in metres"  # joint 4 is Head
    assert -0.05 < joints[..., 1].min() < 0.2, "feet near the floor"


def test_real_clip_gif_and_mp4(bandai_clip, tmp_path):
    import imageio.v2 as imageio

    joints, parents, fps = bandai_clip
    n = min(45, len(joints))
    gif = render_motion(joints, parents, tmp_path / "clip.gif", fps=fps, title="dataset-2 clip",
                        size=(200, 160), max_frames=n)
    with Image.open(gif) as im:
        assert im.size == (200, 160) and im.n_frames == n and im.info.get("loop") == 0
        durations = []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
    assert abs(1000.0 / np.mean(durations) - fps) < 0.5

    # An odd size is rounded up to even for yuv420p.
    mp4 = render_motion(joints, parents, tmp_path / "clip.mp4", fps=fps, size=(201, 161), max_frames=n)
    reader = imageio.get_reader(mp4)
    try:
        meta = reader.get_meta_data()
        frames = [f for f in reader]
    finally:
        reader.close()
    assert abs(meta["fps"] - fps) < 0.01
    assert len(frames) == n and frames[0].shape == (162, 202, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.gif", "clip.mp4"], "temporary files left"


def test_png_contact_sheet(bandai_clip, tmp_path):
    joints, parents, fps = bandai_clip
    out = render_motion(joints, parents, tmp_path / "sheet.png", fps=fps, size=(120, 150))
    with Image.open(out) as im:
        assert im.size == (6 * 120, 150)
    titled = render_motion(joints, parents, tmp_path / "titled.png", fps=fps, size=(120, 150), title="run")
    with Image.open(titled) as im:
        assert im.width == 6 * 120 and im.height > 150
    short = render_motion(joints[:3], parents, tmp_path / "short.png", size=(120, 150))
    with Image.open(short) as im:
        assert im.size == (3 * 120, 150)


def test_bad_suffix_and_failed_render_leave_nothing(tmp_path):
    joints, parents = walker(T=3)
    with pytest.raises(ValueError, match=r"'\.txt'.*\.gif, \.mp4, \.png"):
        render_motion(joints, parents, tmp_path / "motion.txt")
    with pytest.raises(ValueError, match="parents"):
        render_motion(joints, parents[:4], tmp_path / "motion.gif")
    assert list(tmp_path.iterdir()) == []


def test_plot_curves_skips_malformed_lines(tmp_path):
    path = tmp_path / "metrics.jsonl"
    rows = [json.dumps({"iteration": i, "loss": 1.0 / (i + 1), "lr": 1e-4, "tag": "x"}) for i in range(20)]
    rows.insert(3, "{not json")
    path.write_text("\n".join(rows) + "\n")
    with pytest.warns(UserWarning, match="line 4"):
        out = plot_curves(path, tmp_path / "curves.png", smooth=0.6)
    with Image.open(out) as im:
        assert im.format == "PNG" and im.width > 200 and im.height > 200
        # two subplots (loss, lr) draw more than a blank canvas
        assert len(np.unique(np.asarray(im.convert("RGB")).reshape(-1, 3), axis=0)) > 10
    with pytest.raises(ValueError, match="no numeric values"):
        plot_curves([{"iteration": 1, "tag": "x"}], tmp_path / "empty.png")
    assert not (tmp_path / "empty.png").exists()


def test_smoothing_is_per_record_so_sparse_metrics_keep_their_shape():
    w, ys = 0.9, [1.0, 3.0, 2.0, 5.0]
    dense = [sum(w ** (i - j) * (1 - w) * ys[j] for j in range(i + 1)) / (1 - w ** (i + 1)) for i in range(4)]
    np.testing.assert_allclose(_ema(ys, w), dense)  # every record: the debiased EMA
    # logged every 10th record (eval_*): the same EMA with weight w^10, barely smoothed at 0.95^250
    np.testing.assert_allclose(_ema(ys, w, rows=[0, 10, 20, 30]), _ema(ys, w**10))
    np.testing.assert_allclose(_ema(ys, 0.95, rows=[0, 250, 500, 750]), ys, rtol=1e-4)
    # the top axis' map extends past the data with the overall slope instead of clamping
    np.testing.assert_allclose(_interp([-1.0, 0.5, 1.5, 3.0], [0, 1, 2], [0, 10, 14]), [-7.0, 5.0, 12.0, 21.0])


def test_plot_curves_second_axis(tmp_path):
    """A top axis for a field that grows with x (wall time over samples) adds ticks and labels,
    so the figure differs from the one without it; a field that does not grow is refused."""
    recs = [{"samples": 4096 * i, "wall_s": 0.7 * i, "success": i / 30} for i in range(1, 30)]
    one = plot_curves(recs, tmp_path / "one.png", ["success"], "samples")
    two = plot_curves(recs, tmp_path / "two.png", ["success"], "samples", x2="wall_s")
    with Image.open(one) as a, Image.open(two) as b:
        assert a.size == b.size and not np.array_equal(np.asarray(a), np.asarray(b))
    recs[5]["wall_s"] = 0.0
    with pytest.raises(ValueError, match="must grow"):
        plot_curves(recs, tmp_path / "bad.png", ["success"], "samples", x2="wall_s")


def test_several_runs_share_the_subplots(tmp_path):
    """Two runs on one figure: each subplot draws one curve per run that has the key (a continuous
    prior has no code usage), in the run's own colour, with a legend; a second axis (speed differs
    between runs) and unnamed or same-named outputs are refused; the command takes several runs."""
    import json

    from typer.testing import CliRunner

    from motok.cli.main import app
    from motok.render.plot import _figure, plot_run

    a = [{"samples": 4096 * i, "eval_success": i / 10, "code_usage": 0.5} for i in range(1, 9)]
    b = [{"samples": 4096 * i, "eval_success": i / 20} for i in range(1, 12)]
    fig = _figure({"hybrid": a, "continuous": b}, ["eval_success", "code_usage"], "samples")
    succ, usage = fig.axes[:2]
    assert [ln.get_label() for ln in succ.get_lines()] == ["hybrid", "continuous"]
    assert [len(ln.get_xdata()) for ln in succ.get_lines()] == [8, 11]
    assert succ.get_lines()[0].get_color() != succ.get_lines()[1].get_color()
    assert [ln.get_label() for ln in usage.get_lines()] == ["hybrid"] and succ.get_legend() is not None
    with pytest.raises(ValueError, match="single run"):
        _figure({"a": a, "b": b}, ["eval_success"], "samples", x2="samples")
    with pytest.raises(ValueError, match="no metric 'r_im'"):
        _figure({"a": a, "b": b}, ["r_im"], "samples")
    # missing_ok: a key no run has logged yet is left out with a warning; one key must remain
    with pytest.warns(UserWarning, match="no metric 'r_im'"):
        fig = _figure({"a": a, "b": b}, ["eval_success", "r_im"], "samples", missing_ok=True)
    assert [ax.get_title(loc="left") for ax in fig.axes if ax.get_lines()] == ["Success rate"]
    with pytest.raises(ValueError, match="no metric 'r_im'"):
        _figure({"a": a, "b": b}, ["r_im"], "samples", missing_ok=True)
    runs = []
    for name, recs in (("prior_hybrid", a), ("prior_continuous", b)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n")
        runs.append(tmp_path / name)
    with pytest.raises(ValueError, match="-o/--out"):
        plot_run(runs)
    with pytest.raises(ValueError, match="one --label per run"):
        plot_run(runs, tmp_path / "x.png", labels=["one"])
    r = CliRunner().invoke(app, ["--quiet", "plot", str(runs[0]), str(runs[1]), "--keys", "eval_success",
                                 "--x", "samples", "-o", str(tmp_path / "priors.png"), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["metrics"] == [str(p) for p in runs] and (tmp_path / "priors.png").stat().st_size > 0
    r = CliRunner().invoke(app, ["--quiet", "plot", str(runs[0]), str(runs[0] / "metrics.jsonl"), "-o",
                                 str(tmp_path / "same.png")])
    assert r.exit_code == 2 and "--label" in r.output


def test_log_axis_only_for_the_named_keys(tmp_path):
    """``logy`` puts the named subplots (an action loss falling over decades) on a log scale and
    leaves the others linear; a name that is not plotted is an error, not a silent linear axis."""
    from typer.testing import CliRunner

    from motok.cli.main import app
    from motok.render.plot import _figure

    recs = [{"samples": i, "action_loss": 10.0 ** -i, "eval_success": i / 10} for i in range(1, 6)]
    fig = _figure(recs, ["action_loss", "eval_success"], "samples", logy=["action_loss"])
    assert [ax.get_yscale() for ax in fig.axes[:2]] == ["log", "linear"]
    with pytest.raises(ValueError, match="--log actoin_loss: not among the plotted keys"):
        _figure(recs, ["action_loss"], "samples", logy=["actoin_loss"])
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n")
    r = CliRunner().invoke(app, ["--quiet", "plot", str(tmp_path / "run"), "--keys", "action_loss,eval_success",
                                 "--log", "action_loss", "-o", str(tmp_path / "log.png")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["--quiet", "plot", str(tmp_path / "run"), "--keys", "eval_success",
                                 "--log", "action_loss", "-o", str(tmp_path / "bad.png")])
    assert r.exit_code == 2 and "not among the plotted keys" in r.output
