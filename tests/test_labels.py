"""Label accuracy (motok eval labels), the phrasing-held-out split, the retrieval baseline and the
text-separation check, on real Bandai-Namco set-2 motion."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.artifacts import Provenance
from motok.data.dataset import MotionFile, write_motion
from motok.eval.labels import LabelsConfig, caption_lookup, evaluate_motions, fit_classifier, score
from motok.text import phrasings as P
from motok.text.separation import measure

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def classifier(labelled_dataset):
    return fit_classifier(labelled_dataset, LabelsConfig(crops=2))


def _real_test_motion(data, path, relabel=lambda lab: lab):
    """The real test clips as a motion artifact whose labels say what each should show."""
    with MotionFile(data, "motion-dataset") as mf:
        clips = [mf.clip(i) for i in mf.split_indices("test")]
        clips = [replace(c, split="none", labels=relabel(dict(c.labels))) for c in clips]
        write_motion(path, "motion", Provenance(command="pytest", config={}), clips, mf.skeleton, mf.offsets, mf.fps,
                     mf.legacy)
    return path


SWAP = {"left": "right", "right": "left"}


def _wrong(lab: dict) -> dict:
    """Left and right swapped, one hand made both and both made left: every content wrong."""
    c = lab["content"]
    if "left" in c or "right" in c:
        c = re.sub(r"left|right", lambda m: SWAP[m.group()], c)
    elif "both" in c:
        c = c.replace("both-hands", "left-hand")
    else:
        c = {"walk": "run", "run": "walk"}[c]
    return {**lab, "content": c}


def test_classifier_reads_real_held_out_motion(classifier, labelled_dataset, tmp_path):
    # 10 contents (chance 0.1) and 7 styles (chance 0.14), fitted on train clips, measured on test clips.
    assert classifier.test_clips >= 20
    assert classifier.test_accuracy["content"] >= 0.8
    assert classifier.test_accuracy["style"] >= 0.4
    assert len(classifier.classes["content"]) == 10 and len(classifier.classes["style"]) == 7
    right = evaluate_motions(classifier, _real_test_motion(labelled_dataset, tmp_path / "right.h5"))
    assert right["all"]["content"]["accuracy"] == pytest.approx(classifier.test_accuracy["content"])
    assert right["all"]["style"]["accuracy"] == pytest.approx(classifier.test_accuracy["style"])
    # The same motion scored against the wrong requests (left/right, one/both hands, walk/run): low.
    wrong = evaluate_motions(classifier, _real_test_motion(labelled_dataset, tmp_path / "wrong.h5", _wrong))
    assert wrong["all"]["content"]["accuracy"] <= 0.2
    assert wrong["all"]["style"]["accuracy"] == right["all"]["style"]["accuracy"]  # styles untouched


def test_predictions_do_not_depend_on_the_batch_or_a_crop_of_the_clip(classifier, labelled_dataset):
    with MotionFile(labelled_dataset, "motion-dataset") as mf:
        clips = [mf.frames("features", i) for i in mf.split_indices("test")[:6]]
    together = classifier.predict(clips)
    alone = [classifier.predict([c])["content"][0] for c in clips]
    assert together["content"] == alone
    # A clip and the same clip played twice in a row: same whole-clip mean and std, so mostly the same reading.
    twice = classifier.predict([np.concatenate([c, c]) for c in clips])["content"]
    assert np.mean([a == b for a, b in zip(twice, alone)]) >= 0.5


def test_score_counts_only_clips_that_name_a_label():
    pred = {"content": ["walk", "run", "walk"], "style": ["normal", "active", "elderly"]}
    sc = score(pred, [{"content": "walk", "style": "normal"}, {"content": "walk"}, {}])
    assert sc["content"] == {"accuracy": 0.5, "clips": 2, "per_class": {"walk": 0.5}}
    assert sc["style"]["accuracy"] == 1.0 and sc["style"]["clips"] == 1
    assert sc["unlabelled"] == 1


def test_heldout_wordings_and_paraphrases_are_fixed(labelled_dataset):
    assert P.VERSION == 1
    assert set(P.HELDOUT_CONTENT) == set(P.CONTENT_PARAPHRASES)
    assert set(P.HELDOUT_STYLE) == set(P.STYLE_PARAPHRASES)
    assert P.is_heldout("Someone walks and makes a left turn.")
    assert P.is_heldout("A person waves the right hand wearily.")
    assert not P.is_heldout("A person walks forward and turns left.")
    assert not P.is_heldout("A tired person waves the right hand in an exhausted way.")
    para = P.paraphrase_prompts()
    assert len(para) == 450 and len({p.text for p in para}) == 450
    assert sum(p.style is None for p in para) == 30
    # The paraphrases' words are never in a caption, apart from what names the content's side and limb.
    lookup = caption_lookup(labelled_dataset)
    vocab = {w for t in lookup if t not in {p.text for p in para} for w in re.findall(r"[a-z']+", t.lower())}
    shared = {"a", "an", "the", "and", "to", "with", "of", "at", "by", "in", "as", "like", "up",  # function words
              "left", "right", "both", "hand", "hands", "arm", "arms"}  # what names the side and the limb
    for p in para:
        words = set(re.findall(r"[a-z']+", p.text.lower()))
        assert not (words & vocab) - shared, p.text
    # Every caption wording that the split holds out exists in the data, and the rest remain.
    with MotionFile(labelled_dataset, "motion-dataset") as mf:
        texts = [t for i in range(len(mf)) for t, _, _ in mf.captions(i)]
    for name, pat in P.HELDOUT_WORDINGS.items():
        assert any(re.search(pat, t.lower()) for t in texts), name
    assert 0.2 < np.mean([P.is_heldout(t) for t in texts]) < 0.7
    train = P.prompt_set("train", labelled_dataset)
    held = P.prompt_set("heldout_wordings", labelled_dataset)
    assert train and held and not any(P.is_heldout(p.text) for p in train) and all(P.is_heldout(p.text) for p in held)


def test_labels_command_scores_motions_and_the_retrieval_baseline(labelled_dataset, tmp_path):
    from motok.cli.main import app

    real = _real_test_motion(labelled_dataset, tmp_path / "real.h5")
    out = tmp_path / "labels.json"
    r = CliRunner().invoke(app, ["eval", "labels", "-d", str(labelled_dataset), "--motions", str(real),
                                 "--retrieval", "bow", "--set", "crops=1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    rep = json.loads(out.read_text())
    assert rep["kind"] == "labels-report" and rep["classifier"]["test_accuracy"]["content"] >= 0.8
    assert rep["rows"]["real"]["scores"]["all"]["content"]["accuracy"] >= 0.8
    ret = rep["rows"]["retrieval (bow)"]["scores"]
    assert set(ret) == {"all", "train", "heldout_wordings", "paraphrases"}
    # Test captions in training wordings mostly occur in training (on this 210-clip slice less often
    # than on the whole set): bow retrieves their content far above chance (0.1).
    assert ret["train"]["content"]["accuracy"] >= 0.5
    assert ret["paraphrases"]["content"]["clips"] == 450
    # A motion artifact that says nothing about what it should show is refused with a clear error.
    with MotionFile(labelled_dataset, "motion-dataset") as mf:
        c = replace(mf.clip(0), labels={}, captions=[("something entirely different", "", 0.0, 0.0)])
        write_motion(tmp_path / "blank.h5", "motion", Provenance(command="pytest", config={}), [c], mf.skeleton,
                     mf.offsets, mf.fps, mf.legacy)
    r = CliRunner().invoke(app, ["eval", "labels", "-d", str(labelled_dataset), "--motions",
                                 str(tmp_path / "blank.h5")])
    assert r.exit_code == 2 and "no clip says what it should show" in r.output


def test_separation_statistics_on_known_embeddings():
    pairs = {"x": (["a1", "a2", "a3"], ["b1", "b2", "b3"])}
    meaning = lambda ts: np.array([[1.0, 0.0, 0.1 * int(t[1])] if t[0] == "a" else [0.0, 1.0, 0.1 * int(t[1])]
                                   for t in ts])
    wording = lambda ts: np.array([[float(t[1] == k) for k in "123"] + [0.01 * (t[0] == "a")] for t in ts])
    m = measure(meaning, pairs)["x"]
    assert m["closer_rate"] == 1.0 and m["margin"] > 0.5 and m["same_wording"] == pytest.approx(0.0, abs=0.1)
    w = measure(wording, pairs)["x"]
    assert w["closer_rate"] == 0.0 and w["margin"] < -0.5


def test_text_separation_command_bow(labelled_dataset):
    from motok.cli.main import app

    r = CliRunner().invoke(app, ["eval", "text-separation", "--encoder", "bow", "-d", str(labelled_dataset), "--json"])
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)["encoders"]["bow"]
    # Bag of words sees the shared words: the same wording with the other side is nearer than a paraphrase.
    assert rep["contrasts"]["turn left / right"]["margin"] < 0
    assert rep["nearest_caption"]["train"]["content"] >= 0.5  # chance 0.1


def test_classifier_cache_round_trip(classifier, labelled_dataset, tmp_path):
    from motok.eval.labels import load_classifier, save_classifier

    save_classifier(classifier, tmp_path / "clf.npz", key="k1")
    back = load_classifier(tmp_path / "clf.npz", key="k1")
    assert load_classifier(tmp_path / "clf.npz", key="other") is None  # another dataset or config: refit
    with MotionFile(labelled_dataset, "motion-dataset") as mf:
        clips = [mf.frames("features", i) for i in mf.split_indices("test")]
    assert back.predict(clips) == classifier.predict(clips)
    assert back.test_accuracy == classifier.test_accuracy and back.classes == classifier.classes
