"""Inputs that do not belong together, and files that must not be lost: motion at another frame
rate or feature convention than the model that reads it (a tokenizer, the text-motion evaluator,
the label classifier), codes another tokenizer cannot decode, task settings a policy does not read,
a split the file lacks, a damaged artifact, an output over a run's own file, an evaluation over the
run's. Each is one `error:` line naming the file and both sides, before any work, with nothing
written, never a plausible number; or, for an evaluation, the old one kept."""

from __future__ import annotations

import pytest

from motok.cli.main import app

from test_bad_inputs import _one_line_error, runner
from tiny_runs import cache, controllers, tree  # noqa: F401  (fixtures)

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def other(tmp_path_factory, bandai_slice, bandai_dir):
    """The walk slice the tiny runs were trained on (20 fps), preprocessed again at 30 fps, and
    at 20 fps with the official HumanML3D quirks (``--legacy``): same joints, same feature width."""
    from motok.data.preprocess import PreprocessConfig, preprocess

    root = tmp_path_factory.mktemp("other-rates")
    out = {}
    for name, kw in (("fps30", {"fps": 30.0}), ("legacy", {"legacy": True})):
        out[name] = root / f"{name}.h5"
        cfg = PreprocessConfig(data=[str(bandai_slice)], annotations=str(bandai_dir / "annotations"),
                               clips="dataset-2_walk_normal_*", skeleton="bandai21", **kw)
        preprocess(cfg, out[name], command="pytest other")
    return out


@pytest.fixture(scope="module")
def evaluator(small_dataset, tmp_path_factory):
    """A 10-iteration evaluator on the 20 fps walk slice: untrained, but a real run."""
    from motok.eval.evaluator import resolve_config, train_evaluator

    run = tmp_path_factory.mktemp("mismatch-eval") / "ev"
    cfg = resolve_config(None, ["text_encoder=bow", "width=32", "embed_dim=32", "layers=1", "heads=2",
                                "batch_size=8", "iterations=10", "log_every=5", "max_frames=64", "threads=1"])
    train_evaluator(cfg, small_dataset, run, command="pytest")
    return run


@pytest.mark.parametrize("which,says", [("fps30", ["at 30 fps", "trained at 20 fps", "--fps 20"]),
                                        ("legacy", ["with --legacy", "without it"])])
def test_a_tokenizer_refuses_motion_at_another_rate_or_convention(tree, other, tmp_path, which, says):
    """Before: `tokenize encode`, `tokenize eval` and `eval recon` read 30 fps motion with a 20 fps
    tokenizer (the features' velocities per frame are 1.5 times smaller, a code spans 2/3 of the
    time) and wrote tokens or printed errors in millimetres, exit 0."""
    import motok
    from motok.errors import MotokError

    data, out = other[which], tmp_path / "tokens.h5"
    for args in (["tokenize", "encode", "-d", str(data), "-t", str(tree / "tok"), "-o", str(out)],
                 ["tokenize", "eval", "-d", str(data), "-t", str(tree / "tok"), "--split", "train"],
                 ["eval", "recon", "-d", str(data), "-t", str(tree / "tok"), "--split", "train"]):
        _one_line_error(runner.invoke(app, args), str(data), *says)
    assert not out.exists()
    # The same check from Python.
    tok = motok.load(tree / "tok")
    walk = motok.load_motions(data)[0]
    with pytest.raises(MotokError, match=says[0]):
        motok.encode(tok, walk)


def test_the_same_data_still_encodes(tree, small_dataset, tmp_path):
    """The check compares like with like: the data the tokenizer was trained on passes."""
    r = runner.invoke(app, ["tokenize", "encode", "-d", str(small_dataset), "-t", str(tree / "tok"),
                            "-o", str(tmp_path / "t.h5")])
    assert r.exit_code == 0, r.output


def test_t2m_refuses_rows_at_another_rate_than_its_evaluator(tree, other, evaluator, small_dataset, tmp_path,
                                                            monkeypatch):
    """Before: `eval t2m` embedded 30 fps motion with a 20 fps evaluator and printed R-precision and
    FID (and the physical columns of a `--motions` row at the data's rate), exit 0; and `eval recon
    --motions` compared frames of 30 fps clips one to one with 20 fps ones."""
    def boom(*a, **k):
        raise AssertionError("generated before the --motions rows were checked")
    monkeypatch.setattr("motok.gpt.sample.generate", boom)
    fast, out = str(other["fps30"]), tmp_path / "t2m.json"
    base = ["eval", "t2m", "-e", str(evaluator), "--split", "train", "--set", "repeats=1", "--set", "batch=4",
            "-o", str(out)]
    _one_line_error(runner.invoke(app, base + ["-d", fast]), fast, "30 fps", "trained at 20 fps")
    _one_line_error(runner.invoke(app, base + ["-d", str(small_dataset), "-g", str(tree / "gpt"), "--motions", fast]),
                    fast, "30 fps", "trained at 20 fps")
    assert not out.exists()
    _one_line_error(runner.invoke(app, ["eval", "recon", "-d", str(small_dataset), "--motions", fast,
                                        "--split", "train"]), fast, "at 30 fps", "at 20")


