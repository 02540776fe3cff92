"""Motion inputs: files, directories, zip and tar archives read in memory, and .npy arrays."""

from __future__ import annotations

import io
import tarfile
import zipfile

import numpy as np
import pytest

from motok.data.bvh import BvhMotion, MotionFormatError
from motok.data.sources import MotionSource, count_sources, iter_sources, load_npy_positions


@pytest.fixture(scope="module")
def set1(bandai_dir):
    """The real set-1 archive, its member listing (read independently with tarfile) and its
    first few clips."""
    archive = bandai_dir / "bandai-namco-1.tar.xz"
    with tarfile.open(archive) as tf:
        members = [m.name for m in tf.getmembers() if m.isfile()]
    clips = {}
    with tarfile.open(archive) as tf:
        for m in tf:
            if m.name.endswith(".bvh"):
                clips[m.name.rsplit("/", 1)[-1]] = tf.extractfile(m).read()
                if len(clips) == 4:
                    break
    return archive, members, clips


def _npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def test_real_tar_xz_streams_every_clip_in_archive_order(set1):
    archive, members, _ = set1
    got = list(iter_sources(archive))
    bvh_members = [m for m in members if m.endswith(".bvh")]
    assert len(got) == len(bvh_members) == 174  # json labels, cfg/*.txt, README and LICENSE skipped
    assert [s.origin for s in got] == [f"{archive}:{m}" for m in bvh_members]
    assert all(s.kind == "bvh" and s.name == m.rsplit("/", 1)[-1][:-4] for s, m in zip(got, bvh_members))
    assert count_sources(archive) is None  # a compressed tar cannot be listed without decompressing it
    walks = list(iter_sources(archive, pattern="dataset-1_walk_*"))
    assert walks and all(s.name.startswith("dataset-1_walk_") for s in walks) and len(walks) < 174


def test_real_set2_archive_streams_lazily(bandai2_archive):
    it = iter_sources(bandai2_archive)
    first = [next(it) for _ in range(3)]
    it.close()  # stopping early must not need the rest of the 515 MB
    for s in first:
        assert s.origin.startswith(f"{bandai2_archive}:Bandai-Namco-Research-Motiondataset-2/data/")
        assert s.origin.endswith(s.name + ".bvh") and s.data.startswith(b"HIERARCHY")
        assert isinstance(s.load(), BvhMotion)


def _layout(root, clips):
    """A tree with clips in nested folders plus files that are not motion."""
    names = sorted(clips)
    files = {
        f"b/{names[0]}": clips[names[0]],
        f"a/deep/{names[1]}": clips[names[1]],
        names[2]: clips[names[2]],
        "a/labels.json": b'{"content": 1, "style": 2}',
        "README.md": b"# readme",
        "a/.hidden.bvh": b"not motion",
        "__MACOSX/a/._x.bvh": b"resource fork",
        "poses/pose.npy": _npy_bytes(np.zeros((5, 22, 3), np.float32)),
    }
    expected = [f"a/deep/{names[1]}", f"b/{names[0]}", names[2], "poses/pose.npy"]  # sorted paths
    return files, expected


def test_directory(set1, tmp_path):
    files, expected = _layout(tmp_path, set1[2])
    for rel, data in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(data)
    got = list(iter_sources(tmp_path))
    assert [s.origin for s in got] == [str(tmp_path / r) for r in expected]
    assert [s.data for s in got] == [files[r] for r in expected]
    assert [s.kind for s in got] == ["bvh", "bvh", "bvh", "npy"]
    assert count_sources(tmp_path) == 4
    assert [s.name for s in iter_sources(tmp_path, kinds=("npy",))] == ["pose"]
    assert count_sources(tmp_path, kinds=("bvh",)) == 3
    assert len(list(iter_sources(tmp_path, pattern="a/*"))) == 1  # with a slash: the relative path
    one = tmp_path / expected[2]
    assert [s.origin for s in iter_sources(one)] == [str(one)] and count_sources(one) == 1


def test_zip(set1, tmp_path):
    files, expected = _layout(tmp_path, set1[2])
    path = tmp_path / "clips.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("a/", b"")  # a directory entry
        for rel in reversed(list(files)):
            zf.writestr(rel, files[rel])
    got = list(iter_sources(path))
    assert [s.origin for s in got] == [f"{path}:{r}" for r in expected]
    assert [s.data for s in got] == [files[r] for r in expected]
    assert count_sources(path) == 4
    assert isinstance(got[0].load(), BvhMotion) and got[3].load().shape == (5, 22, 3)
    odd = tmp_path / "clips.bin"  # an archive recognized by content rather than name
    odd.write_bytes(path.read_bytes())
    assert len(list(iter_sources(odd))) == 4


