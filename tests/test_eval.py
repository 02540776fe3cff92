"""Evaluation: the metric formulas, physical plausibility, the evaluator and the t2m report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.eval import metrics as M
from motok.eval.physical import physical_metrics

TINY_EVAL = ["text_encoder=bow", "width=32", "embed_dim=32", "layers=1", "heads=2", "batch_size=32",
             "iterations=60", "log_every=10", "max_frames=64", "lr=0.002", "warmup=5", "threads=1"]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="session")
def tiny_evaluator(tmp_path_factory, labelled_dataset):
    from motok.eval.evaluator import resolve_config, train_evaluator
    run = tmp_path_factory.mktemp("eval-run") / "ev"
    summary = train_evaluator(resolve_config(None, TINY_EVAL), labelled_dataset, run, command="pytest")
    return run, summary


# --------------------------------------------------------------------------- FID

def test_fid_of_two_gaussians_equals_the_closed_form():
    rng = np.random.default_rng(0)
    mu1, mu2 = np.array([0.0, 1.0, -2.0]), np.array([1.0, 3.0, 0.5])
    s1, s2 = np.array([1.0, 4.0, 0.25]), np.array([9.0, 1.0, 1.0])  # stds, diagonal covariances
    closed = float(((mu1 - mu2) ** 2).sum() + ((s1 - s2) ** 2).sum())
    assert M.frechet_distance(mu1, np.diag(s1 ** 2), mu2, np.diag(s2 ** 2)) == pytest.approx(closed, rel=1e-9)
    # A full covariance and a scaled copy commute: Tr(S + cS - 2 sqrt(c) S) = tr(S) (1 - sqrt(c))^2.
    a = rng.normal(size=(4, 4))
    S, c = a @ a.T + np.eye(4), 2.5
    expect = 9.0 + np.trace(S) * (1 - np.sqrt(c)) ** 2
    assert M.frechet_distance(np.zeros(4), S, np.full(4, 1.5), c * S) == pytest.approx(expect, rel=1e-8)
    assert M.fid_gaussians_closed_form(np.zeros(4), S, np.full(4, 1.5), c * S) == pytest.approx(expect, rel=1e-8)
    # From samples: the Gaussian fits converge to the same number.
    x = mu1 + s1 * rng.normal(size=(200_000, 3))
    y = mu2 + s2 * rng.normal(size=(200_000, 3))
    assert M.fid(x, y) == pytest.approx(closed, rel=0.02)


def test_fid_of_a_set_with_itself_is_zero():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(500, 32))
    assert M.fid(x, x) == pytest.approx(0.0, abs=1e-6)
    # Fewer samples than dimensions: a singular covariance takes the eps path, still 0, still real.
    few = rng.normal(size=(10, 32))
    val = M.fid(few, few)
    assert isinstance(val, float) and val == pytest.approx(0.0, abs=1e-3)
    assert M.fid(x, x + 1.0) == pytest.approx(32.0, rel=1e-6)  # a shift only moves the means


# --------------------------------------------------------------------------- R-precision, MM-Dist

def test_r_precision_is_one_for_a_perfect_embedding():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(320, 16))
    rp, mmd = M.r_precision(x, x.copy(), rng)
    assert rp.tolist() == [1.0, 1.0, 1.0] and mmd == pytest.approx(0.0, abs=1e-9)


def test_r_precision_is_chance_for_random_embeddings():
    rng = np.random.default_rng(3)
    t, m = rng.normal(size=(32 * 400, 16)), rng.normal(size=(32 * 400, 16))
    rp, _ = M.r_precision(t, m, rng)
    assert rp == pytest.approx([1 / 32, 2 / 32, 3 / 32], abs=0.01)


def test_r_precision_batches_drop_the_remainder_and_ties_count_against():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(70, 8))
    hits = M.r_precision_hits(x[:32], x[:32])
    assert hits.tolist() == [32, 32, 32]
    rp, mmd = M.r_precision(x, x + 0.0, rng)
    assert rp.tolist() == [1.0, 1.0, 1.0]  # 64 of 70 pairs kept: ratios still exact
    collapsed = np.zeros((32, 8))
    assert M.r_precision_hits(collapsed, collapsed).tolist() == [0, 0, 0]
    assert M.mm_dist(np.zeros((2, 2)), np.array([[3.0, 4.0], [0.0, 1.0]])) == pytest.approx(3.0)


# --------------------------------------------------------------------------- Diversity, MModality, CI

def test_diversity_on_hand_made_vectors():
    x = np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 8.0], [0.0, 1.0]])
    rng, twin = np.random.default_rng(5), np.random.default_rng(5)
    a, b = twin.choice(4, 3, replace=False), twin.choice(4, 3, replace=False)
    assert M.diversity(x, rng, times=300) == pytest.approx(np.linalg.norm(x[a] - x[b], axis=1).mean())
    assert M.diversity(np.ones((50, 3)), rng, times=30) == 0.0
    # Two far clusters drawn independently: half the pairs straddle them (distance 10).
    two = np.repeat([[0.0], [10.0]], 5000, axis=0)
    assert M.diversity(two, rng, times=4000) == pytest.approx(5.0, rel=0.05)


def test_multimodality_on_hand_made_vectors():
    groups = [np.array([[0.0, 0.0], [3.0, 4.0]]), np.array([[1.0, 1.0]] * 3)]
    rng = np.random.default_rng(6)
    assert M.multimodality(groups, rng, pairs=10) == pytest.approx(2.5)  # mean of 5 and 0
    line = np.arange(5, dtype=float)[:, None]  # all 10 distinct pairs of 0..4: mean |i - j| = 2
    assert M.multimodality([line], rng, pairs=10) == pytest.approx(2.0)
    with pytest.raises(ValueError):
        M.multimodality([np.zeros((1, 2))], rng)
    # A bootstrap over captions: each draw averages a resampled set of groups, values 0, 2.5 or 5,
    # about 2.5 on average; without it the pairs are all there is and every draw gives 2.5.
    draws = [M.multimodality(groups, rng, pairs=10, resample_captions=True) for _ in range(400)]
    assert set(np.round(draws, 9)) == {0.0, 2.5, 5.0} and np.mean(draws) == pytest.approx(2.5, abs=0.2)
    assert np.std(draws) == pytest.approx(np.sqrt(2 * 2.5 ** 2 / 4), abs=0.3)  # two groups, 5 and 0


def test_mean_and_95_ci():
    mean, ci = M.mean_ci([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5 and ci == pytest.approx(1.96 * np.std([1, 2, 3, 4]) / 2)


def test_mpjpe_and_acceleration_error():
    rng = np.random.default_rng(7)
    gt = rng.normal(size=(10, 5, 3))
    assert M.mpjpe(gt, gt).max() == 0.0
    shifted = gt + np.array([0.0, 0.0, 0.01])  # a global offset: 0 root-relative, 10 mm global
    assert M.mpjpe(shifted, gt).max() == pytest.approx(0.0, abs=1e-9)
    assert M.mpjpe(shifted, gt, root_relative=False) == pytest.approx(np.full(10, 10.0))
    drift = gt + np.arange(10)[:, None, None] * np.array([0.002, 0.0, 0.0])  # constant velocity: no accel
    assert M.acceleration_error(drift, gt).max() == pytest.approx(0.0, abs=1e-9)


# --------------------------------------------------------------------------- physical

FEET = ((15, 16), (19, 20))


def _standing(T: int = 40) -> np.ndarray:
    """21 joints: feet planted (ankles 7 cm up, toes on the floor), the body bobbing above them."""
    j = np.zeros((T, 21, 3))
    j[:, :, 1] = 1.0 + 0.05 * np.sin(np.linspace(0, 6, T))[:, None]
    for ankle, toe, x in ((15, 16, -0.1), (19, 20, 0.1)):
        j[:, ankle] = [x, 0.07, 0.0]
        j[:, toe] = [x, 0.0, 0.12]
    return j


def test_foot_skating_is_zero_with_planted_feet():
    p = physical_metrics(_standing(), 20.0, FEET)
    assert p["skate_cm_s"] == 0.0 and p["skate_ratio"] == 0.0 and p["contact_fraction"] == 1.0
    assert p["penetration_cm"] == 0.0 and p["floating_cm"] == 0.0


def test_foot_skating_equals_the_slide_speed():
    j = _standing()
    t = np.arange(len(j)) / 20.0
    j[..., 0] += 0.8 * t[:, None]  # the whole figure slides at 0.8 m/s along x
    j[..., 2] += 0.6 * t[:, None]  # and 0.6 m/s along z: 1 m/s horizontally
    p = physical_metrics(j, 20.0, FEET)
    assert p["skate_cm_s"] == pytest.approx(100.0) and p["skate_ratio"] == 1.0
    j2 = _standing()
    j2[..., 1] += 0.3 * np.arange(len(j2))[:, None] / 20.0  # vertical motion is not skating
    assert physical_metrics(j2, 20.0, FEET)["skate_cm_s"] == 0.0


def test_penetration_floating_and_jitter():
    sunk = _standing()
    sunk[..., 1] -= 0.02
    assert physical_metrics(sunk, 20.0, FEET)["penetration_cm"] == pytest.approx(2.0)
    high = _standing()
    high[..., 1] += 0.10
    p = physical_metrics(high, 20.0, FEET)
    assert p["floating_cm"] == pytest.approx(5.0) and p["penetration_cm"] == 0.0
    assert p["floating_placed_cm"] == 0.0  # placed on the floor as a whole, it stands
    # a generator's heights: sunk 4 cm for half the clip, floating 8 cm for the other half; placed
    # as a whole on its lowest moment it floats 12 cm (7 above the tolerance) half the time
    bob = _standing()
    bob[..., 1] += np.where(np.arange(len(bob)) < len(bob) // 2, -0.04, 0.08)[:, None]
    p = physical_metrics(bob, 20.0, FEET)
    assert p["penetration_cm"] == pytest.approx(2.0) and p["floating_cm"] == pytest.approx(1.5)
    assert p["floating_placed_cm"] == pytest.approx(3.5)
    j = _standing()
    j[:, 16, 1] = np.where(np.arange(40) % 10 < 5, 0.0, 0.10)  # a toe that lifts 10 cm: contact half the time
    j[:, 16, 2] += np.arange(40) * 0.01  # and drifts 20 cm/s along z all the while
    p = physical_metrics(j, 20.0, FEET)
    assert p["skate_cm_s"] == pytest.approx(20.0 * 16 / (39 + 16))  # only its 16 contact steps slide
    smooth = _standing()
    smooth[:, [k for k in range(21) if k not in (15, 16, 19, 20)], 1] = 1.0  # no bobbing
    smooth[..., 0] += 0.5 * (np.arange(40) / 20.0)[:, None] ** 2  # constant acceleration: zero jerk
    assert physical_metrics(smooth, 20.0, FEET)["jitter_m_s3"] == pytest.approx(0.0, abs=1e-6)
    noisy = smooth + np.random.default_rng(8).normal(scale=0.01, size=smooth.shape)
    assert physical_metrics(noisy, 20.0, FEET)["jitter_m_s3"] > 100.0


def test_physical_on_real_motion(labelled_dataset):
    from motok.eval.physical import artifact_physical
    p = artifact_physical(labelled_dataset)
    assert p["clips"] == 210 and 0.3 < p["contact_fraction"] < 0.95
    assert p["skate_cm_s"] < 5.0 and p["penetration_cm"] < 0.5 and np.isfinite(p["jitter_m_s3"])
    walk = artifact_physical(labelled_dataset, clips=["dataset-2_walk_normal_001", "dataset-2_run_normal_001"])
    assert walk["clips"] == 2 and walk["skate_cm_s"] < 10.0 and walk["skate_ratio"] < 0.05


# --------------------------------------------------------------------------- evaluator

def test_negatives_sharing_caption_or_label_are_voided():
    from motok.eval.evaluator import negatives_mask
    caps = ["a walks", "a walks", "b runs", "c waves"]
    labels = ['{"c": 1}', '{"c": 2}', '{"c": 3}', '{"c": 3}']
    m = negatives_mask(caps, labels, ["caption", "label"])
    assert m.tolist() == [[False, True, False, False], [True, False, False, False],
                          [False, False, False, True], [False, False, True, False]]
    assert not negatives_mask(caps, ["", "", "", ""], ["label"]).any()  # no labels: nothing voided


def test_evaluator_loss_falls_and_retrieval_beats_chance(tiny_evaluator):
    run, summary = tiny_evaluator
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 6 and rows[-1]["loss"] < 0.8 * rows[0]["loss"]
    r = summary["retrieval"]
    assert r["clips"] == 38 and r["t2m_label_R@1"] > r["chance"]["t2m_label_R@1"]
    assert r["t2m_median_rank"] < r["chance"]["t2m_median_rank"]
    meta = json.loads((run / "bundle.json").read_text())
    assert meta["kind"] == "evaluator" and meta["model_sha256"] == summary["model_sha256"]


def test_embeddings_do_not_depend_on_batch_padding(tiny_evaluator, labelled_dataset):
    from motok.data.dataset import MotionFile
    from motok.eval.evaluator import load_evaluator
    ev = load_evaluator(tiny_evaluator[0])
    with MotionFile(labelled_dataset) as mf:
        clips = [mf.frames("features", i) for i in range(6)]
    together = ev.motions(clips)
    alone = np.concatenate([ev.motions([c]) for c in clips])
    np.testing.assert_allclose(together, alone, atol=1e-5)
    assert np.linalg.norm(together, axis=1) == pytest.approx(np.ones(6), abs=1e-5)
    assert ev.texts(["A person walks."]).shape == (1, 32)


# --------------------------------------------------------------------------- the t2m report

def _motion_copy(src: Path, out: Path, noise: float, samples: int = 1, split: str | None = "test") -> Path:
    """A ``motion`` artifact of the ``split`` clips (all with None) with noisy features, ``samples``
    copies per clip."""
    from motok.artifacts import Provenance
    from motok.data.dataset import MotionFile, write_motion
    rng = np.random.default_rng(9)
    with MotionFile(src) as mf:
        clips = []
        for i in (mf.split_indices(split) if split else range(len(mf))):
            for s in range(samples):
                c = mf.clip(i)
                c.features = c.features + noise * rng.normal(size=c.features.shape).astype(np.float32)
                c.joints = c.joints + 0.02 * noise * rng.normal(size=c.joints.shape).astype(np.float32)
                c.labels = {"sample": s, "text": c.captions[0][0]} if samples > 1 else {}
                c.name = f"{c.name}-{s}" if samples > 1 else c.name
                clips.append(c)
        write_motion(out, "motion", Provenance("pytest", {}), clips, mf.skeleton, mf.offsets, mf.fps, False)
    return out


def test_t2m_rows_json_and_markdown(tiny_evaluator, labelled_dataset, tmp_path):
    from motok.eval.report import T2MConfig, markdown, t2m
    gen = _motion_copy(labelled_dataset, tmp_path / "gen.h5", noise=0.5, samples=2)
    rep = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=3), motions=[gen])
    real, g = rep["rows"]
    assert real["name"] == "real motion" and real["motions"] == 38 and g["motions"] == 38
    assert len(real["repeats"]["FID"]) == 3 and "MModality" not in real["metrics"]
    assert 0 <= real["metrics"]["R@1"]["mean"] <= real["metrics"]["R@3"]["mean"] <= 1
    assert real["metrics"]["FID"]["mean"] < g["metrics"]["FID"]["mean"]
    assert g["metrics"]["MModality"]["mean"] > 0 and g["mmodality_counts"]["samples_per_caption"] == 2
    assert g["physical"]["jitter_m_s3"] > real["physical"]["jitter_m_s3"]
    md = markdown(rep)
    assert md.count("\n| ") == 2 and "real motion" in md and "±" in md
    json.dumps(rep)


def test_motions_rows_keep_the_split_and_samples_without_one(tiny_evaluator, labelled_dataset, tmp_path):
    """A tracked dataset keeps its clips' splits: a --motions row scores only the report's split
    (and says how many it left out); GPT samples carry no split and all stay."""
    from motok.artifacts import Provenance
    from motok.data.dataset import MotionFile, write_motion
    from motok.eval.evaluator import EvaluatorError
    from motok.eval.report import T2MConfig, markdown, t2m
    from motok.eval.sets import motion_set
    with MotionFile(labelled_dataset) as mf:
        captioned = [i for i in range(len(mf)) if mf.captions(i)]
        n_test = sum(mf.splits[i] == "test" for i in captioned)
        train = [mf.clip(i) for i in captioned if mf.splits[i] == "train"][:6]
        loose = [mf.clip(i) for i in captioned if mf.splits[i] == "train"][:6]
        for k, c in enumerate(loose):
            c.split = ("", "none")[k % 2]  # "none": what motok writes for samples; "": older files
        write_motion(tmp_path / "train.h5", "motion", Provenance("pytest", {}), train, mf.skeleton, mf.offsets,
                     mf.fps, False)
        write_motion(tmp_path / "loose.h5", "motion", Provenance("pytest", {}), loose, mf.skeleton, mf.offsets,
                     mf.fps, False)
    rep = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=2, physical=False),
              motions=[labelled_dataset], real=False)
    (row,) = rep["rows"]
    assert row["motions"] == n_test and row["other_split_left_out"] == len(captioned) - n_test > 0
    assert f"{len(captioned) - n_test} clip(s) of other splits than test left out" in markdown(rep)
    assert len(motion_set(tmp_path / "loose.h5", split="test").clips) == 6
    assert "other_split_left_out" not in motion_set(tmp_path / "loose.h5", split="test").extra
    assert len(motion_set(tmp_path / "train.h5").clips) == 6  # no split asked: everything
    with pytest.raises(EvaluatorError, match=r"train\.h5: none of its 6 captioned clips is in split 'test'"):
        motion_set(tmp_path / "train.h5", split="test")


def test_common_clips_scores_rows_on_the_clips_they_share(tiny_evaluator, labelled_dataset, tmp_path):
    """--common-clips: a tracked copy that lost some clips and the real split are scored on the
    clips both hold, exactly as those clips alone; a row sharing no name keeps all of its clips."""
    from motok.artifacts import Provenance
    from motok.data.dataset import MotionFile, write_motion
    from motok.eval.report import T2MConfig, markdown, t2m
    with MotionFile(labelled_dataset) as mf:
        test = [mf.clip(i) for i in mf.split_indices("test") if mf.captions(i)]
        kept = [c for k, c in enumerate(test) if k % 7 != 3]  # "tracking" wrote no clip for the others
        write_motion(tmp_path / "kept.h5", "motion", Provenance("pytest", {}), kept, mf.skeleton, mf.offsets,
                     mf.fps, False)
    tracked = _motion_copy(tmp_path / "kept.h5", tmp_path / "tracked.h5", noise=0.2, split=None)
    gen = _motion_copy(labelled_dataset, tmp_path / "gen.h5", noise=0.5, samples=2)
    cfg = T2MConfig(repeats=2, physical=False, common_clips=True)
    real, trk, g = t2m(tiny_evaluator[0], labelled_dataset, cfg, motions=[tracked, gen])["rows"]
    n_left = len(test) - len(kept)
    assert n_left > 0 and real["motions"] == trk["motions"] == len(kept) and g["motions"] == len(test)
    assert real["common_clips_left_out"] == n_left and trk["common_clips_left_out"] == 0
    assert "common_clips_left_out" not in g
    # the restricted real row is those clips scored alone, in the same place
    (alone,) = t2m(tiny_evaluator[0], labelled_dataset, cfg, motions=[tmp_path / "kept.h5"], real=False)["rows"]
    assert alone["repeats"] == real["repeats"]
    assert f"real motion: {n_left} clip(s) left out" in markdown(t2m(tiny_evaluator[0], labelled_dataset, cfg,
                                                                     motions=[tracked]))
    # without the flag every row keeps its clips
    real, trk = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=1, physical=False),
                    motions=[tracked])["rows"]
    assert real["motions"] == len(test) and trk["motions"] == len(kept)


def test_tracked_to_end_keeps_the_clips_played_through(tiny_evaluator, labelled_dataset, tmp_path):
    """--tracked-to-end: a tracked row keeps the clips its `tracked_to_end` label says were played to
    the end, exactly as if only those had been written; with --common-clips the real row follows;
    clips without the label stay, and a flag that finds no tracked file is refused."""
    from motok.artifacts import Provenance
    from motok.data.dataset import TRACKED_TO_END, MotionFile, write_motion
    from motok.eval.evaluator import EvaluatorError
    from motok.eval.report import T2MConfig, markdown, t2m
    with MotionFile(labelled_dataset) as mf:
        test = [mf.clip(i) for i in mf.split_indices("test") if mf.captions(i)]
        for k, c in enumerate(test):
            c.labels = {**c.labels, TRACKED_TO_END: k % 5 != 2}
        ended = [c for c in test if c.labels[TRACKED_TO_END]]
        for path, clips in (("tracked.h5", test), ("ended.h5", ended)):
            write_motion(tmp_path / path, "motion", Provenance("pytest", {}), clips, mf.skeleton, mf.offsets, mf.fps,
                         False)
    n_failed = len(test) - len(ended)
    cfg = T2MConfig(repeats=2, physical=False, common_clips=True, tracked_to_end=True)
    rep = t2m(tiny_evaluator[0], labelled_dataset, cfg, motions=[tmp_path / "tracked.h5"])
    real, trk = rep["rows"]
    assert n_failed > 0 and trk["motions"] == real["motions"] == len(ended)
    assert trk["not_tracked_to_end_left_out"] == n_failed and trk["tracked_clips"] == len(test)
    assert real["common_clips_left_out"] == n_failed
    _, alone = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=2, physical=False, common_clips=True),
                   motions=[tmp_path / "ended.h5"])["rows"]  # in the same place: a row's draws follow its position
    assert alone["metrics"] == trk["metrics"] and alone["repeats"] == trk["repeats"]
    assert f"tracked: {n_failed} clip(s) left out that the tracking played only to its failure" in markdown(rep)
    # without the flag the failed clips count
    (everything,) = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=1, physical=False),
                        motions=[tmp_path / "tracked.h5"], real=False)["rows"]
    assert everything["motions"] == len(test) and "not_tracked_to_end_left_out" not in everything
    plain = _motion_copy(labelled_dataset, tmp_path / "plain.h5", noise=0.1)
    with pytest.raises(EvaluatorError, match="tracked-to-end: no --motions file"):
        t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=1, physical=False, tracked_to_end=True),
            motions=[plain])


def _wrongly_captioned(src: Path, out: Path) -> Path:
    """The test clips unchanged, each carrying the captions of a clip of another label."""
    from motok.artifacts import Provenance
    from motok.data.dataset import MotionFile, write_motion
    with MotionFile(src) as mf:
        clips = [mf.clip(i) for i in mf.split_indices("test")]
        labels = [json.dumps(c.labels, sort_keys=True) for c in clips]
        rng = np.random.default_rng(10)
        while True:  # a permutation that gives no clip a caption of its own label
            perm = rng.permutation(len(clips))
            if all(labels[i] != labels[j] for i, j in enumerate(perm)):
                break
        caps = [clips[j].captions for j in perm]
        for c, cap in zip(clips, caps):
            c.captions, c.labels = cap, {}
        write_motion(out, "motion", Provenance("pytest", {}), clips, mf.skeleton, mf.offsets, mf.fps, False)
    return out


def test_r_precision_is_chance_for_wrong_captions_and_well_above_it_for_the_real_ones(
        tiny_evaluator, labelled_dataset, tmp_path):
    """Through the whole protocol: the real test motion with its own captions against the same
    motion captioned as other labels. Batches of 32: chance is k/32 for R@k."""
    from motok.eval.report import T2MConfig, t2m
    wrong = _wrongly_captioned(labelled_dataset, tmp_path / "wrong.h5")
    rep = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=20, physical=False), motions=[wrong])
    real, bad = (r["metrics"] for r in rep["rows"])
    # 20 repeats x 32 pairs: chance R@1 = 1/32 +- 0.007 (one std of 640 draws)
    assert bad["R@1"]["mean"] < 1 / 32 + 0.025 and bad["R@3"]["mean"] < 3 / 32 + 0.04
    # the real row at 5x chance or more (measured: R@1 0.24, R@3 0.56 after 60 iterations)
    assert real["R@1"]["mean"] > 5 / 32 and real["R@3"]["mean"] > 0.4
    assert bad["MM-Dist"]["mean"] > real["MM-Dist"]["mean"] + 0.1
    assert max(bad["FID"]["mean"], real["FID"]["mean"]) < 1e-3  # the motion itself is real in both rows


def test_caption_overlap_and_the_unseen_rows(tiny_evaluator, labelled_dataset):
    from motok.data.dataset import MotionFile
    from motok.eval.captions import caption_overlap
    from motok.eval.report import T2MConfig, markdown, t2m
    with MotionFile(labelled_dataset) as mf:
        owner, split = mf.h5["captions/clip"][()], mf.splits
        texts = [mf.captions(i) for i in range(len(mf))]
    train = {t for i in range(len(split)) if split[i] == "train" for t, _, _ in texts[i]}
    test = [[t for t, _, _ in texts[i]] for i in range(len(split)) if split[i] == "test" and texts[i]]
    flat = [t for c in test for t in c]
    ov = caption_overlap(labelled_dataset)
    assert ov["captions"] == len(flat) == len(owner[[split[int(c)] == "test" for c in owner]])
    assert ov["share_in_train"] == pytest.approx(np.mean([t in train for t in flat]))
    unseen = [c for c in test if any(t not in train for t in c)]
    assert ov["clips_with_unseen_caption"] == len(unseen) >= 2
    assert 0 < ov["unseen_captions"] == sum(t not in train for t in flat) < len(flat)
    from motok.eval.captions import training_captions, unseen_only
    from motok.eval.sets import real_set
    kept = unseen_only(real_set(labelled_dataset, "test")[0], training_captions(labelled_dataset))
    assert sum(map(len, kept.captions)) == ov["unseen_captions"]
    assert not {t for c in kept.captions for t in c} & train
    rep = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=2, physical=False, captions="unseen"))
    (row,) = rep["rows"]
    assert rep["clips"] == row["motions"] == len(unseen) and rep["captions"] == "unseen"
    assert rep["caption_overlap"]["share_in_train"] == pytest.approx(ov["share_in_train"])
    assert "only captions that do not occur in training" in markdown(rep)
    full = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=2, physical=False))
    assert full["clips"] == len(test) and full["rows"][0]["repeats"]["MM-Dist"] != row["repeats"]["MM-Dist"]


def test_unseen_only_and_the_label_reader_ceiling_by_hand():
    from motok.eval.captions import label_ceiling, unseen_only
    from motok.eval.sets import MotionSet
    clips = [np.full((8, 3), k, np.float32) for k in range(4)]
    ms = MotionSet("x", clips, [["a", "b"], ["a"], ["c"], ["b", "d"]], sample=np.array([0, 1, 0, 1]),
                   labels=["p", "q", "r", "s"], mm_groups=[[0, 1], [2, 3]], mm_texts=["a", "d"])
    u = unseen_only(ms, {"a", "b"})
    assert u.captions == [["c"], ["d"]] and [int(c[0, 0]) for c in u.clips] == [2, 3]
    assert u.sample.tolist() == [0, 1] and u.labels == ["r", "s"] and u.mm_groups == [[2, 3]] and u.mm_texts == ["d"]
    # one batch of 4: labels a, a, b, b -> two clips per label, a perfect reader hits R@1 half the time
    assert label_ceiling(["a", "a", "b", "b"], batch=4, top_k=2, shuffles=3) == \
        {"batch": 4, "shuffles": 3, "R@1": 0.5, "R@2": 1.0}
    assert label_ceiling(list("abcd"), batch=4, top_k=1, shuffles=1)["R@1"] == 1.0
    # batches of 2 from a, a, a, b: every split is {a, b} (both sure) + {a, a} (a coin each): 3/4
    assert label_ceiling(list("aaab"), batch=2, top_k=1, shuffles=50)["R@1"] == pytest.approx(0.75)
    # 5 clips in batches of 2: one is left out (drop_last) and the rest still average exactly
    assert label_ceiling(list("abcde"), batch=2, top_k=1, shuffles=5)["R@1"] == 1.0
    assert label_ceiling(["a", ""], batch=2) is None


@pytest.fixture(scope="module")
def tiny_tokenizer(labelled_dataset, tmp_path_factory) -> Path:
    from motok.quantize.base import QuantizerConfig
    from motok.tokenizer.model import ModelConfig
    from motok.tokenizer.train import TrainConfig, train
    run = tmp_path_factory.mktemp("eval-tok") / "tok"
    cfg = TrainConfig(model=ModelConfig(width=32, depth=1), quantizer=QuantizerConfig(codebook_size=32, dim=16),
                      iterations=10, batch_size=8, window=32, log_every=5, save_every=10, threads=1)
    train(cfg, labelled_dataset, run, command="pytest tiny tokenizer")
    return run


def test_recon_row_with_a_tiny_tokenizer(tiny_evaluator, labelled_dataset, tiny_tokenizer):
    from motok.eval.report import T2MConfig, recon, t2m
    rep = t2m(tiny_evaluator[0], labelled_dataset, T2MConfig(repeats=2, physical=False), tokenizer=tiny_tokenizer,
              real=False)
    (row,) = rep["rows"]
    assert row["name"].startswith("reconstruction") and row["recon"]["mpjpe_mm"] > 0
    same = recon(labelled_dataset, "test", tokenizer=tiny_tokenizer)
    assert same["mpjpe_mm"] == pytest.approx(row["recon"]["mpjpe_mm"]) and same["accel_error_mm"] > 0
    # Against an independent computation: the model's forward pass (not encode/decode), the
    # error definitions written out, every frame of every test clip pooled.
    import torch

    from motok.data.dataset import MotionFile
    from motok.features.humanml3d import recover_from_ric
    from motok.tokenizer.model import load_tokenizer
    model, _ = load_tokenizer(tiny_tokenizer)
    rel, glob, acc = [], [], []
    with MotionFile(labelled_dataset) as mf, torch.no_grad():
        for i in mf.split_indices("test"):
            gt = mf.frames("features", i).astype(np.float64)
            gt = gt[: len(gt) // 4 * 4]
            pred = model.denormalize(model(model.normalize(torch.from_numpy(gt).float()[None])).recon)[0].double()
            p, g = recover_from_ric(pred.numpy(), 21), recover_from_ric(gt, 21)
            rel += list(np.linalg.norm((p - p[:, :1]) - (g - g[:, :1]), axis=-1).mean(1))
            glob += list(np.linalg.norm(p - g, axis=-1).mean(1))
            acc += list(np.linalg.norm(np.diff(p, 2, axis=0) - np.diff(g, 2, axis=0), axis=-1).mean(1))
    assert same["mpjpe_mm"] == pytest.approx(1000 * np.mean(rel), rel=1e-4)
    assert same["mpjpe_global_mm"] == pytest.approx(1000 * np.mean(glob), rel=1e-4)
    assert same["accel_error_mm"] == pytest.approx(1000 * np.mean(acc), rel=1e-4)
    perfect = recon(labelled_dataset, "test", motions=labelled_dataset)
    assert perfect["mpjpe_mm"] == 0.0 and perfect["clips"] == 38


@pytest.mark.parametrize("gt_length", [False, True])
def test_generation_row_from_a_tiny_gpt(tiny_evaluator, labelled_dataset, tiny_tokenizer, tmp_path, gt_length):
    from motok.data.dataset import MotionFile
    from motok.eval.report import T2MConfig, t2m
    from motok.gpt.train import resolve_config, train
    from motok.tokenizer.tokens import encode
    encode(tiny_tokenizer, labelled_dataset, tmp_path / "tokens.h5", command="pytest")
    cfg = resolve_config(None, ["model.num_layers=1", "model.dim=32", "model.heads=2", "model.block_size=24",
                                "text_encoder=bow", "batch_size=4", "iterations=2", "threads=1"])
    train(cfg, tmp_path / "tokens.h5", tmp_path / "gpt", command="pytest")
    pc = T2MConfig(repeats=2, gen_sets=2, mm_captions=3, mm_samples=3, gt_length=gt_length, physical=False)
    rep = t2m(tiny_evaluator[0], labelled_dataset, pc, gpt=tmp_path / "gpt", save_generated=tmp_path / "gen.h5",
              real=False)
    (row,) = rep["rows"]
    assert row["motions"] == 38 and row["mmodality_counts"] == {"captions": 3, "samples_per_caption": 3,
                                                                "pairs_per_caption": 10}
    assert ("GT length" in row["name"]) == gt_length and np.isfinite(row["metrics"]["FID"]["mean"])
    # the tiny GPT and the tiny evaluator both read bow: the report says their text side is shared
    assert row["gpt_text_encoder"] == "bow" and row["text_side"] == "shared"
    from motok.eval.report import markdown
    assert "(shared text side)" in markdown(rep)
    with MotionFile(tmp_path / "gen.h5", "motion") as mf:
        assert len(mf) == 2 * 38 + 3 * 3
        if gt_length:  # every t2m sample is as long as its source clip, cut to whole tokens
            with MotionFile(labelled_dataset) as data:
                test = data.split_indices("test")
                for k in range(38):
                    lab = mf.clip(k).labels
                    src = test[lab["source"]]
                    n = data.frame_offsets[src + 1] - data.frame_offsets[src]
                    assert len(mf.frames("features", k)) == min(n // 4, 23) * 4
    # the kept samples scored again as a --motions row (the text-to-physics queue's last step): the
    # same clips, MModality groups and FID, though the samples carry split "none" and the report "test"
    (again,) = t2m(tiny_evaluator[0], labelled_dataset, pc, motions=[tmp_path / "gen.h5"], real=False)["rows"]
    assert again["motions"] == 38 and "other_split_left_out" not in again
    assert again["mmodality_counts"] == row["mmodality_counts"]
    assert again["metrics"]["FID"]["mean"] == pytest.approx(row["metrics"]["FID"]["mean"], rel=1e-6)


def test_cli_t2m_fid_alias_recon_and_physical(tiny_evaluator, labelled_dataset, tmp_path):
    from motok.cli.main import app
    runner = CliRunner()
    gen = _motion_copy(labelled_dataset, tmp_path / "gen.h5", noise=0.1)
    base = ["--quiet", "eval", "fid", "-e", str(tiny_evaluator[0]), "--data", str(labelled_dataset),
            "--repeats", "2", "-m", str(gen)]
    r = runner.invoke(app, base + ["--json", "--out-md", str(tmp_path / "t.md")])
    assert r.exit_code == 0, r.output
    rep = json.loads(r.output)
    assert [x["name"] for x in rep["rows"]] == ["real motion", "gen"] and (tmp_path / "t.md").exists()
    r = runner.invoke(app, ["eval", "physical", str(gen), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["clips"] == 38
    assert json.loads(r.stdout)["skate_cm_s"] == pytest.approx(rep["rows"][1]["physical"]["skate_cm_s"])
    r = runner.invoke(app, ["eval", "recon", "--data", str(labelled_dataset), "-m", str(gen), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["mpjpe_mm"] > 0
    r = runner.invoke(app, ["eval", "captions", "--data", str(labelled_dataset), "--json"])
    assert r.exit_code == 0, r.output
    cap = json.loads(r.stdout)
    assert cap["clips"] == 38 and 0 < cap["share_in_train"] < 1 and 0 < cap["label_ceiling"]["R@1"] <= 1
    r = runner.invoke(app, base + ["--captions", "unseen", "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["captions"] == "unseen", r.output
    r = runner.invoke(app, base + ["--captions", "novel"])
    assert r.exit_code == 2 and "all or unseen" in r.output
    r = runner.invoke(app, base + ["--common-clips", "--json"])  # gen holds every test clip: nothing left out
    assert r.exit_code == 0 and json.loads(r.output)["config"]["common_clips"] is True, r.output
    assert [x["common_clips_left_out"] for x in json.loads(r.output)["rows"]] == [0, 0]
    r = runner.invoke(app, base + ["--tracked-to-end"])  # gen was not written by `control track`
    assert r.exit_code == 2 and "no --motions file holds clips written by" in r.output, r.output
    bad = runner.invoke(app, ["eval", "t2m", "-e", str(tmp_path / "nope"), "--data", str(labelled_dataset)])
    assert bad.exit_code == 2 and "bundle" in bad.output
    bad = runner.invoke(app, ["eval", "train-evaluator", "--data", str(labelled_dataset), "-o", str(tmp_path / "e"),
                              "--set", "filter_negatives=[style]"])
    assert bad.exit_code == 2 and "filter_negatives" in bad.output


def test_every_eval_recipe_loads():
    from motok.config import load_config
    from motok.eval.evaluator import EvaluatorConfig, resolve_config
    from motok.eval.report import T2MConfig
    from motok.gpt.train import resolve_config as gpt_config
    root = Path(__file__).resolve().parent.parent / "recipes" / "eval"
    # The default evaluator's text side is independent of the default GPT's (docs/eval.md).
    default = resolve_config(root / "evaluator.yaml").text_encoder
    gpt_default = {gpt_config(None, []).text_encoder, gpt_config(root.parent / "gpt" / "default.yaml").text_encoder}
    assert default == EvaluatorConfig().text_encoder == "bow" and gpt_default == {"minilm", "mpnet_tokens"} and default not in gpt_default
    assert resolve_config(root / "evaluator_minilm.yaml").text_encoder == "minilm"
    for path in sorted(root.glob("*.yaml")):
        if path.stem.startswith("evaluator"):
            assert resolve_config(path).iterations >= 1
        elif path.stem.endswith("_toy"):  # dry runs and smoke tests only: small, and said so
            cfg = load_config(T2MConfig, path)
            assert cfg.repeats < 20 and cfg.gen_sets <= cfg.repeats and "measure nothing" in path.read_text()
        else:
            assert load_config(T2MConfig, path).repeats == 20
