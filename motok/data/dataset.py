"""The motion artifacts: ``motion-dataset`` (preprocessed mocap with captions, splits and
statistics) and ``motion`` (any motion motok makes later: decoded tokens, GPT samples).

Both use one packed layout, documented in ``docs/artifacts.md``: every frame of every clip
concatenated under ``/frames`` with a clip offset index under ``/clips``, so a training
loader slices contiguous rows instead of opening one HDF5 group per clip.
"""

from __future__ import annotations

import fnmatch
import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from motok.artifacts import (ArtifactError, Provenance, open_artifact, provenance_of, read_strings, write_artifact,
                             write_strings)
from motok.errors import UnknownNameError, UserError
from motok.skeleton import Skeleton

MOTION_KINDS = ("motion-dataset", "motion")
# What a clip in no split carries: "none" is what motok writes (own data, GPT samples); "" older files.
NO_SPLIT = ("none", "")
# The label `motok control track` gives each simulated clip: played to its end (true) or only to
# the controller's failure (false); `motok eval t2m --tracked-to-end` keeps the first.
TRACKED_TO_END = "tracked_to_end"


@dataclass
class Clip:
    name: str
    features: np.ndarray  # (T, 12J-1)
    joints: np.ndarray  # (T, J, 3) canonical global positions, metres
    local_quats: np.ndarray  # (T, J, 4)
    root_translation: np.ndarray  # (T, 3)
    source: str = ""
    source_fps: float = 0.0
    split: str = "none"
    labels: dict = field(default_factory=dict)
    captions: list = field(default_factory=list)  # [(text, tokens, start, end)]

    @property
    def num_frames(self) -> int:
        return len(self.features)


FRAME_KEYS = ("features", "joints", "local_quats", "root_translation")
FRAME_CHUNK = 4096  # rows per HDF5 chunk of a frames dataset: whole-clip reads touch few chunks


def write_motion(path, kind: str, provenance: Provenance, clips: list[Clip], skeleton: Skeleton,
                 offsets: np.ndarray, fps: float, legacy: bool, stats: tuple | None = None) -> Path:
    """Write clips in the packed layout; atomic (see :func:`motok.artifacts.write_artifact`)."""
    if not clips:
        raise ValueError(f"{path}: refusing to write a {kind} artifact with no clips")
    with MotionWriter(path, kind, provenance, skeleton, offsets, fps, legacy, stats, stream=False) as w:
        w.add(clips)
    return Path(path)


