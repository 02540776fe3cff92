"""HumanML3D's folder layout both ways (`motok export humanml3d`, `motok preprocess -d FOLDER`):
a round trip of real Bandai-Namco clips, the golden HumanML3D clip in both directions, and the
export loaded by a minimal reimplementation of the official loaders."""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.cli.main import app
from motok.data.dataset import MotionFile
from motok.data.humanml3d_folder import caption_line, export_humanml3d, fallback_tokens
from motok.data.preprocess import PreprocessConfig, preprocess
from motok.errors import UserError
from motok.features.humanml3d import feature_slices, mean_std, recover_from_ric

runner = CliRunner()


def _cli(*args) -> dict:
    r = runner.invoke(app, ["-q", *map(str, args), "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


class OfficialLoader:
    """What T2M-GPT's and MoMask's ``Text2MotionDataset`` do with a HumanML3D folder, rewritten
    from their description: the split file's names, ``Mean.npy``/``Std.npy`` from the folder,
    ``new_joint_vecs/NAME.npy``, ``texts/NAME.txt`` lines split at ``#`` into caption, tokens
    (``word/POS`` separated by spaces), start and end in seconds (0 and 0: the whole clip, else
    a crop of ``motion[int(start * fps):int(end * fps)]`` as its own item); motions outside
    ``[min_len, max_len)`` frames are dropped; an item is cropped at random to a multiple of
    ``unit`` frames, normalized and zero-padded to ``pad_to`` frames."""

    def __init__(self, root: Path, split: str, fps: float = 20.0, min_len: int = 40, max_len: int = 200,
                 unit: int = 4, pad_to: int = 196):
        self.mean, self.std = np.load(root / "Mean.npy"), np.load(root / "Std.npy")
        self.unit, self.pad_to, self.items = unit, pad_to, []
        ids = [ln.strip() for ln in (root / f"{split}.txt").read_text().splitlines()]
        for name in ids:
            motion = np.load(root / "new_joint_vecs" / f"{name}.npy")
            if not min_len <= len(motion) < max_len:
                continue
            whole = []
            for line in (root / "texts" / f"{name}.txt").read_text().splitlines():
                caption, tokens, start, end = line.strip().split("#")
                tokens = tokens.split(" ")
                assert all(t.count("/") == 1 for t in tokens), tokens  # the word vectorizer splits at '/'
                start, end = float(start), float(end)
                if start == 0.0 and end == 0.0:
                    whole.append((caption, tokens))
                else:
                    crop = motion[int(start * fps):int(end * fps)]
                    if min_len <= len(crop) < max_len:
                        self.items.append((name, crop, [(caption, tokens)]))
            if whole:
                self.items.append((name, motion, whole))

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        name, motion, texts = self.items[i]
        caption, tokens = random.choice(texts)
        n = len(motion) // self.unit * self.unit
        start = random.randint(0, len(motion) - n)
        x = (motion[start:start + n] - self.mean) / self.std
        x = np.concatenate([x, np.zeros((self.pad_to - n, x.shape[1]))]) if n < self.pad_to else x
        return caption, tokens, x, n, name


@pytest.fixture(scope="module")
def exported(small_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("hml") / "walks"
    summary = _cli("export", "humanml3d", "-d", small_dataset, "-o", out)
    return out, summary


def test_export_layout_and_statistics(exported, small_dataset):
    out, summary = exported
    with MotionFile(small_dataset) as mf:
        names, splits, J = mf.names, mf.splits, mf.skeleton.num_joints
        assert summary["clips"] == len(names) == 24 and summary["feature_dim"] == 251 == 12 * J - 1
        for split in ("train", "val", "test"):
            assert (out / f"{split}.txt").read_text().split() == [n for n, s in zip(names, splits) if s == split]
        assert (out / "all.txt").read_text().split() == names
        for i, name in enumerate(names[:5]):
            f, j = np.load(out / "new_joint_vecs" / f"{name}.npy"), np.load(out / "new_joints" / f"{name}.npy")
            assert f.dtype == j.dtype == np.float32 and f.shape[1] == 251 and j.shape == (len(f), J, 3)
            np.testing.assert_array_equal(f, mf.frames("features", i))
            # HumanML3D's new_joints are what recover_from_ric gives back from new_joint_vecs
            np.testing.assert_allclose(recover_from_ric(f, J), j, atol=1e-4)
            lines = (out / "texts" / f"{name}.txt").read_text().splitlines()
            assert [ln.split("#")[0] for ln in lines] == [c[0] for c in mf.captions(i)]
            assert all("/" in ln.split("#")[1] and ln.endswith("#0.0#0.0") for ln in lines)  # the annotations' POS
        # cal_mean_variance over the train split, which is also what preprocess stored
        train = [mf.frames("features", i) for i in mf.split_indices("train")]
        mean, std = mean_std(train, J)
        np.testing.assert_array_equal(np.load(out / "Mean.npy"), mean)
        np.testing.assert_array_equal(np.load(out / "Std.npy"), std)
        np.testing.assert_array_equal(np.load(out / "Std.npy"), mf.stats()[1])
    side = json.loads((out / "motok.json").read_text())
    assert side["skeleton"]["name"] == "bandai21" and side["stats_split"] == "train" and side["fps"] == 20.0


def test_round_trip_gives_back_features_joints_captions_and_splits(exported, small_dataset, tmp_path):
    out, _ = exported
    s = _cli("preprocess", "-d", out, "-o", tmp_path / "back.h5")
    assert s["statistics"] == "Mean.npy, Std.npy" and s["annotations"] == str(out)
    with MotionFile(small_dataset) as a, MotionFile(tmp_path / "back.h5", "motion-dataset") as b:
        assert b.names == a.names and b.splits == a.splits and b.skeleton.to_dict() == a.skeleton.to_dict()
        assert (b.fps, b.legacy) == (a.fps, a.legacy)
        np.testing.assert_array_equal(b.offsets, a.offsets)
        for key in ("features", "joints", "root_translation"):
            np.testing.assert_array_equal(b.h5["frames"][key][()], a.h5["frames"][key][()])
        # local rotations are re-derived by IK: the same up to the sign of a quaternion and the
        # forward smoothing's reach from the clip's end
        dots = np.abs((b.h5["frames/local_quats"][()] * a.h5["frames/local_quats"][()]).sum(-1))
        assert dots.min() > 1 - 1e-3
        for i in range(len(a)):
            assert b.clip(i).captions == a.clip(i).captions and b.clip(i).labels == a.clip(i).labels
        for x, y in zip(a.stats(), b.stats()):
            np.testing.assert_array_equal(x, y)
        assert b.h5["stats"].attrs["split"] == "train"
    for args, says in ((["--fps", "30"], "features are at 20 fps (its motok.json says) and cannot be resampled"),
                       (["-d", out / "new_joints"], "read it on its own, as the only -d")):
        r = runner.invoke(app, ["preprocess", "-d", str(out), *map(str, args), "-o", str(tmp_path / "no.h5")])
        assert r.exit_code == 2 and says in r.output, r.output


def test_the_export_loads_in_the_official_loader(exported, small_dataset):
    out, _ = exported
    with MotionFile(small_dataset) as mf:
        lengths = {n: int(mf.frame_offsets[i + 1] - mf.frame_offsets[i]) for i, n in enumerate(mf.names)}
        split_of = dict(zip(mf.names, mf.splits))
    for split in ("train", "test"):
        ds = OfficialLoader(out, split, min_len=24)
        expected = sorted(n for n, s in split_of.items() if s == split and 24 <= lengths[n] < 200)
        assert sorted(it[0] for it in ds.items) == expected and len(ds) > 0
        random.seed(0)
        caption, tokens, x, n, name = ds[0]
        assert x.shape == (196, 251) and n % 4 == 0 and np.all(np.isfinite(x)) and not x[n:].any()
        assert caption and tokens
    train = OfficialLoader(out, "train", min_len=24)
    z = np.concatenate([m for _, m, _ in train.items])
    z = (z - train.mean) / train.std
    assert np.abs(z.mean(0)).max() < 0.2  # normalized by the train statistics: about zero mean


def test_golden_clip_into_motok(golden_dir, golden_features, golden_joints, tmp_path):
    """An official HumanML3D folder (the golden clip, no motok.json) read into motok: the
    features and joints as they are, HumanML3D's own statistics, smpl22 from the 263 dims,
    legacy features; exported again, the same arrays come out."""
    root = tmp_path / "HumanML3D"
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (root / sub).mkdir(parents=True)
    shutil.copy(golden_dir / "new_joint_vecs_012314.npy", root / "new_joint_vecs" / "012314.npy")
    shutil.copy(golden_dir / "new_joints_012314.npy", root / "new_joints" / "012314.npy")
    for f in ("Mean.npy", "Std.npy"):
        shutil.copy(golden_dir / f, root / f)
    (root / "texts" / "012314.txt").write_text(
        "a person serves a tennis ball.#a/DET person/NOUN serve/VERB a/DET tennis/NOUN ball/NOUN#0.0#0.0\n"
        "someone swings an arm overhead.#someone/PRON swing/VERB an/DET arm/NOUN overhead/ADV#1.0#5.0\n")
    (root / "test.txt").write_text("012314\n")
    s = _cli("preprocess", "-d", root, "-o", tmp_path / "golden.h5")
    assert s["skeleton"] == "smpl22" and s["legacy"] is True and s["splits"]["test"] == 1
    with MotionFile(tmp_path / "golden.h5") as mf:
        c = mf.clip("012314")
        np.testing.assert_array_equal(c.features, golden_features)
        np.testing.assert_array_equal(c.joints, golden_joints)
        assert c.split == "test" and [x[2:] for x in c.captions] == [(0.0, 0.0), (1.0, 5.0)]
        np.testing.assert_array_equal(mf.stats()[0], np.load(golden_dir / "Mean.npy"))
        np.testing.assert_array_equal(mf.stats()[1], np.load(golden_dir / "Std.npy"))
        assert mf.h5["stats"].attrs["split"] == "all"  # HumanML3D's script: every file of the folder
    _cli("export", "humanml3d", "-d", tmp_path / "golden.h5", "-o", tmp_path / "again")
    np.testing.assert_array_equal(np.load(tmp_path / "again/new_joint_vecs/012314.npy"), golden_features)
    np.testing.assert_array_equal(np.load(tmp_path / "again/new_joints/012314.npy"), golden_joints)
    assert (tmp_path / "again/texts/012314.txt").read_text() == (root / "texts/012314.txt").read_text()
    ds = OfficialLoader(tmp_path / "again", "test")
    assert [(it[0], len(it[1])) for it in ds.items] == [("012314", 80), ("012314", 170)]  # the span, the clip


def test_golden_joints_out_of_motok(golden_dir, golden_features, golden_joints, tmp_path):
    """The other way: HumanML3D's joints preprocessed by motok (legacy) and exported give back
    the official feature vectors (frames 0-88, docs/features.md) and the joints."""
    cfg = PreprocessConfig(data=[str(golden_dir / "new_joints_012314.npy")], annotations=None,
                           skeleton="smpl22", legacy=True)
    preprocess(cfg, tmp_path / "g.h5")
    s = export_humanml3d(tmp_path / "g.h5", tmp_path / "out")
    assert s["stats_split"] == "all" and s["captioned"] == 0 and not (tmp_path / "out/texts").exists()
    feats = np.load(tmp_path / "out/new_joint_vecs/new_joints_012314.npy")
    for block, sl in feature_slices(22).items():
        assert np.abs(feats[:89, sl] - golden_features[:89, sl]).max() < 1e-4, block
    joints = np.load(tmp_path / "out/new_joints/new_joints_012314.npy")
    assert np.abs(joints - golden_joints[:len(joints)]).max() < 1e-4
    assert (tmp_path / "out/all.txt").read_text() == "new_joints_012314\n"
    assert (tmp_path / "out/train.txt").read_text() == ""


def test_captions_without_tokens_and_bad_outputs(small_dataset, tmp_path):
    assert fallback_tokens("A person walks, then turns.") == "a/OTHER person/OTHER walks/OTHER then/OTHER turns/OTHER"
    line = caption_line("a person waves.", "", 1.0, 2.5, "x")
    assert line == "a person waves.#a/OTHER person/OTHER waves/OTHER#1.0#2.5"
    with pytest.raises(UserError, match="'#'"):
        caption_line("a # b", "", 0, 0, "x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "old.npy").write_bytes(b"")
    r = runner.invoke(app, ["export", "humanml3d", "-d", str(small_dataset), "-o", str(tmp_path / "full")])
    assert r.exit_code == 2 and "is not an empty folder" in r.output
    r = runner.invoke(app, ["export", "humanml3d", "-d", str(small_dataset), "--stats", "val", "-o",
                            str(tmp_path / "x")])
    assert r.exit_code == 2 and "--stats 'val'" in r.output and not (tmp_path / "x").exists()
    assert not list(tmp_path.glob(".*part*"))  # nothing half-written left behind
