"""The Python API (motok.api, docs/api.md) on tiny real runs: ``import motok`` stays light, each
function gives what its command writes (the command's file and the API's output written to a
file hold the same arrays, byte for byte), mistakes are one line, and every example of
docs/api.md runs."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

import motok
import tiny_runs
from motok.errors import MotokError, UserError
from tiny_runs import tiny_prior_bundle

tree = tiny_runs.tree  # runs/{tok, tokens.h5, gpt} (a module fixture)

pytestmark = pytest.mark.usefixtures("one_thread")

ROOT = Path(__file__).resolve().parents[1]
TEXTS = ["a person walks forward", "someone waves"]


@pytest.fixture(scope="module")
def runs(tree, hum, small_dataset, tmp_path_factory):
    """The runs docs/api.md names, beside the tiny tokenizer and GPT: ``bandai2.h5`` (the walk
    slice), ``expert``, ``prior_hybrid`` (2-iteration, untrained) and ``nav`` (a 2-iteration
    navigation policy over the prior), with the reference caches in the test's folders."""
    from motok.control.highlevel.policy import HighLevelNetConfig, TaskTrainConfig
    from motok.control.highlevel.train import train_from_prior
    from motok.sim.reference import load_library

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MOTOK_CACHE", str(tmp_path_factory.mktemp("cache")))
        (tree / "bandai2.h5").symlink_to(small_dataset)
        tiny_prior_bundle(tree, hum, load_library(hum, small_dataset, clips=[0, 1, 2]), small_dataset)
        (tree / "prior").rename(tree / "prior_hybrid")
        cfg = TaskTrainConfig(seed=0, iterations=2, save_every=1000, task="navigation")
        cfg.env.num_envs, cfg.env.nthread = 4, 1
        cfg.ppo = replace(cfg.ppo, horizon=8, epochs=1, minibatch_size=16)
        cfg.net = HighLevelNetConfig(policy=[16], value=[16])
        train_from_prior(cfg, tree / "prior_hybrid", tree / "nav", codebooks=2)
        yield tree


def cli(*args: str) -> str:
    from motok.cli.main import app

    r = CliRunner().invoke(app, ["--quiet", *args])
    assert r.exit_code == 0, (args, r.output)
    return r.stdout