class MotionWriter:
    """A motion artifact written a batch of clips at a time (:meth:`add`), for motion too large
    to hold at once (Table 1's 800,000 generated frames per row): frames go to the file as they
    come and only each clip's name, labels and captions are kept until the end. The file appears
    only if the ``with`` block ends without an error, as with :func:`write_motion`.

    ``stream=False`` takes every clip in one :meth:`add` into contiguous datasets (what
    :func:`write_motion` does): HDF5's chunked, resizable datasets keep dirty chunks in a cache that
    is written when the file closes, and a disk that fills then fails inside h5py's deallocation,
    where no error can reach the caller (the process dies). Streaming flushes after every batch so
    a full disk surfaces as an error from :meth:`add`."""

    def __init__(self, path, kind: str, provenance: Provenance, skeleton: Skeleton, offsets: np.ndarray,
                 fps: float, legacy: bool, stats: tuple | None = None, stream: bool = True):
        self.stream = stream
        self.path, self.kind, self.provenance = path, kind, provenance
        self.skeleton, self.offsets, self.fps, self.legacy, self.stats = skeleton, offsets, fps, legacy, stats
        self.clips: list[Clip] = []  # frameless copies: the frames are already in the file
        self.frames = 0

    def __enter__(self):
        self._cm = write_artifact(self.path, self.kind, self.provenance)
        f = self.f = self._cm.__enter__()
        f.attrs["fps"] = float(self.fps)
        f.attrs["legacy"] = bool(self.legacy)
        f.attrs["num_joints"] = int(self.skeleton.num_joints)
        sk = f.create_group("skeleton")
        sk.attrs["definition"] = json.dumps(self.skeleton.to_dict())
        write_strings(sk, "names", self.skeleton.joints)
        sk.create_dataset("parents", data=self.skeleton.parents)
        sk.create_dataset("offsets", data=np.asarray(self.offsets, dtype=np.float32))
        self.fr = f.create_group("frames")
        return self

    def add(self, clips: list[Clip]) -> None:
        """Append ``clips``' frames to the file."""
        if not clips:
            return
        n = sum(c.num_frames for c in clips)
        if not self.stream and self.frames:
            raise ValueError(f"{self.path}: a writer with stream=False takes all its clips in one add")
        for key in FRAME_KEYS:
            rows = np.concatenate([getattr(c, key) for c in clips]).astype(np.float32)
            if not self.stream:
                self.fr.create_dataset(key, data=rows)
            elif key not in self.fr:
                self.fr.create_dataset(key, data=rows, maxshape=(None,) + rows.shape[1:],
                                       chunks=(FRAME_CHUNK,) + rows.shape[1:])
            else:
                ds = self.fr[key]
                ds.resize(self.frames + n, axis=0)
                ds[self.frames:] = rows
        if "feature_dim" not in self.f.attrs:
            self.f.attrs["feature_dim"] = int(clips[0].features.shape[1])
        if self.stream:
            self.f.flush()
        self.frames += n
        empty = np.zeros((0,))
        self.clips += [replace(c, features=np.zeros((c.num_frames, 0)), joints=empty, local_quats=empty,
                               root_translation=empty) for c in clips]

    def _finish(self) -> None:
        """The clip index, captions and statistics, written once every frame is in."""
        clips, f = self.clips, self.f
        if not clips:
            raise ValueError(f"{self.path}: refusing to write a {self.kind} artifact with no clips")
        c = f.create_group("clips")
        write_strings(c, "name", [x.name for x in clips])
        write_strings(c, "source", [x.source for x in clips])
        c.create_dataset("source_fps", data=np.array([x.source_fps for x in clips], dtype=np.float64))
        write_strings(c, "split", [x.split for x in clips])
        write_strings(c, "labels", [json.dumps(x.labels, sort_keys=True) for x in clips])
        lengths = np.array([x.num_frames for x in clips], dtype=np.int64)
        c.create_dataset("offset", data=np.concatenate([[0], np.cumsum(lengths)]))

        caps = [(i, *cap) for i, x in enumerate(clips) for cap in x.captions]
        g = f.create_group("captions")
        g.create_dataset("clip", data=np.array([r[0] for r in caps], dtype=np.int64))
        write_strings(g, "text", [r[1] for r in caps])
        write_strings(g, "tokens", [r[2] for r in caps])
        g.create_dataset("start", data=np.array([r[3] for r in caps], dtype=np.float64))
        g.create_dataset("end", data=np.array([r[4] for r in caps], dtype=np.float64))
        if self.stats is not None:
            st = f.create_group("stats")
            st.attrs["split"] = self.stats[2]
            st.create_dataset("mean", data=np.asarray(self.stats[0], dtype=np.float32))
            st.create_dataset("std", data=np.asarray(self.stats[1], dtype=np.float32))

    def __exit__(self, et, ev, tb):
        if et is None:
            try:
                self._finish()
            except BaseException as e:  # the half-written file must not appear
                self._cm.__exit__(type(e), e, e.__traceback__)
                raise
        return self._cm.__exit__(et, ev, tb)