def test_t2m_refuses_a_gpt_whose_motion_is_at_another_rate(tree, other, tmp_path):
    """The generation row: a GPT (through its tokenizer) makes 20 fps motion; data and evaluator at
    30 fps are refused before anything is generated."""
    from motok.eval.evaluator import EvaluatorError
    from motok.eval.generate import generated_set
    from motok.eval.protocol import T2MConfig
    from motok.eval.sets import real_set

    ref, info = real_set(other["fps30"], "train")
    with pytest.raises(EvaluatorError, match="generates motion at 20 fps.*at 30 fps"):
        generated_set(tree / "gpt", None, ref, T2MConfig(), tmp_path / "g.h5", fps=info["fps"])
    assert not (tmp_path / "g.h5").exists()


def test_labels_refuses_motion_the_classifier_cannot_read(tree, other, small_dataset, monkeypatch):
    """Before: `eval labels --motions` scored 30 fps motion with a classifier fitted on 20 fps
    features, exit 0; a GPT of 20 fps motion was scored against 30 fps data the same way."""
    fast = str(other["fps30"])
    _one_line_error(runner.invoke(app, ["eval", "labels", "-d", str(small_dataset), "--motions", fast]),
                    fast, "at 30 fps", "at 20 fps")

    def boom(*a, **k):
        raise AssertionError("generated before the rates were compared")
    monkeypatch.setattr("motok.gpt.sample.generate", boom)
    _one_line_error(runner.invoke(app, ["eval", "labels", "-d", fast, "--gpt", str(tree / "gpt")]),
                    str(tree / "gpt"), "at 20 fps", f"{fast}: 251-d at 30 fps")


def test_a_split_the_file_does_not_have_is_named_as_such(tree, small_dataset, tmp_path):
    """Before: `tokenize encode --split tset` said 'no clip has at least 4 frames to encode', and a
    control command's unknown split listed the split of every clip (thousands of words)."""
    from motok.data.dataset import select_clips
    from motok.errors import UserError

    out = tmp_path / "t.h5"
    r = runner.invoke(app, ["tokenize", "encode", "-d", str(small_dataset), "-t", str(tree / "tok"),
                            "--split", "tset", "-o", str(out)])
    _one_line_error(r, str(small_dataset), "no clip in split 'tset'", "['test', 'train', 'val']")
    assert not out.exists()
    with pytest.raises(UserError) as e:
        select_clips(small_dataset, None, "tset")
    assert str(e.value).endswith("has no split 'tset' (it has ['test', 'train', 'val'])"), str(e.value)


def test_allow_mismatch_still_needs_a_tokenizer_that_can_decode_the_codes(tree, small_dataset, tmp_path):
    """`--allow-mismatch` lets another tokenizer decode, one of the same shape. Before: one with a
    smaller codebook ended `gpt sample` (after sampling) and `tokenize decode` in an IndexError
    traceback."""
    from motok.quantize.base import QuantizerConfig
    from motok.tokenizer.model import ModelConfig
    from motok.tokenizer.train import TrainConfig, train

    small = tmp_path / "tok16"
    train(TrainConfig(model=ModelConfig(width=32, depth=1), quantizer=QuantizerConfig(codebook_size=16, dim=16),
                      iterations=2, batch_size=4, window=32, log_every=1, save_every=2, threads=1),
          small_dataset, small, command="pytest")
    out = tmp_path / "out.h5"
    for args, whose in ((["gpt", "sample", "-g", str(tree / "gpt"), "--text", "a person walks", "-o", str(out)],
                         tree / "gpt"),
                        (["tokenize", "decode", "-d", str(tree / "tokens.h5"), "-o", str(out)], tree / "tokens.h5")):
        r = runner.invoke(app, args + ["-t", str(small), "--allow-mismatch"])
        _one_line_error(r, str(small), "1 codebook(s) of 16 codes", f"the codes of {whose} need", "of 32 codes")
        assert not out.exists()


