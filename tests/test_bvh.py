"""BVH parsing, forward kinematics and writing, on the Bandai-Namco archives."""

from __future__ import annotations

import pickle
import re
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from motok.data.bvh import BvhMotion, MotionFormatError, parse_bvh, read_bvh
from motok.data.export import write_bvh
from motok.data.sources import iter_sources
from motok.skeleton import detect_skeleton

BANDAI_NAMES = ["joint_Root", "Hips", "Spine", "Chest", "Neck", "Head",
                "Shoulder_L", "UpperArm_L", "LowerArm_L", "Hand_L", "Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R",
                "UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L", "UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R"]
BANDAI_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")


@pytest.fixture(scope="module")
def set1_clips(bandai_dir) -> dict[str, bytes]:
    """Four set-1 clips (the set-1 archive is small enough to stream per module)."""
    out = {}
    for src in iter_sources(bandai_dir / "bandai-namco-1.tar.xz", kinds=("bvh",)):
        out[src.origin] = src.data
        if len(out) == 4:
            break
    return out


@pytest.fixture(scope="module")
def clip(set1_clips) -> tuple[str, bytes]:
    return next(iter(set1_clips.items()))


# ----------------------------------------------------------------------------- the whole of set 2

@pytest.mark.slow
def test_every_set2_clip_parses(bandai2_archive):
    n = frames = nbytes = 0
    parse_s = 0.0
    t0 = time.perf_counter()
    for src in iter_sources(bandai2_archive, kinds=("bvh",)):
        t = time.perf_counter()
        m = parse_bvh(src.data, src.origin)
        parse_s += time.perf_counter() - t
        n, frames, nbytes = n + 1, frames + m.num_frames, nbytes + len(src.data)
        assert m.names == BANDAI_NAMES, src.origin
        assert all(c == BANDAI_CHANNELS for c in m.channels), src.origin
        assert abs(m.fps - 30.0) < 1e-3 and m.num_frames > 0
        assert m.rotations.shape == (m.num_frames, 22, 4) and m.translations.shape == (m.num_frames, 22, 3)
        assert np.allclose(np.linalg.norm(m.rotations, axis=-1), 1.0)
    total_s = time.perf_counter() - t0
    assert n == 2902
    assert frames == 384_931
    mb = nbytes / 1e6
    print(f"\nset 2: {n} clips, {frames} frames, {mb:.1f} MB of BVH text; "
          f"with xz decompression {total_s:.2f} s = {mb / total_s:.0f} MB/s, {frames / total_s:,.0f} frames/s; "
          f"parse_bvh alone {parse_s:.2f} s = {mb / parse_s:.0f} MB/s, {frames / parse_s:,.0f} frames/s")


def test_set1_clips_parse(set1_clips):
    for origin, data in set1_clips.items():
        m = parse_bvh(data, origin)
        declared = int(re.search(rb"Frames:\s*(\d+)", data).group(1))
        assert m.num_frames == declared and m.names == BANDAI_NAMES
        assert detect_skeleton(joint_names=m.names).name == "bandai21"
        assert sorted(m.end_sites) == [BANDAI_NAMES.index(j) for j in ("Head", "Hand_L", "Hand_R", "Toes_L", "Toes_R")]


# ----------------------------------------------------------------------------- forward kinematics

