"""`motok plot` for people: every panel titled and its axes labelled with units for the metrics
each stage logs, train/validation/evaluation values of one quantity on one panel, the run's
name and kind in the title; TensorBoard event files as an optional extra."""

from __future__ import annotations

import json
import re
import sys

import pytest
from PIL import Image
from typer.testing import CliRunner

from motok.cli.main import app
from motok.render.metric_names import BY_KIND, COMMON, Metric, describe, split_key
from motok.render.plot import _figure, plot_run
from conftest import require_module

from tiny_runs import tree  # noqa: F401  (fixture)

runner = CliRunner()

# What the physics stages log (from real runs' metrics.jsonl); the tokenizer's and the GPT's
# keys are read from the real runs of the `tree` fixture.
CONTROL_KEYS = {
    "control-expert": ["episode_return", "episode_r_im", "episode_seconds", "success", "episodes", "r_im", "r_style",
                       "reward", "disc_loss", "disc_gp", "disc_ref", "disc_pol", "policy_loss", "value_loss",
                       "entropy", "approx_kl", "clip_frac", "explained_var", "lr", "iteration", "samples", "wall_s",
                       "samples_per_s", "rollout_s", "update_s", "hard_clips", "hard_share", "train_success",
                       "train_mpjpe_mm", "train_seconds", "difficulty_s", "eval_success", "eval_success_any_body",
                       "eval_seconds", "eval_mpjpe_mm", "eval_g_mpjpe_mm"],
    "control-prior": ["rollout_action_err", "code_usage_0", "code_perplexity_3", "code_usage", "code_perplexity",
                      "action_loss", "reg_loss", "commit_loss", "mm_loss", "kl_loss", "loss", "grad_norm", "w_mm",
                      "codes_reset", "active_codebooks"],
    "control-task": ["episode_r_task", "r_task", "eval_episodes", "eval_targets", "eval_reached_share",
                     "eval_time_to_reach_mean_s", "eval_time_to_reach_median_s", "eval_falls_per_episode",
                     "eval_diverged", "eval_mean_reward", "eval_goal_speed_mean", "eval_goal_speed_median",
                     "eval_start_distance_mean_m", "eval_closest_distance_mean_m", "eval_approach_share"],
    "evaluator": ["loss", "lr", "it_s"],
}


def _known(key: str, kind: str) -> bool:
    q = split_key(key)[0]
    return q in COMMON or q in BY_KIND.get(kind, {}) or re.sub(r"_\d+$", "", q) in COMMON


def _numeric_keys(run) -> list[str]:
    recs = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines() if ln.strip()]
    return sorted({k for r in recs for k, v in r.items() if isinstance(v, (int, float))})


def test_every_key_each_stage_logs_has_a_label_and_a_unit(tree):  # noqa: F811
    logged = {"tokenizer": _numeric_keys(tree / "tok"), "gpt": _numeric_keys(tree / "gpt"), **CONTROL_KEYS}
    assert {"it_s", "dead", "recon", "usage"} <= set(logged["tokenizer"]) and "val_loss" in logged["gpt"]
    for kind, keys in logged.items():
        unknown = [k for k in keys if not _known(k, kind)]
        assert not unknown, f"{kind}: no label for {unknown}"
        for k in keys:
            m = describe(split_key(k)[0], kind)
            assert m.label[0].isupper() and "_" not in m.label and m.unit and m.unit != k, (kind, k, m)
    assert describe("it_s").label == "Training speed" and describe("it_s").unit == "iterations/s"
    assert describe("dead").label == "Dead codes"
    # one key, a stage's own meaning
    assert describe("loss", "gpt").unit == "cross-entropy, nats/token" != describe("loss", "tokenizer").unit
    # a key no table knows is still readable, its unit guessed from the suffix
    assert describe("foot_slide_mm") == Metric("Foot slide", "mm")
    assert describe("code_usage_3").label == "Code usage, codebook 3"
    # an evaluation's reference clips (the mocap's own feet) share the simulated value's panel
    assert split_key("eval_ref_sole_slip_cm_s") == ("sole_slip_cm_s", "the clips themselves")
    assert split_key("eval_sole_slip_cm_s") == ("sole_slip_cm_s", "evaluation")