@pytest.mark.parametrize("mode, suffix", [("w:gz", ".tar.gz"), ("w:bz2", ".tar.bz2"), ("w", ".tar")])
def test_tar(set1, tmp_path, mode, suffix):
    files, expected = _layout(tmp_path, set1[2])
    path = tmp_path / f"clips{suffix}"
    order = list(reversed(list(files)))
    with tarfile.open(path, mode) as tf:
        for rel in order:
            info = tarfile.TarInfo(rel)
            info.size = len(files[rel])
            tf.addfile(info, io.BytesIO(files[rel]))
    got = list(iter_sources(path))
    in_archive_order = [r for r in order if r in expected]
    assert [s.origin for s in got] == [f"{path}:{r}" for r in in_archive_order]
    assert [s.data for s in got] == [files[r] for r in in_archive_order]
    assert count_sources(path) == (4 if suffix == ".tar" else None)


def test_empty_archives_name_the_archive(tmp_path):
    z = tmp_path / "empty.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("README.md", b"nothing here")
    t = tmp_path / "labels.tar.gz"
    with tarfile.open(t, "w:gz") as tf:
        info = tarfile.TarInfo("x.json")
        info.size = 2
        tf.addfile(info, io.BytesIO(b"{}"))
    (tmp_path / "emptydir").mkdir()
    for path in (z, t, tmp_path / "emptydir"):
        with pytest.raises(MotionFormatError, match="no motion files") as e:
            list(iter_sources(path))
        assert e.value.source == str(path) and str(path) in str(e.value)


def test_unknown_and_broken_inputs(set1, tmp_path):
    txt = tmp_path / "notes.txt"
    txt.write_text("hello")
    with pytest.raises(MotionFormatError, match="unknown input type") as e:
        list(iter_sources(txt))
    assert str(txt) in str(e.value)
    with pytest.raises(MotionFormatError, match="unknown input type"):
        count_sources(txt)
    rar = tmp_path / "clips.rar"
    rar.write_bytes(b"Rar!\x1a\x07\x00" + bytes(100))
    with pytest.raises(MotionFormatError, match="unknown input type"):
        list(iter_sources(rar))
    with pytest.raises(FileNotFoundError):
        iter_sources(tmp_path / "missing.tar.xz")  # at the call, not at the first item
    with pytest.raises(FileNotFoundError):
        count_sources(tmp_path / "missing.bvh")
    cut = tmp_path / "cut.tar.xz"  # a download that stopped part way
    cut.write_bytes(set1[0].read_bytes()[:400_000])
    with pytest.raises(MotionFormatError, match="not a readable archive") as e:
        list(iter_sources(cut))
    assert e.value.source == str(cut)
    bad_zip = tmp_path / "bad.zip"
    bad_zip.write_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(MotionFormatError, match="not a readable archive"):
        list(iter_sources(bad_zip))


def test_npy_positions(golden_dir, golden_joints):
    data = (golden_dir / "new_joints_012314.npy").read_bytes()
    pos = load_npy_positions(data, "new_joints_012314.npy")
    assert pos.shape == golden_joints.shape and pos.shape[1:] == (22, 3) and pos.dtype == np.float64
    np.testing.assert_array_equal(pos, golden_joints)
    src = MotionSource("new_joints_012314", "x.npy", data, "npy")
    np.testing.assert_array_equal(src.load(), golden_joints)


@pytest.mark.parametrize("arr, part", [
    (np.zeros((10, 66), np.float32), "reshape it to (T, J, 3)"),
    (np.zeros((10, 22, 2)), "found (10, 22, 2)"),
    (np.zeros((10, 22)), "expected shape (T, J, 3)"),
    (np.zeros((0, 22, 3)), "at least one frame"),
    (np.zeros((10, 22, 3), np.int64), "dtype int64"),
    (np.array(["a"]), "dtype <U1"),
])
def test_npy_bad_shapes_and_dtypes(arr, part):
    with pytest.raises(MotionFormatError) as e:
        load_npy_positions(_npy_bytes(arr), "bad.npy")
    assert str(e.value).startswith("bad.npy: ") and part in str(e.value)


def test_npy_nan_and_unreadable():
    arr = np.zeros((8, 22, 3))
    arr[3, 5, 1] = np.nan
    with pytest.raises(MotionFormatError, match="frame 3, joint 5"):
        load_npy_positions(_npy_bytes(arr), "nan.npy")
    with pytest.raises(MotionFormatError, match="not a readable .npy"):
        load_npy_positions(b"HIERARCHY\n", "text.npy")
    with pytest.raises(MotionFormatError, match="not a readable .npy"):
        load_npy_positions(_npy_bytes(np.array([{"a": 1}], dtype=object)), "pickle.npy")
    buf = io.BytesIO()
    np.savez(buf, a=np.zeros((2, 22, 3)))
    with pytest.raises(MotionFormatError, match="npz"):
        load_npy_positions(buf.getvalue(), "arch.npy")