@pytest.mark.parametrize("task,sets,refused", [
    ("steering", ["tasks.navigation.min_distance=1"], "tasks.navigation.min_distance=1"),
    ("steering", ["tasks.steering.max_speed=1.2", "tasks.hmd.episode_seconds=2"], "tasks.hmd.episode_seconds=2"),
    ("multitask", ["tasks.compose.target_seconds=1"], "tasks.compose.target_seconds=1"),
    ("multitask", ['tasks.multitask.tasks=["navigation","hmd"]', "tasks.multitask.switch=[]",
                   "tasks.steering.max_speed=1"], "tasks.steering.max_speed=1"),
    ("steering", ["tasks.steering.max_speed=1.2"], None),
    ("multitask", ["tasks.navigation.min_distance=1", "tasks.steering.max_speed=1"], None),
    ("compose", ["tasks.navigation.min_distance=1", "tasks.compose.target_seconds=1"], None),
])
def test_an_evaluation_refuses_settings_of_a_task_the_policy_does_not_play(task, sets, refused):
    """Before: `control eval --task steering --policy RUN --set tasks.navigation.min_distance=1`
    evaluated the steering policy as without it and recorded the setting in the report, exit 0."""
    from motok.control.highlevel.evaluate import with_task_settings
    from motok.control.highlevel.policy import TaskTrainConfig
    from motok.errors import UserError

    cfg = TaskTrainConfig(task=task)
    if refused is not None:
        with pytest.raises(UserError, match=f"^--set {refused.replace('[', '.').replace(']', '.')}: a '{task}' "
                                            f"policy reads only tasks.{task}"):
            with_task_settings(cfg, sets)
        return
    new = with_task_settings(cfg, sets)
    for s in sets:
        key, value = s.split("=")
        _, name, field = key.split(".")
        assert getattr(getattr(new.tasks, name), field) == float(value), s


