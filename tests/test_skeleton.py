"""Skeleton definitions as data: built-ins, auto-detection, user YAML and its errors."""

from __future__ import annotations

import pytest
import yaml

from motok.data.bvh import read_bvh
from motok.skeleton import SkeletonError, builtin_names, detect_skeleton, load_skeleton


def test_builtins():
    assert {"smpl22", "bandai21"} <= set(builtin_names())
    s, b = load_skeleton("smpl22"), load_skeleton("bandai21")
    assert (s.num_joints, s.feature_dim) == (22, 263) and (b.num_joints, b.feature_dim) == (21, 251)
    assert [s.joints[i] for i in s.face_joints] == ["right_hip", "left_hip", "right_shoulder", "left_shoulder"]
    assert b.parents[b.index("Toes_L")] == b.index("Foot_L")


def test_detect_by_bvh_joint_names_and_by_count(bandai_slice):
    m = read_bvh(sorted(bandai_slice.glob("*.bvh"))[0])
    assert "joint_Root" in m.names
    assert detect_skeleton(joint_names=m.names).name == "bandai21"
    assert detect_skeleton(num_joints=22).name == "smpl22"
    with pytest.raises(SkeletonError, match="no built-in skeleton matches"):
        detect_skeleton(joint_names=["a", "b"])


def test_user_yaml_roundtrip_and_errors(tmp_path):
    d = load_skeleton("bandai21").to_dict()
    d["name"] = "mine"
    p = tmp_path / "mine.yaml"
    p.write_text(yaml.safe_dump(d))
    mine = load_skeleton(p)
    assert mine.name == "mine" and mine.joints == load_skeleton("bandai21").joints
    bad = dict(d, chains=[c for c in d["chains"][:-1]])
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(SkeletonError, match=r"mine.yaml: field 'chains' must reach every joint.*Shoulder_L"):
        load_skeleton(p)
    bad = dict(d, face_joints=["Hips", "Nope", "Head", "Neck"])
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(SkeletonError, match="field 'face_joints' names unknown joint 'Nope'"):
        load_skeleton(p)
    bad = {k: v for k, v in d.items() if k != "leg_joints"}
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(SkeletonError, match="lacks field 'leg_joints'"):
        load_skeleton(p)