def clip_index(names: list[str], clip, positions: dict[str, int] | None = None, where: str = "",
               within: str = "", error: type[Exception] = UnknownNameError) -> int:
    """Position of ``clip`` (a name in ``names`` or an index into it), else ``error`` with a one-line
    message that suggests similar names. ``positions`` (name -> index) spares a linear search;
    ``where`` prefixes the message and ``within`` follows the clip's name in it."""
    if isinstance(clip, (int, np.integer)):
        if not 0 <= int(clip) < len(names):
            raise error(f"{where}clip index {clip} out of range (0..{len(names) - 1})")
        return int(clip)
    if clip not in (names if positions is None else positions):
        near = [n for n in names if str(clip).lower() in n.lower()][:5]
        hint = f"; similar: {near}" if near else f"; first clips: {names[:3]}"
        raise error(f"{where}no clip named {clip!r}{within}{hint}")
    return names.index(clip) if positions is None else positions[clip]


class NonFiniteMotionError(UserError):
    """A motion artifact whose frames hold NaN or infinite numbers."""


class ClipFile:
    """What the readers of clip-indexed artifacts share (motion, motion-dataset, tokens): the open
    file, its skeleton, the clips' names and splits, their captions; a context manager."""

    # What every such artifact holds (a subclass adds its own): checked when it is opened, so a file
    # another tool wrote, or one cut short, is one line and not a KeyError deep in a reader.
    REQUIRED = ("skeleton", "skeleton/offsets", "clips/name", "clips/split", "clips/labels", "clips/offset",
                "captions/clip", "captions/text", "captions/tokens", "captions/start", "captions/end")
    ROWS: tuple[str, ...] = ()  # datasets of one row per frame (or token), indexed by clips/offset

    def __init__(self, path, kind: str | tuple[str, ...]):
        self.path = Path(path)
        self.h5 = f = open_artifact(path, kind)
        try:
            self._check_layout()
        except ArtifactError:
            f.close()
            raise
        self.skeleton = Skeleton.from_dict(json.loads(f["skeleton"].attrs["definition"]), source=f"{path}:/skeleton")
        self.names = read_strings(f["clips/name"])
        self.splits = read_strings(f["clips/split"])
        self._index = {n: i for i, n in enumerate(self.names)}
        self._captions = None

    def _check_layout(self) -> None:
        f, kind = self.h5, str(self.h5.attrs["kind"])
        missing = [m for m in (*self.REQUIRED, *self.ROWS) if m not in f]
        if missing or "definition" not in f["skeleton"].attrs:
            what = missing[0] if missing else "skeleton.definition"
            raise ArtifactError(f"{self.path}: a {kind} artifact without {what} (damaged, or not written by motok)")
        off, n = f["clips/offset"], len(f["clips/name"])
        ends = off[()] if len(off) == n + 1 else None
        if ends is None or (np.diff(ends) < 0).any() or ends[0] != 0:
            raise ArtifactError(f"{self.path}: clips/offset does not index its {n} clips (damaged, or not written "
                                f"by motok)")
        for m in self.ROWS:
            if len(f[m]) != ends[-1]:
                raise ArtifactError(f"{self.path}: {m} has {len(f[m])} rows, its clips end at row {ends[-1]} "
                                    f"(damaged, or not written by motok)")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self.h5.close()

    def __len__(self):
        return len(self.names)

    @property
    def provenance(self) -> Provenance:
        return provenance_of(self.h5)

    def index(self, name_or_index) -> int:
        return clip_index(self.names, name_or_index, positions=self._index, where=f"{self.path}: ")

    def captions(self, clip, tokens: bool = False) -> list[tuple]:
        """``[(text, start, end)]`` of a clip; with ``tokens``, ``[(text, tokens, start, end)]``
        (the ``word/POS`` tokens of the annotations, "" where there were none)."""
        i = self.index(clip)
        if self._captions is None:  # read once: per-call reads made whole-dataset loops quadratic
            g = self.h5["captions"]
            self._captions = (g["clip"][()], read_strings(g["text"]), read_strings(g["tokens"]), g["start"][()],
                              g["end"][()])
        owner, texts, toks, start, end = self._captions
        return [(texts[j], *((toks[j],) if tokens else ()), float(start[j]), float(end[j]))
                for j in np.flatnonzero(owner == i)]


