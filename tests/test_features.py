"""The HumanML3D representation (motok.features) against the official golden clip and real mocap."""

from __future__ import annotations

import dataclasses
import tarfile

import numpy as np
import pytest
import torch

from motok.features import kinematics
from motok.features.humanml3d import (
    SMPL_LEG_LENGTH, STD_EPS, contact_threshold, extract_features, feature_slices, forward_kinematics,
    inverse_kinematics, mean_std, recover_from_ric, recover_local_quats, recover_root, resample_positions,
    resample_quats, skeleton_offsets,
)
from motok.rotations import euler_to_quat, qmul, qrot, quat_to_euler, yaw_quat
from motok.skeleton import load_skeleton

# HumanML3D paramUtil.t2m_raw_offsets / t2m_kinematic_chain, by joint index.
T2M_RAW_OFFSETS = np.array([
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
    [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0]], dtype=np.float64)
T2M_CHAINS = ((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15), (9, 14, 17, 19, 21), (9, 13, 16, 18, 20))
CONFORMANT_FRAMES = 89  # the golden features come from 171 frames, ours from 170: sigma-20 smoothing
# (radius 80) of the forward sees the missing last frame only from frame 89 on.
BANDAI_MEMBERS = ("dataset-2_run_feminine_021.bvh", "dataset-2_walk-turn-left_active_041.bvh",
                  "dataset-2_raise-up-both-hands_elderly_006.bvh")


@pytest.fixture(scope="module")
def smpl22():
    return load_skeleton("smpl22")


@pytest.fixture(scope="module")
def bandai21():
    return load_skeleton("bandai21")


def _facing_angle(joints0, skeleton):
    """Yaw (rad) of the body's forward at one frame, measured from +Z."""
    r_hip, l_hip, r_sdr, l_sdr = skeleton.face_joints
    across = joints0[r_hip] - joints0[l_hip] + joints0[r_sdr] - joints0[l_sdr]
    fwd = np.cross([0.0, 1.0, 0.0], across)
    return float(np.arctan2(fwd[0], fwd[2]))


# --- skeleton definition ------------------------------------------------------------------

def test_smpl22_chains_match_humanml3d():
    assert load_skeleton("smpl22").chains == T2M_CHAINS


def test_smpl22_directions_match_humanml3d():
    np.testing.assert_array_equal(load_skeleton("smpl22").directions, T2M_RAW_OFFSETS)


def test_feature_layout():
    for J, dim in ((22, 263), (21, 251)):
        sl = feature_slices(J)
        assert list(sl) == ["root_rot_velocity", "root_linear_velocity", "root_y", "ric", "rot",
                            "local_velocity", "foot_contact"]
        assert [s.stop - s.start for s in sl.values()] == [1, 2, 1, 3 * (J - 1), 6 * (J - 1), 3 * J, 4]
        assert sl["foot_contact"].stop == dim == 12 * J - 1


# --- 1. the official inverse --------------------------------------------------------------

@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_recover_from_ric_golden(golden_features, golden_joints, backend):
    f = golden_features if backend == "numpy" else torch.from_numpy(golden_features)
    rec = recover_from_ric(f, 22)
    assert type(rec) is type(f)
    rec = rec.numpy() if backend == "torch" else rec
    assert rec.shape == golden_joints.shape and rec.dtype == np.float32
    np.testing.assert_allclose(rec, golden_joints, atol=1e-5, rtol=0)


def test_recover_batched_torch_matches_numpy(golden_features):
    batch = torch.from_numpy(np.stack([golden_features, golden_features[::-1].copy()]))
    rec = recover_from_ric(batch, 22)
    assert rec.shape == (2, 170, 22, 3)
    np.testing.assert_allclose(rec[1].numpy(), recover_from_ric(golden_features[::-1].copy(), 22), atol=1e-5)
    quat, pos = recover_root(batch)
    assert quat.shape == (2, 170, 4) and pos.shape == (2, 170, 3)


# --- 2. legacy conformance with the official features -------------------------------------

def test_legacy_matches_golden_every_block(golden_joints, golden_features, smpl22):
    res = extract_features(golden_joints, smpl22, legacy=True, fps=20, target_offsets=None)
    assert res.features.shape == (169, 263) and res.features.dtype == np.float32
    n = CONFORMANT_FRAMES
    for name, sl in feature_slices(22).items():
        err = np.abs(res.features[:n, sl] - golden_features[:n, sl]).max()
        assert err < 1e-4, f"block {name}: max abs error {err:.3g}"