def _axis_matrix(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    if axis == "X":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "Y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _naive_fk(text: str, frames: list[int]) -> dict[int, np.ndarray]:
    """World joint positions by a plain reading of the file: per line, per joint, per channel,
    rotation matrices multiplied in channel order. Shares no code with motok."""
    lines = text.splitlines()
    joints, stack = [], []
    k = 0
    while lines[k].strip() != "MOTION":
        w = lines[k].split()
        if w and w[0] in ("ROOT", "JOINT"):
            joints.append({"parent": stack[-1] if stack else None, "offset": None, "channels": []})
            stack.append(len(joints) - 1)
        elif w and w[0] == "End":
            stack.append(None)
        elif w and w[0] == "OFFSET" and stack[-1] is not None:
            joints[stack[-1]]["offset"] = np.array([float(x) for x in w[1:4]])
        elif w and w[0] == "CHANNELS":
            joints[stack[-1]]["channels"] = w[2:]
        elif w and w[0] == "}":
            stack.pop()
        k += 1
    rows = [r for r in lines[k + 3:] if r.strip()]
    out = {}
    for f in frames:
        vals = iter(float(x) for x in rows[f].split())
        world = []
        for j in joints:
            t, r = j["offset"].copy(), np.eye(3)
            for ch in j["channels"]:
                v = next(vals)
                if ch.endswith("position"):
                    t["XYZ".index(ch[0])] = v
                else:
                    r = r @ _axis_matrix(ch[0], v)
            if j["parent"] is None:
                world.append((r, t))
            else:
                pr, pt = world[j["parent"]]
                world.append((pr @ r, pt + pr @ t))
        out[f] = np.array([p for _, p in world])
    return out


def test_fk_matches_a_per_joint_loop(clip):
    origin, data = clip
    m = parse_bvh(data, origin)
    frames = [0, m.num_frames // 3, m.num_frames - 1]
    expected = _naive_fk(data.decode(), frames)
    got = m.global_positions()
    for f in frames:
        np.testing.assert_allclose(got[f], expected[f], atol=1e-6)


def test_bone_lengths_constant_where_positions_equal_offsets(set1_clips):
    for origin, data in set1_clips.items():
        m = parse_bvh(data, origin)
        dev = np.abs(m.translations - m.offsets).max(axis=(0, 2))
        rigid = [j for j in range(2, 22) if dev[j] < 1e-4]  # joint_Root and Hips move freely
        assert len(rigid) == 20, f"{origin}: position channels differ from OFFSET at {np.flatnonzero(dev >= 1e-4)}"
        p = m.global_positions()
        for j in rigid:
            length = np.linalg.norm(p[:, j] - p[:, m.parents[j]], axis=-1)
            assert np.ptp(length) < 1e-3, (origin, m.names[j])
            assert abs(length[0] - np.linalg.norm(m.offsets[j])) < 1e-3


def test_poses_are_upright_in_centimetres(set1_clips):
    for origin, data in set1_clips.items():
        m = parse_bvh(data, origin)
        p = m.global_positions()
        y = {n: p[:, m.names.index(n), 1] for n in ("Hips", "Head", "Toes_L", "Toes_R")}
        assert np.all(y["Head"] > y["Hips"] + 20), origin  # Y is up
        assert 50 < np.median(y["Hips"]) < 130, origin  # a standing pelvis, in cm
        assert -5 < min(y["Toes_L"].min(), y["Toes_R"].min()) < 20, origin  # feet reach the floor


def test_subset_keeps_world_positions(clip):
    m = parse_bvh(*clip[::-1])
    full = m.global_positions()
    sub = m.subset(BANDAI_NAMES[1:])
    assert sub.names[0] == "Hips" and sub.parents[0] == -1 and list(sub.parents[1:3]) == [0, 1]
    np.testing.assert_allclose(sub.global_positions(), full[:, 1:], atol=1e-9)
    grot, _ = m.global_transforms()
    np.testing.assert_allclose(np.abs((sub.rotations[:, 0] * grot[:, 1]).sum(-1)), 1.0, atol=1e-9)
    # Cutting the spine: Neck hangs from Hips, its local transform absorbing Spine and Chest.
    keep = [n for n in BANDAI_NAMES[1:] if n not in ("Spine", "Chest")]
    cut = m.subset(keep)
    assert cut.parents[keep.index("Neck")] == keep.index("Hips")
    np.testing.assert_allclose(cut.global_positions(), full[:, [BANDAI_NAMES.index(n) for n in keep]], atol=1e-9)
    with pytest.raises(ValueError):
        m.subset(["Spine", "Hips"])
    with pytest.raises(KeyError):
        m.subset(["Hips", "Tail"])


# ----------------------------------------------------------------------------- writing

def _check_blender_syntax(text: str) -> None:
    """The layout Blender's BVH importer walks: one keyword per line, '{' and '}' alone on their
    lines, OFFSET with 3 numbers, CHANNELS with its count of names, End Site on every leaf, then
    MOTION, 'Frames: N', 'Frame Time: t' and N rows of the CHANNELS total."""
    lines = [ln.split() for ln in text.split("\n")]
    assert lines[-1] == [] and text.endswith("\n")
    lines = [w for w in lines if w]
    assert lines[0] == ["HIERARCHY"] and lines[1][0] == "ROOT" and len(lines[1]) == 2
    k, depth, width, leaf, roots = 1, 0, 0, False, 0
    while lines[k] != ["MOTION"]:
        w = lines[k]
        if w[0] in ("ROOT", "JOINT") or w == ["End", "Site"]:
            assert len(w) == 2, k
            roots += w[0] == "ROOT"
            assert lines[k + 1] == ["{"], k
            assert lines[k + 2][0] == "OFFSET" and len(lines[k + 2]) == 4, k
            [float(x) for x in lines[k + 2][1:]]
            if w[0] == "End":
                assert lines[k + 3] == ["}"]
                leaf = True
                k += 4
                continue
            ch = lines[k + 3]
            assert ch[0] == "CHANNELS" and int(ch[1]) == len(ch) - 2 == (6 if w[0] == "ROOT" else 3), k
            assert all(re.fullmatch(r"[XYZ](position|rotation)", c) for c in ch[2:])
            width += int(ch[1])
            depth += 1
            leaf = False
            k += 4
        else:
            assert w == ["}"], k
            depth -= 1
            k += 1
    assert depth == 0 and roots == 1 and leaf
    assert len(lines[k + 1]) == 2 and lines[k + 1][0] == "Frames:"  # Blender checks the token counts
    assert len(lines[k + 2]) == 3 and lines[k + 2][:2] == ["Frame", "Time:"]
    frames, ft = int(lines[k + 1][1]), float(lines[k + 2][2])
    assert ft > 0 and len(lines) - (k + 3) == frames
    assert all(len(r) == width for r in lines[k + 3:])


@pytest.mark.parametrize("order", ["ZXY", "XYZ"])
def test_write_round_trip(clip, tmp_path, order):
    m = parse_bvh(clip[1], clip[0]).subset(BANDAI_NAMES[1:])  # Hips as root: it carries the motion
    expected = m.global_positions()
    path = tmp_path / f"clip_{order}.bvh"
    write_bvh(path, m.names, m.parents, m.offsets, m.rotations, m.translations[:, 0], m.fps, order=order,
              end_sites=m.end_sites)
    text = path.read_text()
    _check_blender_syntax(text)
    assert f"CHANNELS 3 {' '.join(a + 'rotation' for a in order)}" in text
    back = read_bvh(path)
    assert back.names == m.names and back.num_frames == m.num_frames and abs(back.fps - m.fps) < 1e-4
    assert np.abs(back.global_positions() - expected).max() < 0.1  # 1 mm, in cm
    # Through another rotation order: read ZXY/XYZ, write the other, read again.
    other = "XYZ" if order == "ZXY" else "ZXY"
    write_bvh(tmp_path / "again.bvh", back.names, back.parents, back.offsets, back.rotations,
              back.translations[:, 0], back.fps, order=other)
    again = read_bvh(tmp_path / "again.bvh")
    assert again.channels[1] == tuple(a + "rotation" for a in other)
    assert np.abs(again.global_positions() - expected).max() < 0.1
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_write_rejects_bad_input(tmp_path):
    q = np.tile([1.0, 0, 0, 0], (2, 2, 1))
    with pytest.raises(ValueError, match="permutation"):
        write_bvh(tmp_path / "a.bvh", ["a", "b"], [-1, 0], np.zeros((2, 3)), q, np.zeros((2, 3)), 30, order="XXY")
    with pytest.raises(ValueError, match="one root"):
        write_bvh(tmp_path / "a.bvh", ["a", "b"], [-1, -1], np.zeros((2, 3)), q, np.zeros((2, 3)), 30)
    with pytest.raises(ValueError):
        write_bvh(tmp_path / "a.bvh", ["a", "b"], [-1, 0], np.zeros((2, 3)), q, np.zeros((3, 3)), 30)
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- syntax coverage

SYNTHETIC = (
    "HIERARCHY\r\n"
    "ROOT pelvis\r\n{\r\n"
    "\tOFFSET 1.0 2.0 3.0\r\n"
    "\tCHANNELS 6 Zrotation Yrotation Xrotation Xposition Yposition Zposition\r\n"
    "\tJOINT spine {\r\n"  # brace on the name line
    "\t\tOFFSET 0 1.5E+1 0\r\n"
    "\t\tCHANNELS 3 Xposition Yposition Zposition\r\n"  # translation only
    "\t\tJOINT left hand\r\n\t\t{\r\n"  # a name with a space
    "\t\t\tOFFSET 2.5e-1 0 0\r\n"
    "\t\t\tCHANNELS 3 Yrotation Xrotation Zrotation\r\n"
    "\t\t\tEnd Site\r\n\t\t\t{\r\n\t\t\t\tOFFSET 0 0 1\r\n\t\t\t}\r\n"
    "\t\t}\r\n"
    "\t\tJOINT twist\r\n\t\t{\r\n"
    "\t\t\tOFFSET 0 1 0\r\n"
    "\t\t\tCHANNELS 1 Yrotation\r\n"
    "\t\t\tJOINT fixed\r\n\t\t\t{\r\n\t\t\t\tOFFSET 1 0 0\r\n\t\t\t\tCHANNELS 0\r\n"
    "\t\t\t\tEnd Site\r\n\t\t\t\t{\r\n\t\t\t\t\tOFFSET 1 0 0\r\n\t\t\t\t}\r\n\t\t\t}\r\n"
    "\t\t}\r\n"
    "\t}\r\n"
    "}\r\n"
    "MOTION\r\n"
    "Frames:\t2\r\n"
    "Frame Time:\t4.1666667e-02\r\n"
    "10 20 30 1 2 3\t0.5 14 -0.5\t45 -30 60 90\r\n"
    "-10 -2.5e1 3e+1 4 5 6 0 15 0 0 0 0 -90\r\n"
)


def test_synthetic_syntax():
    m = parse_bvh(SYNTHETIC, "synthetic.bvh")
    assert m.names == ["pelvis", "spine", "left hand", "twist", "fixed"]
    assert list(m.parents) == [-1, 0, 1, 1, 3]
    assert m.channels[4] == () and m.channels[3] == ("Yrotation",)
    assert abs(m.fps - 24.0) < 1e-4 and m.num_frames == 2
    np.testing.assert_allclose(m.offsets[1], [0, 15, 0])
    np.testing.assert_allclose(m.end_sites[2], [0, 0, 1])
    rows = np.array([[10, 20, 30, 1, 2, 3, 0.5, 14, -0.5, 45, -30, 60, 90],
                     [-10, -25, 30, 4, 5, 6, 0, 15, 0, 0, 0, 0, -90]], dtype=float)

    def quat(order, angles):  # scipy's upper-case orders are intrinsic, as in BVH
        q = Rotation.from_euler(order, angles, degrees=True).as_quat()
        return np.concatenate([q[..., 3:], q[..., :3]], -1)

    def same_rotation(a, b):
        np.testing.assert_allclose(np.abs((a * b).sum(-1)), 1.0, atol=1e-12)

    same_rotation(m.rotations[:, 0], quat("ZYX", rows[:, 0:3]))
    same_rotation(m.rotations[:, 2], quat("YXZ", rows[:, 9:12]))
    same_rotation(m.rotations[:, 3], quat("Y", rows[:, 12:13]))
    same_rotation(m.rotations[:, 1], np.tile([1.0, 0, 0, 0], (2, 1)))
    np.testing.assert_allclose(m.translations[:, 0], rows[:, 3:6])
    np.testing.assert_allclose(m.translations[:, 1], rows[:, 6:9])
    np.testing.assert_allclose(m.translations[:, 4], [[1, 0, 0]] * 2)
    got = m.global_positions()
    expected = _naive_fk(SYNTHETIC.replace("JOINT spine {", "JOINT spine\n{"), [0, 1])
    for f in (0, 1):
        np.testing.assert_allclose(got[f], expected[f], atol=1e-9)


def test_single_frame_and_zero_frames():
    one = re.sub(r"Frames:\t2", "Frames: 1", SYNTHETIC).rsplit("\r\n", 2)[0] + "\r\n"
    assert parse_bvh(one, "one.bvh").num_frames == 1
    head = SYNTHETIC.split("Frames:")[0]
    zero = parse_bvh(head + "Frames: 0\nFrame Time: 0.01\n", "zero.bvh")
    assert zero.rotations.shape == (0, 5, 4) and zero.global_positions().shape == (0, 5, 3)


def test_error_pickles_and_keeps_fields():
    e = MotionFormatError("a.bvh", "expected a number", line=7)
    back = pickle.loads(pickle.dumps(e))
    assert (back.source, back.line, str(back)) == ("a.bvh", 7, "a.bvh, line 7: expected a number")
    assert isinstance(back, ValueError)


def test_read_bvh_from_path(clip, tmp_path):
    p = tmp_path / "x.bvh"
    p.write_bytes(clip[1])
    m = read_bvh(p)
    assert isinstance(m, BvhMotion) and m.source == str(p)
    np.testing.assert_array_equal(m.rotations, parse_bvh(clip[1]).rotations)


# ----------------------------------------------------------------------------- bad input

def _line_of(text: str, needle: str, nth: int = 0) -> int:
    """1-based number of the line where ``needle`` starts its ``nth`` occurrence."""
    pos = -1
    for _ in range(nth + 1):
        pos = text.index(needle, pos + 1)
    return text.count("\n", 0, pos) + 1


def _short(text: str, frames: int = 6) -> str:
    """A real clip cut to a few frames, with 'Frames:' adjusted."""
    head, body = text.split("Frame Time:", 1)
    ft, *rows = body.split("\n")
    head = re.sub(r"Frames:\s*\d+", f"Frames: {frames}", head)
    return head + "Frame Time:" + ft + "\n" + "\n".join(rows[:frames]) + "\n"


def _row_line(text: str, k: int) -> int:
    return _line_of(text, "Frame Time:") + 1 + k


def _replace_value(text: str, row: int, col: int, new: str) -> str:
    lines = text.split("\n")
    n = _row_line(text, row) - 1
    vals = lines[n].split()
    vals[col] = new
    lines[n] = " ".join(vals)
    return "\n".join(lines)


def _drop_line(text: str, line: int) -> str:
    lines = text.split("\n")
    del lines[line - 1]
    return "\n".join(lines)


# Each case: (id, mutate(text) -> bad text, expected line (computed on the bad text), message part)
BAD_CASES = [
    ("truncated", lambda t: _drop_line(_drop_line(t, _row_line(t, 5)), _row_line(t, 4)),
     lambda b: _row_line(b, 4), "expected frame 5"),
    ("too-few-values", lambda t: _replace_value(t, 2, 7, ""), lambda b: _row_line(b, 2), "expected 132 values"),
    ("too-many-values", lambda t: _replace_value(t, 3, 0, "1 2"), lambda b: _row_line(b, 3), "found 133"),
    ("non-numeric", lambda t: _replace_value(t, 1, 40, "abc"), lambda b: _row_line(b, 1), "value 41 is 'abc'"),
    ("nan", lambda t: _replace_value(t, 4, 3, "nan"), lambda b: _row_line(b, 4), "finite"),
    ("inf", lambda t: _replace_value(t, 0, 100, "-inf"), lambda b: _row_line(b, 0), "finite"),
    ("extra-row", lambda t: t + t.split("\n")[_row_line(t, 0) - 1] + "\n", lambda b: _row_line(b, 6), "beyond"),
    ("channels-count", lambda t: t.replace("CHANNELS 6", "CHANNELS 5", 3),
     lambda b: _line_of(b, "CHANNELS 5"), "declares 5 channels but lists 6"),
    ("channels-missing-count",  # the second joint's CHANNELS loses its count
     lambda t: t.replace("CHANNELS 6 ", "CHANNELS ", 2).replace("CHANNELS ", "CHANNELS 6 ", 1),
     lambda b: _line_of(b, "CHANNELS X"), "channel count"),
    ("missing-close-brace", lambda t: _drop_line(t, _line_of(t, "}")), lambda b: _line_of(b, "MOTION"),
     "unbalanced braces"),
    ("extra-close-brace", lambda t: t.replace("MOTION", "}\nMOTION"), lambda b: _line_of(b, "MOTION") - 1,
     "unbalanced braces"),
    ("missing-motion", lambda t: t.replace("MOTION\n", "").replace("MOTION\r\n", ""),
     lambda b: _line_of(b, "Frames:"), "expected a 'MOTION' line"),
    ("missing-frames", lambda t: _drop_line(t, _line_of(t, "Frames:")), lambda b: _line_of(b, "Frame Time"),
     "'Frames: <count>'"),
    ("bad-frames", lambda t: re.sub(r"Frames:\s*\d+", "Frames: six", t), lambda b: _line_of(b, "Frames:"),
     "field 'Frames'"),
    ("missing-frame-time", lambda t: _drop_line(t, _line_of(t, "Frame Time")),
     lambda b: _line_of(b, "Frames:") + 1, "'Frame Time: <seconds>'"),
    ("bad-frame-time", lambda t: re.sub(r"Frame Time:\s*\S+", "Frame Time: -0.03", t),
     lambda b: _line_of(b, "Frame Time"), "field 'Frame Time'"),
    ("bad-offset", lambda t: re.sub(r"OFFSET (\S+) (\S+) (\S+)", r"OFFSET \1 \2", t, count=1),
     lambda b: _line_of(b, "OFFSET"),
     "three finite numbers"),
    ("no-hierarchy", lambda t: t.replace("HIERARCHY", "HIERARCHIE"), lambda b: 1, "HIERARCHY"),
    ("empty", lambda t: "", lambda b: 1, "empty file"),
    ("blank", lambda t: " \n\t\r\n", lambda b: 1, "empty file"),
]


@pytest.mark.parametrize("case", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_input_names_file_and_line(clip, case):
    _, mutate, line_of, part = case
    good = _short(clip[1].decode())
    parse_bvh(good, "good.bvh")  # the unmutated text is fine
    bad = mutate(good)
    assert bad != good
    with pytest.raises(MotionFormatError) as info:
        parse_bvh(bad, "broken_clip.bvh")
    e = info.value
    expected = line_of(bad)
    assert e.source == "broken_clip.bvh" and e.line == expected, str(e)
    assert str(e).startswith(f"broken_clip.bvh, line {expected}: ") and part in str(e), str(e)