def test_decoding_with_more_codebooks_than_the_codes_hold_is_refused(small_dataset, tmp_path):
    """Before: `tokenize decode --codebooks 3` of codes encoded with `--codebooks 1` (and
    `motok.decode` of one column with codebooks=3) ended in a ValueError traceback."""
    import numpy as np

    import motok
    from motok.errors import MotokError
    from motok.quantize.base import QuantizerConfig
    from motok.tokenizer.model import ModelConfig
    from motok.tokenizer.train import TrainConfig, train

    rvq = tmp_path / "rvq"
    train(TrainConfig(model=ModelConfig(width=32, depth=1),
                      quantizer=QuantizerConfig(kind="rvq", num_codebooks=3, codebook_size=16, dim=16),
                      iterations=2, batch_size=4, window=32, log_every=1, save_every=2, threads=1),
          small_dataset, rvq, command="pytest")
    one = tmp_path / "one.h5"
    r = runner.invoke(app, ["tokenize", "encode", "-d", str(small_dataset), "-t", str(rvq), "-m", "1", "-o", str(one)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "out.h5"
    _one_line_error(runner.invoke(app, ["tokenize", "decode", "-d", str(one), "-t", str(rvq), "-m", "3",
                                        "-o", str(out)]), "--codebooks 3", str(one), "1 codebook(s)")
    assert not out.exists()
    tok = motok.load(rvq)
    with pytest.raises(MotokError, match=r"--codebooks 3: the array has codes of 1 codebook\(s\) only"):
        motok.decode(tok, np.zeros((5, 1), dtype=np.int64), codebooks=3)
    # as many as both have, by default, and fewer on request
    assert motok.decode(tok, np.zeros((5, 1), dtype=np.int64)).num_frames == 5 * tok.rate
    r = runner.invoke(app, ["tokenize", "decode", "-d", str(one), "-t", str(rvq), "-m", "1", "-o", str(out)])
    assert r.exit_code == 0 and out.exists(), r.output


def test_an_output_never_takes_the_place_of_a_runs_own_file(tree, evaluator, small_dataset, tmp_path):
    """Before: `eval t2m -o RUN/bundle.json` replaced a tokenizer run's bundle.json with the report
    (a JSON with a `kind`, so it passed for motok's own file) and the run no longer loaded; `sim
    build-humanoid -o RUN/humanoid.xml` replaced a control run's humanoid the same way."""
    import shutil

    import motok
    from motok.sim.mjcf import build_humanoid

    run = tmp_path / "tok"
    shutil.copytree(tree / "tok", run)
    build_humanoid(small_dataset, run / "humanoid.xml")  # as a control run holds one
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    t2m = ["eval", "t2m", "-d", str(small_dataset), "-e", str(evaluator), "--split", "train", "--set", "repeats=1",
           "--set", "batch=4"]
    for args, target in ((t2m + ["-o", str(run / "bundle.json")], run / "bundle.json"),
                         (["sim", "build-humanoid", "-d", str(small_dataset), "--total-mass", "50",
                           "-o", str(run / "humanoid.xml")], run / "humanoid.xml")):
        _one_line_error(runner.invoke(app, args), str(target), f"is a file of the run {run}")
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    motok.load(run)  # still a run
    # a new report beside the run's files is fine
    r = runner.invoke(app, t2m + ["-o", str(run / "t2m.json")])
    assert r.exit_code == 0 and (run / "t2m.json").exists(), r.output


@pytest.mark.parametrize("damage,says", [
    ("drop frames/features", "a motion-dataset artifact without frames/features"),
    ("cut frames/joints", "frames/joints has 100 rows, its clips end at row"),
    ("drop captions/text", "a motion-dataset artifact without captions/text"),
    ("cut clips/offset", "clips/offset does not index its 24 clips"),
])
def test_an_artifact_cut_short_or_missing_a_part_is_one_line(tree, small_dataset, tmp_path, damage, says):
    """A motion-dataset another tool wrote, or one cut short: before, a KeyError traceback from deep in
    a reader, or (rows cut) a clip silently read short."""
    import shutil

    import h5py

    bad = tmp_path / "bad.h5"
    shutil.copy(small_dataset, bad)
    how, member = damage.split()
    with h5py.File(bad, "a") as f:
        rows = f[member][()]
        del f[member]
        if how == "cut":
            f[member] = rows[:100] if member.startswith("frames") else rows[:-1]
    for args in (["tokenize", "encode", "-d", str(bad), "-t", str(tree / "tok"), "-o", str(tmp_path / "t.h5")],
                 ["render", "-d", str(bad), "--clip", "5", "--max-frames", "3", "-o", str(tmp_path / "r.gif")]):
        _one_line_error(runner.invoke(app, args), str(bad), says, "damaged, or not written by motok")
    assert not (tmp_path / "t.h5").exists() and not (tmp_path / "r.gif").exists()


def test_a_tokens_artifact_without_its_tokens_is_one_line(tree, tmp_path):
    import shutil

    import h5py

    bad = tmp_path / "tokens.h5"
    shutil.copy(tree / "tokens.h5", bad)
    with h5py.File(bad, "a") as f:
        del f["tokens"]
    r = runner.invoke(app, ["tokenize", "decode", "-d", str(bad), "-t", str(tree / "tok"), "-o", str(tmp_path / "m.h5")])
    _one_line_error(r, str(bad), "a tokens artifact without tokens")


def test_a_runs_evaluation_is_not_replaced_by_one_of_other_clips(controllers, small_dataset):
    """Before: `control eval --task imitation --prior RUN --clips ONE` (and `control expert eval`,
    `control eval --policy`) wrote RUN/eval.json over the run's evaluation of all its clips, without
    a word. Now the other evaluation is moved aside; the same evaluation again replaces it."""
    import json

    from motok.control.expert.evaluate import evaluate_run
    from motok.control.priors.evaluate import evaluate_prior

    prior, expert = controllers
    for run, evaluate in ((prior, evaluate_prior), (expert, evaluate_run)):
        evaluate(run, data=small_dataset, clips="dataset-2_walk_normal_00[12]")
        first = json.loads((run / "eval.json").read_text())
        evaluate(run, data=small_dataset, clips="dataset-2_walk_normal_00[12]")  # the same: replaced
        assert sorted(p.name for p in run.glob("eval*.json")) == ["eval.json"]
        evaluate(run, data=small_dataset, clips="dataset-2_walk_normal_003")  # other clips: the first kept
        kept = [p for p in run.glob("eval.replaced-*.json")]
        assert len(kept) == 1 and json.loads(kept[0].read_text())["clips"] == first["clips"]
        assert list(json.loads((run / "eval.json").read_text())["clips"]) == ["dataset-2_walk_normal_003"]


def test_codebooks_with_an_expert_is_refused(controllers, small_dataset, tmp_path):
    """Before: `control track --expert RUN --codebooks 2` (and `gpt sample --expert RUN -m 2`) tracked
    with the expert as without the option, and said nothing."""
    _, expert = controllers
    out = tmp_path / "sim.h5"
    r = runner.invoke(app, ["control", "track", "-d", str(small_dataset), "--clips", "dataset-2_walk_normal_001",
                            "--expert", str(expert), "-m", "2", "-o", str(out)])
    _one_line_error(r, "--codebooks 2", f"the expert {expert} has none")
    assert not out.exists()