def test_default_differs_from_golden_rotations(golden_joints, golden_features, smpl22):
    # The switch must matter: the default re-roots the arm chains and expresses root children
    # in the facing frame, so the 6D block departs from the official numbers.
    res = extract_features(golden_joints, smpl22)
    sl = feature_slices(22)
    n = CONFORMANT_FRAMES
    assert np.abs(res.features[:n, sl["rot"]] - golden_features[:n, sl["rot"]]).max() > 1e-2
    np.testing.assert_array_equal(res.features[:, sl["foot_contact"]], golden_features[:169, sl["foot_contact"]])


def test_legacy_arm_chains_need_t2m_directions(golden_joints, golden_features):
    # Guards the conformance test itself: with other rest directions the 6D block must fail.
    sk = load_skeleton("smpl22")
    d = T2M_RAW_OFFSETS.copy()
    d[16:22] = np.where(np.arange(16, 22)[:, None] % 2 == 0, [[1.0, 0, 0]], [[-1.0, 0, 0]])
    res = extract_features(golden_joints, dataclasses.replace(sk, directions=d), legacy=True)
    sl = feature_slices(22)["rot"]
    assert np.abs(res.features[:CONFORMANT_FRAMES, sl] - golden_features[:CONFORMANT_FRAMES, sl]).max() > 0.1


# --- 3. the default convention round-trips ------------------------------------------------

def test_default_round_trips(golden_joints, smpl22):
    res = extract_features(golden_joints, smpl22)
    np.testing.assert_allclose(recover_from_ric(res.features, 22), res.joints, atol=1e-4, rtol=0)
    np.testing.assert_allclose(res.root_translation, res.joints[:, 0])
    fk = forward_kinematics(res.local_quats, res.root_translation, res.offsets, smpl22)
    np.testing.assert_allclose(fk, res.joints, atol=1e-5, rtol=0)
    _, root_pos = recover_root(res.features)
    rot_path = forward_kinematics(recover_local_quats(res.features, smpl22), root_pos, res.offsets, smpl22)
    np.testing.assert_allclose(rot_path, res.joints, atol=1e-4, rtol=0)


def test_default_root_is_smoothed_heading(golden_joints, smpl22):
    # The default keeps HumanML3D's sigma-20 smoothed forward (correct face order) as r_rot, and
    # faces +Z by its frame-0 value, so the recovered r_rot starts at the identity.
    res = extract_features(golden_joints, smpl22)
    quat, _ = recover_root(res.features)
    expect = kinematics.root_rotation(res.joints.astype(np.float64), smpl22, smooth=True)
    n = CONFORMANT_FRAMES - 1  # res.joints lacks the last frame; the smoothing sees it from here on
    np.testing.assert_allclose(np.abs((quat[:n] * expect[:n]).sum(-1)), 1.0, atol=1e-6)
    np.testing.assert_allclose(expect[0], [1.0, 0.0, 0.0, 0.0], atol=1e-6)


def test_legacy_rotation_path(golden_features, smpl22):
    # The official recover_from_rot on the official features gives the official joints.
    offsets = skeleton_offsets(recover_from_ric(golden_features, 22)[0], smpl22)
    _, root_pos = recover_root(golden_features)
    pos = forward_kinematics(recover_local_quats(golden_features, smpl22, legacy=True), root_pos, offsets,
                             smpl22, legacy=True)
    np.testing.assert_allclose(pos, recover_from_ric(golden_features, 22), atol=1e-4, rtol=0)


@pytest.mark.parametrize("legacy", [False, True])
def test_uniform_skeleton_is_ik_then_fk(golden_joints, smpl22, legacy):
    x = golden_joints.astype(np.float64) * 1.3 + np.array([0.2, 0.1, -0.4])
    tgt = skeleton_offsets(golden_joints[0], smpl22) * 0.9
    src = skeleton_offsets(x[0], smpl22)
    quats = inverse_kinematics(x, smpl22, smooth_forward=False, legacy=legacy)
    np.testing.assert_allclose(forward_kinematics(quats, x[:, 0], src, smpl22, legacy=legacy), x, atol=1e-5)
    scale = kinematics.leg_length(tgt, smpl22) / kinematics.leg_length(src, smpl22)
    explicit = forward_kinematics(quats, x[:, 0] * scale, tgt, smpl22, legacy=legacy)
    np.testing.assert_allclose(kinematics.uniform_skeleton(x, smpl22, tgt), explicit, atol=1e-9)


def test_target_offsets_retarget(golden_joints, smpl22):
    tgt = skeleton_offsets(golden_joints[0], smpl22) * 1.25
    res = extract_features(golden_joints, smpl22, target_offsets=tgt)
    lengths = np.linalg.norm(res.joints[:, 1:] - res.joints[:, smpl22.parents[1:]], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(np.linalg.norm(tgt[1:], axis=-1), lengths.shape), atol=1e-5)
    base = extract_features(golden_joints, smpl22)
    # Everything scales with the body: the root path by the leg ratio, heights by the bones.
    np.testing.assert_allclose(res.joints, base.joints * 1.25, atol=1e-4)


