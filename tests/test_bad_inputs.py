"""A clear one-line error (exit 2) for every class of bad input, found before the work starts and
with nothing written; one parametrized test per class."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from motok.cli.main import app

from tiny_runs import tree  # noqa: F401  (a fixture)

pytestmark = pytest.mark.usefixtures("one_thread")
runner = CliRunner()


def _one_line_error(r, *says):
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.strip().splitlines() if not ln.startswith("note:")]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    for s in says:
        assert s in lines[0], (s, lines[0])


@pytest.fixture(scope="module")
def bvh(bandai_slice, tmp_path_factory):
    """One real take, and copies with no motion and with too little of it."""
    d = tmp_path_factory.mktemp("bvh")
    src = sorted(bandai_slice.glob("*.bvh"))[0].read_text()
    head, motion = src.split("MOTION", 1)
    first_row = motion.split("Frame Time:", 1)[1].splitlines()[1]
    (d / "take.bvh").write_text(src)
    (d / "zero.bvh").write_text(head + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n")
    (d / "one.bvh").write_text(head + f"MOTION\nFrames: 1\nFrame Time: 0.0333333\n{first_row}\n")
    (d / "junk.bvh").write_text("this is not a BVH file\n")
    return d


@pytest.fixture
def no_generation(monkeypatch):
    """Sampling must be refused before any code is generated."""
    import motok.gpt.sample as s

    def boom(*a, **k):
        raise AssertionError("generated before checking the arguments")
    monkeypatch.setattr(s, "generate", boom)


@pytest.mark.parametrize("args,says", [
    (["--top-k", "0"], "--top-k 0 must be >= 1"),
    (["--top-k", "-3"], "--top-k -3"),
    (["--top-k", "33"], "between 1 and 32, the codebook size"),
    (["--top-p", "0"], "--top-p 0.0 must be in (0, 1]"),
    (["--top-p", "1.5"], "--top-p 1.5"),
    (["--seconds", "0"], "--seconds 0.0 must be > 0"),
    (["--seconds", "-2"], "--seconds -2.0"),
    (["-n", "0"], "--num-samples 0 must be >= 1"),
    (["--temperature", "0"], "--temperature 0.0 must be > 0"),
])
def test_sampling_values_out_of_range(tree, tmp_path, no_generation, args, says):
    out = tmp_path / "s.h5"
    r = runner.invoke(app, ["gpt", "sample", "-g", str(tree / "gpt"), "--text", "a person walks", "-o", str(out),
                            *args])
    _one_line_error(r, says)
    assert not out.exists()


@pytest.mark.parametrize("texts,says", [
    (["--text", ""], "text 1 is empty"),
    (["--text", "a person walks", "--text", "   "], "text 2 is empty"),
    ([], "no text given"),
    (["--texts-file", "EMPTY"], "no text given"),
])
def test_empty_texts_are_refused(tree, tmp_path, no_generation, texts, says):
    (tmp_path / "empty.txt").write_text("\n  \n")
    texts = [str(tmp_path / "empty.txt") if t == "EMPTY" else t for t in texts]
    r = runner.invoke(app, ["gpt", "sample", "-g", str(tree / "gpt"), *texts, "-o", str(tmp_path / "s.h5")])
    _one_line_error(r, says)


def test_a_text_past_the_encoder_window_is_said_to_be_truncated(tree, tmp_path, monkeypatch):
    from motok.text.encoders import HashedBagOfWords, get_encoder, overlong
    monkeypatch.setattr(HashedBagOfWords, "window", 6, raising=False)  # bow reads all; pretend it stops at 6 words
    monkeypatch.setattr(HashedBagOfWords, "lengths", lambda self, t: [len(x.split()) for x in t], raising=False)
    long = "a person walks forward and then turns around slowly"
    r = runner.invoke(app, ["-q", "gpt", "sample", "-g", str(tree / "gpt"), "--text", "a person walks", "--text", long,
                            "-o", str(tmp_path / "s.h5"), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["truncated"] == [{"text": 2, "tokens": 9}]
    assert "warning: text 2 is 9 tokens long" in r.stderr and "only the first 6" in r.stderr  # even with -q
    minilm = get_encoder("minilm")  # the real window of the default encoder
    assert minilm.window == 256 and list(overlong(minilm, ["walk " * 300, "a person walks"]).values()) == [302]


OUTPUT_CASES = [(cmd, where) for cmd in ("render", "preprocess", "gpt --render", "plot", "export", "tokenize train")
                for where in ("a folder", "under a file", "unwritable", "wrong suffix")
                if not (cmd == "tokenize train" and where == "wrong suffix")]  # a run folder has no suffix to get wrong


@pytest.mark.parametrize("cmd,where", OUTPUT_CASES)
def test_outputs_that_cannot_be_written_fail_before_the_work(tree, small_dataset, bvh, tmp_path, monkeypatch,
                                                             no_generation, cmd, where):
    import motok.data.preprocess as pre
    monkeypatch.setattr(pre, "iter_sources", lambda *a, **k: (_ for _ in ()).throw(AssertionError("read inputs")))
    (tmp_path / "file").write_text("x")
    suffix = {"render": ".gif", "preprocess": ".h5", "gpt --render": ".gif", "plot": ".png", "export": ".bvh",
              "tokenize train": ""}[cmd]
    out = {"a folder": tmp_path, "under a file": tmp_path / "file" / f"x{suffix}",
           "unwritable": f"/proc/x{suffix}", "wrong suffix": tmp_path / "x.jpg"}[where]
    if cmd == "tokenize train" and where == "a folder":
        out = tmp_path / "file"  # a run folder that is a file
    args = {"render": ["render", "-d", str(small_dataset), "--clip", "0", "-o", str(out)],
            "preprocess": ["preprocess", "-d", str(bvh / "take.bvh"), "-o", str(out)],
            "gpt --render": ["gpt", "sample", "-g", str(tree / "gpt"), "--text", "a walk", "-o",
                             str(tmp_path / "s.h5"), "--render", str(out)],
            "plot": ["plot", str(tree / "gpt"), "-o", str(out)],
            "export": ["export", "bvh", "-d", str(small_dataset), "--clip", "0", "-o", str(out)],
            "tokenize train": ["tokenize", "train", "-d", str(small_dataset), "-o", str(out)]}[cmd]
    r = runner.invoke(app, args)
    says = {"a folder": "is a f", "under a file": "is a file, not a folder", "unwritable": "cannot write in",
            "wrong suffix": "unknown suffix '.jpg'"}[where]
    _one_line_error(r, says)
    assert not (tmp_path / "s.h5").exists()


@pytest.mark.parametrize("name,says", [
    ("zero.bvh", "'Frames: 0': the file has a skeleton but no motion"),
    ("one.bvh", "clip has 1 frame(s) at 20 fps"),
    ("junk.bvh", "line 1: expected 'HIERARCHY'"),
])
def test_mocap_without_usable_motion(bvh, tmp_path, name, says):
    r = runner.invoke(app, ["preprocess", "-d", str(bvh / name), "-o", str(tmp_path / "x.h5")])
    _one_line_error(r, name, says)
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("args,says", [
    (["preprocess", "-d", "TAKE", "--fps", "0"], "--fps 0.0 must be > 0"),
    (["preprocess", "-d", "TAKE", "--fps", "-5"], "--fps -5.0 must be > 0"),
    (["preprocess", "-d", "TAKE", "-j", "0"], "jobs 0 must be >= 1"),
    (["preprocess", "-d", "TAKE", "--fps", "0", "--skip-bad"], "fps 0.0"),  # not "no clip could be loaded"
    (["plot", "GPT", "--smooth", "1.5"], "--smooth 1.5 must be in [0, 1)"),
    (["sim", "pd-track", "-d", "DATA", "--seconds", "0"], "--seconds 0.0 must be > 0"),
])
def test_settings_out_of_range(tree, small_dataset, bvh, tmp_path, args, says):
    subst = {"TAKE": str(bvh / "take.bvh"), "GPT": str(tree / "gpt"), "DATA": str(small_dataset)}
    r = runner.invoke(app, [subst.get(a, a) for a in args] + (["-o", str(tmp_path / "x.h5")]
                                                              if args[0] == "preprocess" else []))
    _one_line_error(r, says)


@pytest.mark.parametrize("what,says", [
    ("an artifact", "an HDF5 artifact, not a metrics log"),
    ("a folder", "not a run folder (it has no metrics.jsonl)"),
    ("a text file", "not a metrics log"),
    ("--keys", "no metric 'lss' in the log; it has: iteration, loss"),
    ("--x", "--x 'sampels' is not a numeric field"),
])
def test_plot_of_something_that_is_not_a_run(tree, small_dataset, tmp_path, what, says):
    (tmp_path / "notes.txt").write_text("hello\n")
    args = {"an artifact": [str(small_dataset)], "a folder": [str(tmp_path)],
            "a text file": [str(tmp_path / "notes.txt")],
            "--keys": [str(tree / "gpt"), "--keys", "loss,lss"], "--x": [str(tree / "gpt"), "--x", "sampels"]}[what]
    r = runner.invoke(app, ["plot", *args, "-o", str(tmp_path / "c.png")])
    _one_line_error(r, says)
    assert not (tmp_path / "c.png").exists()
