"""Artifact I/O: kinds, versions, provenance, atomic writes."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from motok import __version__
from motok.artifacts import ArtifactError, Provenance, hash_inputs, open_artifact, provenance_of, write_artifact
from motok.atomic import atomic_path, write_json


def _prov(**kw):
    return Provenance(command="motok test", config={"a": 1}, **kw)


def test_roundtrip_kind_version_provenance(tmp_path):
    src = tmp_path / "input.bin"
    src.write_bytes(b"motion")
    p = tmp_path / "x.h5"
    with write_artifact(p, "motion", _prov(inputs=hash_inputs([src]))) as f:
        f.create_dataset("a", data=np.arange(3))
    with open_artifact(p, "motion") as f:
        prov = provenance_of(f)
        assert f.attrs["kind"] == "motion" and int(f.attrs["schema_version"]) == 1
    assert prov.motok_version == __version__ and prov.config == {"a": 1}
    # sha256 of b"motion"
    import hashlib
    assert prov.inputs[str(src)] == hashlib.sha256(b"motion").hexdigest()


def test_crash_leaves_no_file(tmp_path):
    p = tmp_path / "x.h5"
    with pytest.raises(RuntimeError):
        with write_artifact(p, "motion", _prov()) as f:
            f.create_dataset("a", data=np.arange(3))
            raise RuntimeError("boom")
    assert not p.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["clip.gif", "clip.mp4", "curves.png", "walk.bvh", "lib.npz"])
def test_atomic_path_replaces_only_on_success_and_keeps_the_suffix(tmp_path, name):
    target = tmp_path / "out" / name
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.suffix == target.suffix and tmp.name.startswith(".")
        tmp.write_bytes(b"first")
    assert target.read_bytes() == b"first"
    with pytest.raises(KeyboardInterrupt):  # a crash or Ctrl-C half way: the old file stays whole
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise KeyboardInterrupt
    assert target.read_bytes() == b"first" and [p.name for p in target.parent.iterdir()] == [name]


def _strict(text):
    """Parse as a strict JSON reader (jq, JavaScript) would: NaN and Infinity are errors."""
    import json

    def reject(c):
        raise ValueError(f"not JSON: {c}")
    return json.loads(text, parse_constant=reject)


def test_results_json_is_strict_and_atomic(tmp_path):
    from pathlib import Path

    path = tmp_path / "eval.json"
    obj = {"reached": 0.0, "time": float("nan"), "top": float("inf"), "n": 3, "ok": True,
           "per": [1.5, np.float32("nan"), np.float64(-np.inf), (np.float32(0.25), np.int64(7))],
           "nested": {"empty": float("nan"), "where": Path("runs/x"), "mask": np.array([True, False])}}
    write_json(path, obj)
    got = _strict(path.read_text())
    assert got == {"reached": 0.0, "time": None, "top": None, "n": 3, "ok": True,
                   "per": [1.5, None, None, [0.25, 7]], "nested": {"empty": None, "where": "runs/x", "mask": [True, False]}}
    assert obj["time"] != obj["time"]  # the caller's object is left as it was
    with pytest.raises(TypeError):  # what JSON cannot hold fails, and the old file stays whole
        write_json(path, {"x": object()}, default=None)
    assert _strict(path.read_text()) == got and [p.name for p in tmp_path.iterdir()] == ["eval.json"]


def test_written_files_get_the_ordinary_mode(tmp_path):
    """safetensors (like mkstemp) creates 0600 files: a checkpoint sent to someone else must stay readable."""
    import os

    import torch
    from safetensors.torch import save_file

    umask = os.umask(0o022)
    os.umask(umask)
    with atomic_path(tmp_path / "private.bin") as tmp:
        os.close(os.open(tmp, os.O_CREAT | os.O_WRONLY, 0o600))
    with atomic_path(tmp_path / "model.safetensors") as tmp:
        save_file({"w": torch.zeros(2)}, str(tmp))
    for name in ("private.bin", "model.safetensors"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name


def test_wrong_kind_and_version_are_named(tmp_path):
    p = tmp_path / "x.h5"
    with write_artifact(p, "motion", _prov()):
        pass
    with pytest.raises(ArtifactError, match="expected a motion-dataset artifact, found kind 'motion'"):
        open_artifact(p, "motion-dataset")
    with h5py.File(p, "a") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(ArtifactError, match="schema version 99 is not supported"):
        open_artifact(p, "motion")
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w"):
        pass
    with pytest.raises(ArtifactError, match="not a motok artifact"):
        open_artifact(plain)
    junk = tmp_path / "junk.h5"
    junk.write_text("hello")
    with pytest.raises(ArtifactError, match="not an HDF5 file"):
        open_artifact(junk)


def test_a_checkpoint_interrupted_while_saving_leaves_the_last_one_whole(tmp_path, monkeypatch):
    """A training killed in the seconds a checkpoint takes to write (a session's end) must resume
    from the previous checkpoint, not find new weights beside a bundle.json that refuses them."""
    import torch

    from motok.checkpoint import load_bundle, register_kind, save_bundle

    register_kind("test-ckpt")
    run = tmp_path / "run"
    old = {"w": torch.arange(4.0)}
    save_bundle(run, "test-ckpt", old, {"lr": 1}, _prov(), train_state={"iteration": torch.tensor(100)})

    def killed(*a, **k):
        raise KeyboardInterrupt  # stands for the kill, after the new weights were already written
    monkeypatch.setattr(torch, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        save_bundle(run, "test-ckpt", {"w": torch.zeros(4)}, {"lr": 1}, _prov(),
                    train_state={"iteration": torch.tensor(200)})
    monkeypatch.undo()
    meta, state, ts = load_bundle(run, "test-ckpt", with_train_state=True)
    assert torch.equal(state["w"], old["w"]) and int(ts["iteration"]) == 100
    assert sorted(p.name for p in run.iterdir()) == ["bundle.json", "model.safetensors", "train_state.pt"]
    save_bundle(run, "test-ckpt", {"w": torch.ones(4)}, {"lr": 2}, _prov(), train_state={"iteration": torch.tensor(300)})
    meta, state, ts = load_bundle(run, "test-ckpt", with_train_state=True)
    assert torch.equal(state["w"], torch.ones(4)) and int(ts["iteration"]) == 300 and meta["config"] == {"lr": 2}


def test_provenance_records_the_machine_and_its_kernels(small_dataset):
    """A real artifact says which CPU, SIMD kernels and package versions made it (a run repeats to
    the digit only on the same ones; docs/results.md); a record from before machines were recorded
    is read as unknown, never as this machine's."""
    import json
    from importlib import metadata

    from motok.machine import machine_record

    with open_artifact(small_dataset, "motion-dataset") as f:
        m = provenance_of(f).machine
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__
    except ImportError:
        from numpy.core._multiarray_umath import __cpu_dispatch__
    assert m["cpu"] and m["cores"] >= 1 and set(m["numpy_simd"]) <= set(__cpu_dispatch__)
    assert m["packages"]["numpy"] == np.__version__ and m["packages"]["h5py"] == metadata.version("h5py")
    assert m["packages"]["torch"] == metadata.version("torch") and m["torch_cpu_capability"]
    # the dataset was made in this process (its env and torch threads may have had other test settings)
    now, moment = machine_record(), ("env", "torch_threads")
    assert {k: v for k, v in m.items() if k not in moment} == {k: v for k, v in now.items() if k not in moment}
    old = json.loads(_prov().to_json())
    del old["machine"]
    assert Provenance.from_json(json.dumps(old)).machine == {}


def test_capped_kernels_are_recorded_and_named_as_other_arithmetic():
    """A process with its kernels capped (torch to its default level, numpy's dispatched SIMD targets
    switched off, as the variables that repeat an AVX2 run on an AVX-512 machine do) records other
    kernels and the variables, and the record's comparison names exactly what changed; the same
    process compared with itself names nothing."""
    import json
    import os
    import subprocess
    import sys

    import torch  # noqa: F401  (imported, so that the record holds torch's kernel level)

    from motok.machine import arithmetic_differences, machine_record

    here = machine_record()
    assert arithmetic_differences(here) == [] and arithmetic_differences({}) == []
    caps = {"ATEN_CPU_CAPABILITY": "default", "NPY_DISABLE_CPU_FEATURES": " ".join(here["numpy_simd"])}
    out = subprocess.run([sys.executable, "-c", "import json, torch; from motok.machine import machine_record; "
                          "print(json.dumps(machine_record()))"], env=dict(os.environ, **caps),
                         capture_output=True, text=True, check=True)
    capped = json.loads(out.stdout)
    assert capped["torch_cpu_capability"] == "DEFAULT" and capped["numpy_simd"] == []
    assert {k: capped["env"][k] for k in caps} == caps
    # env always differs (the caps are new); the kernels wherever this machine dispatched more than the caps allow
    expected = [k for k, moved in (("torch_cpu_capability", here["torch_cpu_capability"] != "DEFAULT"),
                                   ("numpy_simd", bool(here["numpy_simd"])), ("env", True),
                                   ("torch_threads", here["torch_threads"] != capped["torch_threads"])) if moved]
    assert [c.split(":")[0] for c in arithmetic_differences(here, capped)] == expected


def test_a_motion_written_in_batches_equals_one_written_at_once(small_dataset, tmp_path):
    """`MotionWriter` (what `control generate` streams its episodes through) writes the same file
    as `write_motion` whatever the batches, and a failure midway leaves no file."""
    from motok.data.dataset import MotionFile, MotionWriter, write_motion

    with MotionFile(small_dataset) as mf:
        clips = [mf.clip(i) for i in range(len(mf))]
        sk, offsets, fps, legacy = mf.skeleton, mf.offsets, mf.fps, mf.legacy
    prov = Provenance(command="test", config={})
    write_motion(tmp_path / "once.h5", "motion", prov, clips, sk, offsets, fps, legacy)
    with MotionWriter(tmp_path / "batches.h5", "motion", prov, sk, offsets, fps, legacy) as w:
        for a, b in ((0, 1), (1, 10), (10, 10), (10, len(clips))):  # one clip, many, none, the rest
            w.add(clips[a:b])
    with MotionFile(tmp_path / "once.h5") as one, MotionFile(tmp_path / "batches.h5") as bat:
        assert bat.names == one.names and np.array_equal(bat.frame_offsets, one.frame_offsets)
        for key in ("features", "joints", "local_quats", "root_translation"):
            assert np.array_equal(bat.h5["frames"][key][()], one.h5["frames"][key][()])
        assert [bat.clip(i).labels for i in range(len(bat))] == [c.labels for c in clips]
        assert [bat.clip(i).captions for i in range(len(bat))] == [one.clip(i).captions for i in range(len(one))]
    with pytest.raises(RuntimeError), MotionWriter(tmp_path / "half.h5", "motion", prov, sk, offsets, fps,
                                                   legacy) as w:
        w.add(clips[:3])
        raise RuntimeError("the simulation broke")
    with pytest.raises(ValueError, match="no clips"), MotionWriter(tmp_path / "empty.h5", "motion", prov, sk,
                                                                   offsets, fps, legacy):
        pass
    assert not (tmp_path / "half.h5").exists() and not (tmp_path / "empty.h5").exists()
