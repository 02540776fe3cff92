"""Non-finite motion: a motion artifact with a NaN or an infinity in its frames is refused by every
reader that consumes it (tracking's reference library, motion matching, the T2M rows, the
physical metrics, tokenizer training), naming the clip and the frame, instead of an SVD that does
not converge, an infinite distance with exit 0 or a metric that equals the real row's."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from motok.cli.main import app
from motok.data.dataset import MotionFile, NonFiniteMotionError

CLIP, FRAME = 3, 17


@pytest.fixture(scope="module")
def broken(small_dataset, tmp_path_factory):
    """Copies of the walk dataset with a NaN in one joint (``joints``) or an infinity in one
    feature (``features``) of clip CLIP, frame FRAME."""
    out = {}
    for key, bad in (("joints", np.nan), ("features", np.inf)):
        p = tmp_path_factory.mktemp("nonfinite") / f"{key}.h5"
        shutil.copyfile(small_dataset, p)
        with h5py.File(p, "r+") as f:
            row = int(f["clips/offset"][CLIP]) + FRAME
            ds = f["frames"][key]
            v = ds[row]
            v.flat[1] = bad
            ds[row] = v
        out[key] = p
    with MotionFile(small_dataset) as mf:
        out["name"], out["split"] = mf.names[CLIP], mf.splits[CLIP]
    return out


def _says(msg: str, name: str) -> bool:
    return f"clip {name!r} frame {FRAME}" in msg and "NaN or inf" in msg


@pytest.mark.parametrize("key", ["joints", "features"])
def test_reading_a_clip_refuses_non_finite_frames(broken, key):
    with MotionFile(broken[key]) as mf:
        with pytest.raises(NonFiniteMotionError) as e:
            mf.frames(key, CLIP)
        assert _says(str(e.value), broken["name"])
        mf.frames(key, CLIP + 1)  # the other clips are still readable
        other = "features" if key == "joints" else "joints"
        mf.frames(other, CLIP)


def test_bulk_readers_refuse_them_too(broken):
    from motok.eval.evaluator import load_split
    from motok.eval.transitions import load_set
    from motok.tokenizer.train import load_train_data

    with pytest.raises(NonFiniteMotionError) as e:
        load_train_data(broken["features"], broken["split"], 4)
    assert _says(str(e.value), broken["name"])
    with MotionFile(broken["features"]) as mf, pytest.raises(NonFiniteMotionError):
        load_split(mf, None)  # the evaluator's and `eval t2m --motions`' rows
    with pytest.raises(NonFiniteMotionError) as e:
        load_set(broken["joints"])  # `eval motion-matching`, in bulk for many clips
    assert _says(str(e.value), broken["name"])


def test_the_reference_library_of_tracking_refuses_them(hum, broken):
    from motok.sim.reference import load_library

    with pytest.raises(NonFiniteMotionError) as e:
        load_library(hum, broken["joints"], clips=[broken["name"]])
    assert _says(str(e.value), broken["name"])


@pytest.mark.parametrize("cmd", [["eval", "physical", "-d", "BAD"],
                                 ["eval", "motion-matching", "-d", "DATA", "--motions", "BAD", "--threshold", "0.5"]])
def test_the_commands_say_it_in_one_line(cmd, broken, small_dataset):
    args = [{"BAD": str(broken["joints"]), "DATA": str(small_dataset)}.get(a, a) for a in cmd]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and _says(lines[0], broken["name"]), r.output