def test_train_and_validation_share_a_panel_and_the_run_is_named(tree, tmp_path):  # noqa: F811
    """The GPT's loss and val_loss are two curves on one labelled panel with a legend; the figure
    says the run's name and kind; the PNG is written."""
    out = tmp_path / "gpt.png"
    r = runner.invoke(app, ["-q", "plot", str(tree / "gpt"), "--keys", "loss,val_loss,acc,val_acc,it_s", "-o",
                            str(out), "--json"])
    assert r.exit_code == 0, r.output
    with Image.open(out) as im:
        assert im.format == "PNG" and im.width > 400
    recs = [json.loads(ln) for ln in (tree / "gpt" / "metrics.jsonl").read_text().splitlines()]
    fig = _figure(recs, ["loss", "val_loss", "acc", "val_acc", "it_s"], "iteration", kind="gpt", title="gpt (gpt)")
    loss, acc, speed = [ax for ax in fig.axes if ax.get_visible()]
    assert loss.get_title(loc="left") == "Next-token loss" and loss.get_ylabel() == "cross-entropy, nats/token"
    assert [ln.get_label() for ln in loss.get_lines()] == ["training", "validation"] and loss.get_legend()
    assert acc.get_title(loc="left") == "Next-token accuracy" and len(acc.get_lines()) == 2
    assert speed.get_title(loc="left") == "Training speed" and speed.get_ylabel() == "iterations/s"
    assert speed.get_legend() is None and loss.get_xlabel() == "Iteration (optimizer steps)"
    assert fig.get_suptitle() == "gpt (gpt)"
    # plot_run names the run from its folder and its kind from the bundle beside the log
    plot_run(tree / "tok", tmp_path / "tok.png")
    plot_run([tree / "tok", tree / "gpt"], tmp_path / "both.png", keys=["loss"])
    from motok.render.plot import run_title
    assert run_title([tree / "tok" / "metrics.jsonl"], ["tok"]) == "tok (tokenizer)"
    assert run_title([tree / "tok" / "metrics.jsonl", tree / "gpt" / "metrics.jsonl"], ["tok", "gpt"]) \
        == "tok, gpt (tokenizer, gpt)"


def test_several_runs_keep_their_colour_and_the_data_its_line_style():
    a = [{"samples": i, "success": i / 10, "eval_success": i / 12} for i in range(1, 6)]
    b = [{"samples": i, "success": i / 20, "eval_success": i / 25} for i in range(1, 6)]
    fig = _figure({"hybrid": a, "continuous": b}, ["success", "eval_success"], "samples")
    ax, = [ax for ax in fig.axes if ax.get_visible()]
    lines = ax.get_lines()
    assert [ln.get_label() for ln in lines] == ["hybrid · training", "hybrid · evaluation", "continuous · training",
                                                "continuous · evaluation"]
    assert lines[0].get_color() == lines[1].get_color() != lines[2].get_color()
    assert lines[0].get_linestyle() == lines[2].get_linestyle() != lines[1].get_linestyle()
    assert ax.get_xlabel() == "Environment samples (simulated steps)"


def test_tensorboard_event_files(tree, tmp_path, monkeypatch):  # noqa: F811
    """--tensorboard DIR writes DIR/RUN/<data>/ event files (training and validation apart, so that
    TensorBoard overlays them), replaces its own earlier output, and without the package says how
    to install it."""
    out = tmp_path / "tb"
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "torch.utils.tensorboard", None)  # as if the extra were not installed
        r = runner.invoke(app, ["plot", str(tree / "gpt"), "-o", str(tmp_path / "c.png"), "--tensorboard", str(out)])
        assert r.exit_code == 2 and "pip install 'motok[tensorboard]'" in r.output, r.output
    require_module("tensorboard", "tensorboard is not installed (make install EXTRAS=dev,tensorboard; .ci/run installs it)")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    for _ in range(2):  # the second conversion replaces the first
        r = runner.invoke(app, ["-q", "plot", str(tree / "gpt"), "-o", str(tmp_path / "c.png"), "--tensorboard",
                                str(out), "--json"])
        assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["tensorboard"] == [str(out / "gpt")]
    assert sorted(p.name for p in (out / "gpt").iterdir()) == ["training", "validation"]
    recs = [json.loads(ln) for ln in (tree / "gpt" / "metrics.jsonl").read_text().splitlines()]
    for role, key in (("training", "loss"), ("validation", "val_loss")):
        assert len(list((out / "gpt" / role).iterdir())) == 1
        acc = EventAccumulator(str(out / "gpt" / role))
        acc.Reload()
        got = [(e.step, round(e.value, 5)) for e in acc.Scalars("loss")]
        assert got == [(r["iteration"], round(r[key], 5)) for r in recs if key in r]
    (out / "gpt" / "notes.txt").write_text("mine")
    r = runner.invoke(app, ["plot", str(tree / "gpt"), "-o", str(tmp_path / "c.png"), "--tensorboard", str(out)])
    assert r.exit_code == 2 and "other files than event files" in r.output