class MotionFile(ClipFile):
    """Read access to a motion or motion-dataset artifact; clips load lazily by name or index."""

    REQUIRED = (*ClipFile.REQUIRED, "clips/source", "clips/source_fps")
    ROWS = tuple(f"frames/{k}" for k in FRAME_KEYS)

    def __init__(self, path, kind: str | tuple[str, ...] = MOTION_KINDS):
        super().__init__(path, kind)
        f = self.h5
        self.kind = str(f.attrs["kind"])
        self.fps = float(f.attrs["fps"])
        self.legacy = bool(f.attrs["legacy"])
        self.offsets = f["skeleton/offsets"][()]
        self.frame_offsets = f["clips/offset"][()]

    def frames(self, key: str, clip) -> np.ndarray:
        """The rows ``key`` (features, joints, ...) of one clip, refused if any is NaN or inf."""
        i = self.index(clip)
        a, b = self.frame_offsets[i], self.frame_offsets[i + 1]
        return self.check_finite(key, self.h5["frames"][key][a:b], i)

    def check_finite(self, key: str, rows: np.ndarray, clip: int) -> np.ndarray:
        """``rows`` (clip ``clip``'s ``key``, read in bulk) if every number is finite, else an error
        naming the clip and its first bad frame. Motion with a NaN or inf in it is never consumed:
        an SVD on it fails deep inside the tracker, a distance to it is infinite, a metric on it
        equals whatever the NaN-skipping reduction left (a real clip's), all without a word."""
        finite = np.isfinite(rows)
        if finite.all():  # the common case costs one vectorised pass
            return rows
        bad = int(np.flatnonzero(~finite.reshape(len(rows), -1).all(1))[0])
        raise NonFiniteMotionError(f"{self.path}: clip {self.names[clip]!r} frame {bad}: {key} holds NaN or inf "
                                   f"(motion with non-finite numbers cannot be tracked or measured)")

    def clip(self, clip) -> Clip:
        i = self.index(clip)
        c = self.h5["clips"]
        return Clip(
            name=self.names[i],
            features=self.frames("features", i), joints=self.frames("joints", i),
            local_quats=self.frames("local_quats", i), root_translation=self.frames("root_translation", i),
            source=_str(c["source"][i]), source_fps=float(c["source_fps"][i]), split=self.splits[i],
            labels=json.loads(c["labels"][i]),
            captions=self.captions(i, tokens=True),
        )

    def split_indices(self, split: str) -> list[int]:
        return [i for i, s in enumerate(self.splits) if s == split]

    def stats(self) -> tuple[np.ndarray, np.ndarray]:
        if "stats" not in self.h5:
            raise UnknownNameError(f"{self.path}: a {self.kind} artifact has no statistics")
        return self.h5["stats/mean"][()], self.h5["stats/std"][()]


def _str(v) -> str:
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def select_clips(data, pattern: str | None, split: str | None = None) -> list[str]:
    """Names of the clips of the motion artifact at ``data`` (or of an open one: a
    :class:`MotionFile`, clips in memory) in ``split`` (train, val, test; all if None) matching
    the glob ``pattern`` (all if None)."""
    if not hasattr(data, "split_indices"):
        with MotionFile(data) as mf:
            return select_clips(mf, pattern, split)
    names = list(data.names)
    if split is not None:
        if split not in data.splits:
            raise UserError(f"{data.path} has no split {split!r} (it has {sorted(set(data.splits))})")
        names = [names[i] for i in data.split_indices(split)]
    if not pattern:
        return names
    chosen = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
    if not chosen:
        where = f" in split {split!r}" if split else ""
        raise UserError(f"no clip of {data.path}{where} matches {pattern!r} (e.g. {names[:3]})")
    return chosen