def h5_content(path, skip=()) -> dict:
    """Every dataset's bytes and every attribute of an HDF5 file, but its provenance (which names
    the command and the time) and the datasets in ``skip``."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            out.update({f"{name}@{k}": repr(v) for k, v in obj.attrs.items() if k != "provenance"})
            if isinstance(obj, h5py.Dataset) and name not in skip:
                v = obj[()]
                out[name] = repr(v.tolist()) if v.dtype.kind == "O" else (str(v.dtype), v.shape, v.tobytes())
        visit("/", f)
        f.visititems(visit)
    return out


# ---------------------------------------------------------------------- importing motok

def run_python(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def test_import_motok_is_quick_and_loads_neither_torch_nor_mujoco():
    res = run_python(
        "import json, sys, time; t = time.perf_counter(); import motok; t = time.perf_counter() - t\n"
        "first = sorted(m for m in sys.modules if m.split('.')[0] in ('motok', 'torch', 'mujoco', 'numpy'))\n"
        "motok.Motion; motok.load_motions\n"
        "print(json.dumps({'s': t, 'first': first, 'file': motok.__file__,"
        " 'heavy': sorted(m for m in ('torch', 'mujoco') if m in sys.modules)}))")
    assert res["file"] == str(ROOT / "motok" / "__init__.py")
    assert res["first"] == ["motok"] and res["s"] < 0.5, res  # the package alone: no stage, no numpy
    assert res["heavy"] == []  # the motion half of the API reads and writes HDF5 without torch


def test_the_lazy_names_are_the_api():
    from motok.api import models, motion

    assert set(motok.API) == set(motion.__all__) | set(models.__all__)
    for name, module in motok.API.items():
        assert getattr(motok, name) is getattr({"motion": motion, "models": models}[module], name)
        assert name in dir(motok)
    # no API name is also a module of the package, which would hide it once imported (motok.render)
    modules = {p.stem for p in (ROOT / "motok").iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()}
    assert not set(motok.API) & modules
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        motok.nope


def test_no_module_of_motok_takes_an_api_name_from_the_package():
    """The package serves the API lazily; a module importing an API name from ``motok`` would run
    the API (every stage) in the middle of its own import, the circle the import check cannot see."""
    found = []
    for path in (ROOT / "motok").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module == "motok" and not node.level:
                found += [f"{path.name}: {a.name}" for a in node.names if a.name in motok.API]
    assert not found


# ---------------------------------------------------------------------- the API gives what the commands write

def test_generate_render_and_export_give_what_gpt_sample_writes(runs, tmp_path):
    opts = ["-n", "2", "--seed", "3", "--seconds", "1.6", "--top-k", "20", "--temperature", "0.9"]
    texts = [a for t in TEXTS for a in ("--text", t)]
    cli("gpt", "sample", "-g", str(runs / "gpt"), *texts, *opts, "-o", str(tmp_path / "cli.h5"),
        "--render", str(tmp_path / "cli.gif"), "--bvh", str(tmp_path / "cli.bvh"))
    gpt = motok.load_gpt(runs / "gpt")
    walks = motok.generate(gpt, TEXTS, num_samples=2, seed=3, seconds=1.6, top_k=20, temperature=0.9)
    assert [m.caption for m in walks] == [t for t in TEXTS for _ in range(2)]
    assert [m.labels["seed"] for m in walks] == [3, 4, 3, 4]
    assert walks[0].joints.shape == (32, 21, 3) and walks[0].features.shape == (32, 251) and walks[0].fps == 20
    motok.save_motions(walks, tmp_path / "api.h5")
    assert h5_content(tmp_path / "api.h5") == h5_content(tmp_path / "cli.h5")
    for m in walks:
        gif, bvh = motok.render_motion(m, tmp_path / "api.gif"), motok.export_bvh(m, tmp_path / "api.bvh")
        assert gif.read_bytes() == (tmp_path / f"cli_{m.name}.gif").read_bytes()
        assert bvh.read_bytes() == (tmp_path / f"cli_{m.name}.bvh").read_bytes()
    # `motok render` and `export bvh` of a clip of the file: the same pictures and BVH
    cli("render", "-d", str(tmp_path / "cli.h5"), "--clip", walks[1].name, "-o", str(tmp_path / "one.png"))
    cli("export", "bvh", "-d", str(tmp_path / "cli.h5"), "--clip", walks[1].name, "-o", str(tmp_path / "one.bvh"))
    again = motok.load_motions(tmp_path / "cli.h5", clips="*-01")
    assert [m.name for m in again] == [walks[1].name, walks[3].name]
    assert motok.render_motion(again[0], tmp_path / "two.png").read_bytes() == (tmp_path / "one.png").read_bytes()
    assert motok.export_bvh(again[0], tmp_path / "two.bvh").read_bytes() == (tmp_path / "one.bvh").read_bytes()
    frames = motok.render_frames(walks[0], max_frames=5, size=(64, 48))
    assert frames.shape == (5, 48, 64, 3) and frames.dtype == np.uint8 and frames.std() > 0
    assert np.array_equal(frames, motok.render_frames(walks[0], max_frames=5, size=(64, 48)))


def test_encode_and_decode_give_what_tokenize_writes(runs, tmp_path):
    from motok.data.dataset import MotionFile
    from motok.tokenizer.tokens import TokenFile

    cli("tokenize", "encode", "-d", str(runs / "bandai2.h5"), "-t", str(runs / "tok"), "-o", str(tmp_path / "t.h5"))
    cli("tokenize", "decode", "-d", str(tmp_path / "t.h5"), "-t", str(runs / "tok"), "-o", str(tmp_path / "d.h5"))
    tok = motok.load(runs / "tok")
    data = motok.load_motions(runs / "bandai2.h5")
    with TokenFile(tmp_path / "t.h5") as tf, MotionFile(tmp_path / "d.h5") as dec:
        assert tf.names == [m.name for m in data]
        for i, m in enumerate(data[:4]):
            codes = motok.encode(tok, m)
            assert codes.dtype == np.int32 and np.array_equal(codes, tf.indices(i))
            back, ref = motok.decode(tok, codes, name=m.name), dec.clip(m.name)
            assert back.num_frames == m.num_frames // tok.rate * tok.rate == ref.num_frames
            for key in ("features", "joints", "local_quats", "root_translation"):
                assert np.array_equal(getattr(back.clip, key), getattr(ref, key)), key
    one = motok.decode(tok, codes[:, 0].tolist(), caption="a walk")  # (L,) lists too
    assert one.caption == "a walk" and one.name == "decoded"
    with pytest.raises(UserError, match="codes must be integers in 0..31"):
        motok.decode(tok, [3, 32])
    with pytest.raises(MotokError, match="the tokenizer has 1 codebook"):
        motok.encode(tok, data[0], codebooks=2)


def test_track_gives_what_control_track_writes(runs, small_dataset, tmp_path):
    gpt = motok.load_gpt(runs / "gpt")
    motok.save_motions(motok.generate(gpt, TEXTS, seed=1, seconds=1.6), tmp_path / "walk.h5")
    out = tmp_path / "cli_sim.h5"
    cli("control", "track", "-d", str(tmp_path / "walk.h5"), "--prior", str(runs / "prior_hybrid"), "-o", str(out),
        "--render", str(tmp_path / "cli_sim.gif"))
    written = json.loads(out.with_name("cli_sim.track.json").read_text())
    prior = motok.load_controller(runs / "prior_hybrid")
    res = motok.track(prior, motok.load_motions(tmp_path / "walk.h5"), render=tmp_path / "api_sim.gif")
    assert res.per_clip == written["per_clip"] and len(res.motions) == written["written"]
    assert {k: v for k, v in res.summary.items() if k != "video"} == \
        {k: v for k, v in written.items() if k in res.summary and k != "video"}
    assert (tmp_path / "api_sim.gif").read_bytes() == (tmp_path / "cli_sim.gif").read_bytes()
    motok.save_motions(res.motions, tmp_path / "api_sim.h5")
    # the same simulated clips; only the source they name differs (the file, or memory)
    assert h5_content(tmp_path / "api_sim.h5", skip={"clips/source"}) == h5_content(out, skip={"clips/source"})
    sim = res.motions[0]
    assert sim.labels["tracked_to_end"] == res.per_clip[sim.name]["tracked_to_end"] and sim.fps == 20
    expert = motok.load(runs / "expert")
    assert repr(expert).startswith("Controller(an expert") and motok.track(expert, sim).summary["clips"] == 1


def test_evaluate_task_gives_what_control_eval_reports(runs):
    out = json.loads(cli("control", "eval", "--task", "navigation", "--policy", str(runs / "nav"), "-n", "2",
                         "--json"))
    nav = motok.load(runs / "nav")
    assert isinstance(nav, motok.TaskPolicy) and nav.task == "navigation" and "hybrid prior" in repr(nav)
    res = motok.evaluate_task(nav, episodes=2)
    for key in ("episodes", "targets", "reached_share", "falls_per_episode", "mean_reward", "checkpoint"):
        assert res[key] == out[key], key
    assert "provenance" not in res and "written" not in res


# ---------------------------------------------------------------------- mistakes

def test_mistakes_are_one_line_naming_what_was_expected(runs, small_dataset, tmp_path):
    with pytest.raises(UserError, match="expected a control-expert or control-prior bundle, found kind 'gpt'"):
        motok.load_controller(runs / "gpt")
    with pytest.raises(UserError, match="an expert has none"):
        motok.load_controller(runs / "expert", codebooks=1)
    with pytest.raises(MotokError, match="no bundle.json"):
        motok.load(runs)
    walks = motok.load_motions(small_dataset, clips="dataset-2_walk_normal_00[12]")
    other = motok.Motion(walks[1].clip, walks[1].skeleton, 30.0, walks[1].offsets)
    with pytest.raises(UserError, match="differ in skeleton, frame rate"):
        motok.save_motions([walks[0], other], tmp_path / "x.h5")
    with pytest.raises(UserError, match="must be distinct"):
        motok.save_motions([walks[0], walks[0]], tmp_path / "x.h5")
    with pytest.raises(UserError, match="expected a Motion or a list of them, got an empty list"):
        motok.save_motions([], tmp_path / "x.h5")
    with pytest.raises(MotokError, match="unknown suffix"):
        motok.save_motions(walks, tmp_path / "x.bvh")
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------- docs/api.md

RUNS_LINE = 'RUNS = Path("runs")'


def doc_blocks() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", (ROOT / "docs" / "api.md").read_text(encoding="utf-8"),
                      flags=re.S | re.M)


def test_every_example_of_the_docs_runs(runs, tmp_path, monkeypatch):
    """The blocks of docs/api.md in order, in one namespace, from an empty folder, with ``RUNS``
    pointing at this module's runs (the page's one convention)."""
    blocks = doc_blocks()
    assert len(blocks) >= 6 and sum(b.count(RUNS_LINE) for b in blocks) == 1
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    namespace: dict = {"__name__": "docs_api"}
    for i, block in enumerate(blocks):
        code = block.replace(RUNS_LINE, f"RUNS = Path({str(runs)!r})")
        exec(compile(code, f"docs/api.md, python block {i + 1}", "exec"), namespace)
    for name in ("walk.gif", "walk.bvh", "walk.h5", "walk_sim.mp4", "walk_sim.gif"):
        assert (tmp_path / name).stat().st_size > 0, name


def test_the_readme_example_runs(runs, monkeypatch):
    """README's "From Python" block, from the folder that holds runs/ (as the README's commands run)."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"### From Python\n.*?```python\n(.*?)```", readme, flags=re.S).group(1)
    assert len([ln for ln in block.splitlines() if ln.strip()]) == 6
    monkeypatch.chdir(runs.parent)
    monkeypatch.setenv("MOTOK_CACHE", str(runs.parent / "cache"))
    namespace: dict = {"__name__": "readme"}
    exec(compile(block, "README.md, From Python", "exec"), namespace)
    assert (runs.parent / "walk.gif").stat().st_size > 0 and len(namespace["result"].per_clip) == 4