# --- 4. real mocap: Bandai-Namco set 2 ----------------------------------------------------

def _parse_bvh(text):
    """Minimal BVH reader for the Bandai files: joint names, parents, frame time, (T, J, 6) channels."""
    head, motion = text.split("MOTION")
    names, parents, stack, last = [], [], [], None
    for line in head.splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] in ("ROOT", "JOINT"):
            names.append(tok[1])
            parents.append(stack[-1] if stack else -1)
            last = len(names) - 1
        elif tok[0] == "End":
            last = None
        elif tok[0] == "{":
            stack.append(last)
        elif tok[0] == "}":
            stack.pop()
    lines = motion.strip().splitlines()
    frame_time = float(lines[1].split(":")[1])
    data = np.array([ln.split() for ln in lines[2:] if ln.strip()], dtype=np.float64)
    return names, parents, frame_time, data.reshape(len(data), len(names), 6)


def _bvh_positions(parents, data):
    """Global joint positions: every joint carries its own translation channels (cm), rotations ZXY."""
    q = euler_to_quat(data[..., 3:], "ZXY")  # channels Zrotation Xrotation Yrotation
    g = np.zeros(q.shape)
    p = np.zeros(data.shape[:-1] + (3,))
    for j, parent in enumerate(parents):
        if parent < 0:
            g[:, j], p[:, j] = q[:, j], data[:, j, :3]
        else:
            g[:, j] = qmul(g[:, parent], q[:, j])
            p[:, j] = p[:, parent] + qrot(g[:, parent], data[:, j, :3])
    return p


@pytest.fixture(scope="module")
def bandai_clips(bandai2_archive, bandai21):
    """name -> positions (T, 21, 3) in metres at 30 fps, joint_Root dropped, in bandai21 order."""
    out = {}
    with tarfile.open(bandai2_archive, "r|xz") as tf:
        for member in tf:
            base = member.name.rsplit("/", 1)[-1]
            if member.name.startswith("Bandai-Namco-Research-Motiondataset-2/data/") and base in BANDAI_MEMBERS:
                names, parents, frame_time, data = _parse_bvh(tf.extractfile(member).read().decode())
                assert round(1.0 / frame_time) == 30
                pos = _bvh_positions(parents, data) / 100.0
                out[base] = pos[:, [names.index(n) for n in bandai21.joints]]
                if len(out) == len(BANDAI_MEMBERS):
                    break
    assert sorted(out) == sorted(BANDAI_MEMBERS), f"archive lacks some of {BANDAI_MEMBERS}"
    return out


@pytest.mark.parametrize("clip", BANDAI_MEMBERS)
def test_bandai_features(bandai_clips, bandai21, clip):
    pos30 = bandai_clips[clip]
    pos = resample_positions(pos30, 30, 20)
    assert len(pos) == int(np.floor((len(pos30) - 1) * 20 / 30)) + 1
    res = extract_features(pos, bandai21, fps=20)
    f = res.features
    assert f.shape == (len(pos) - 1, 251)
    assert np.isfinite(f).all()
    np.testing.assert_allclose(recover_from_ric(f, 21), res.joints, atol=1e-4, rtol=0)
    np.testing.assert_allclose(forward_kinematics(res.local_quats, res.root_translation, res.offsets, bandai21),
                               res.joints, atol=1e-5, rtol=0)
    contacts = f[:, feature_slices(21)["foot_contact"]]
    assert set(np.unique(contacts)) <= {0.0, 1.0}
    if "raise-up" in clip:  # standing still: both feet planted almost throughout
        assert contacts.mean() > 0.9
    else:  # locomotion: each foot both planted and swinging
        assert (contacts.min(0) == 0).all() and (contacts.max(0) == 1).all()
    # Faces +Z at frame 0: exactly by frame 0's own forward in legacy mode, by the smoothed one
    # (within the sway of one stride) by default.
    assert abs(_facing_angle(res.joints[0], bandai21)) < np.radians(10)
    legacy = extract_features(pos, bandai21, fps=20, legacy=True)
    assert abs(_facing_angle(legacy.joints[0], bandai21)) < 1e-5
    assert res.joints[..., 1].min() == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(res.joints[0, 0, [0, 2]], 0.0, atol=1e-6)


# --- 5. the small pieces ------------------------------------------------------------------

def test_mean_std_block_average():
    J = 2  # blocks of 1, 2, 1, 3, 6, 6, 4 dims
    v = np.arange(1.0, 24.0)
    v[19:] = 0.0  # a constant block: its std is guarded
    data = np.stack([np.zeros(23), v])  # std of each dim = v / 2
    mean, std = mean_std(data, J)
    np.testing.assert_allclose(mean, v / 2)
    expect = np.repeat([0.5, 1.25, 2.0, 3.0, 5.25, 8.25, 1.0], [1, 2, 1, 3, 6, 6, 4])
    np.testing.assert_allclose(std, expect)
    mean2, std2 = mean_std([data[:1], data[1:]], J)  # a list of clips, concatenated over time
    np.testing.assert_allclose(std2, expect)
    assert STD_EPS > 0
    with pytest.raises(ValueError):
        mean_std(np.zeros((3, 24)), J)


def test_resample_grid():
    t30 = np.arange(128) / 30.0
    x = np.stack([t30, 2 * t30 + 1.0], -1)  # linear in time: interpolation must be exact
    y = resample_positions(x, 30, 20)
    assert y.shape == (85, 2)  # floor(127 * 20 / 30) + 1
    t20 = np.arange(85) / 20.0
    np.testing.assert_allclose(y, np.stack([t20, 2 * t20 + 1.0], -1), atol=1e-12)
    assert len(resample_positions(np.zeros((121, 3)), 60, 20)) == 41  # exact multiple keeps the last frame
    np.testing.assert_array_equal(resample_positions(x, 30, 30), x)
    up = resample_positions(x, 30, 60)
    assert len(up) == 255 and up[-1, 0] == pytest.approx(t30[-1])


def test_resample_quats_slerp():
    angles = np.linspace(0.0, 3.0, 31)  # yaw ramp, 0.1 rad per source frame
    q = yaw_quat(angles)
    q[5] *= -1  # the sign of a quaternion must not matter
    r = resample_quats(q, 30, 20)
    assert r.shape == (21, 4)
    # Output k sits at source frame 1.5 k: even k land on source frames, odd k halfway between.
    yaw = quat_to_euler(r, "YXZ")[:, 0]
    np.testing.assert_allclose(np.radians(yaw), 0.15 * np.arange(21), atol=1e-9)
    np.testing.assert_allclose(np.abs((r[::2] * q[::3]).sum(-1)), 1.0, atol=1e-12)  # endpoints exact
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0)


def test_contact_threshold_scaling(golden_joints, smpl22):
    assert contact_threshold(smpl22, 20) == pytest.approx(0.002)
    assert contact_threshold(smpl22, 30) == pytest.approx(0.002 * 4 / 9)
    assert contact_threshold(smpl22, 20, leg_length=2 * SMPL_LEG_LENGTH) == pytest.approx(0.008)
    assert contact_threshold(smpl22, 20, leg_length=SMPL_LEG_LENGTH) == pytest.approx(0.002)
    # A body twice the size moves its feet twice as far per frame: contacts must not change.
    sl = feature_slices(22)["foot_contact"]
    small = extract_features(golden_joints, smpl22).features[:, sl]
    big = extract_features(golden_joints * 2.0, smpl22).features[:, sl]
    np.testing.assert_array_equal(big, small)
    # ...which a fixed threshold would get wrong on this clip.
    feet = list(smpl22.feet_left) + list(smpl22.feet_right)
    d2 = ((np.diff(golden_joints[:, feet].astype(np.float64) * 2.0, axis=0)) ** 2).sum(-1)
    assert ((d2 < 0.002) != small.astype(bool)).any()


@pytest.mark.parametrize("legacy", [False, True])
def test_heading_and_translation_invariance(golden_joints, smpl22, legacy):
    base = extract_features(golden_joints, smpl22, legacy=legacy).features
    q = yaw_quat(np.full(golden_joints.shape[:2], 2.1))
    moved = qrot(q, golden_joints.astype(np.float64)) + np.array([3.0, 0.7, -5.0])
    np.testing.assert_allclose(extract_features(moved, smpl22, legacy=legacy).features, base, atol=2e-5, rtol=0)


def test_contacts_need_two_feet_joints_per_side(golden_joints, smpl22):
    bad = dataclasses.replace(smpl22, feet_left=(7,))
    with pytest.raises(ValueError, match="foot joints"):
        extract_features(golden_joints, bad)


def test_qbetween_antiparallel_is_a_half_turn():
    # The official qbetween gives NaN here; a body facing exactly -Z must still get a yaw.
    q = kinematics.root_quat(np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(np.abs(q[0]), [0.0, 0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(qrot(q, np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])), [[0, 0, 1.0]] * 2, atol=1e-12)
    u = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    q = kinematics.qbetween_unit(u, -u)
    assert np.isfinite(q).all()
    np.testing.assert_allclose(qrot(q, u), -u, atol=1e-12)
