"""BVH motion capture files: vectorized parsing and forward kinematics (writing: ``motok.data.export``).

The HIERARCHY is small (a few hundred tokens) and is walked token by token; the MOTION block
is most of the file and is read as one numeric array by numpy's C parser. Line-by-line Python
runs only after that fast path has failed, to name the offending line.
"""

from __future__ import annotations

import io
import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from motok.errors import MotokError
from motok.rotations import euler_to_quat, qinv, qmul, qrot

__all__ = ["MotionFormatError", "BvhMotion", "parse_bvh", "read_bvh", "forward_kinematics"]


class MotionFormatError(MotokError, ValueError):
    """A motion input that cannot be read; the message names the file, the line or field, and
    what was expected there."""

    def __init__(self, source: str, message: str, line: int | None = None):
        self.source, self.message, self.line = str(source), message, line
        where = self.source if line is None else f"{self.source}, line {line}"
        super().__init__(f"{where}: {message}")

    def __reduce__(self):  # the default would call __init__ with the formatted text only
        return type(self), (self.source, self.message, self.line)


@dataclass
class BvhMotion:
    source: str
    names: list[str]
    parents: np.ndarray  # (J,) int, -1 for the root
    offsets: np.ndarray  # (J, 3) OFFSET values in file units
    channels: list[tuple[str, ...]]
    end_sites: dict[int, np.ndarray]
    frame_time: float
    rotations: np.ndarray  # (T, J, 4) local quaternions (w, x, y, z)
    translations: np.ndarray  # (T, J, 3) position channels where present, else the OFFSET

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def global_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations ``(T, J, 4)`` and positions ``(T, J, 3)``."""
        return forward_kinematics(self.parents, self.rotations, self.translations)

    def global_positions(self) -> np.ndarray:
        return self.global_transforms()[1]

    def subset(self, names) -> "BvhMotion":
        """The same motion on the joints ``names`` only (parents listed before children).

        A kept joint hangs from its nearest kept ancestor; a joint with no kept ancestor becomes
        a root whose local transform is its world transform, so world positions and rotations of
        the kept joints are unchanged (e.g. drop ``joint_Root`` to make ``Hips`` the root). Where
        dropped joints sat in between, the local rotation and translation absorb theirs and so
        vary per frame; ``channels`` keeps each joint's own channels, with positions added to
        new roots.
        """
        names = list(names)
        lookup = {n: i for i, n in enumerate(self.names)}
        if any(n not in lookup for n in names) or len(set(names)) != len(names):
            raise KeyError(f"{self.source}: subset {names} must name distinct joints of {self.names}")
        old = np.array([lookup[n] for n in names], dtype=np.int64)
        new_of = {int(o): k for k, o in enumerate(old)}
        par = np.full(len(old), -1, dtype=np.int64)
        for k, o in enumerate(old):
            a = int(self.parents[o])
            while a >= 0 and a not in new_of:
                a = int(self.parents[a])
            par[k] = new_of.get(a, -1)
            if par[k] >= k:
                raise ValueError(f"{self.source}: list {names[par[k]]!r} before its descendant {names[k]!r}")
        grot, gpos = self.global_transforms()
        rot, trans = grot[:, old], gpos[:, old]
        kid = np.flatnonzero(par >= 0)
        inv = qinv(rot[:, par[kid]])
        rot[:, kid], trans[:, kid] = qmul(inv, rot[:, kid]), qrot(inv, trans[:, kid] - trans[:, par[kid]])
        rest = _rest_positions(self.parents, self.offsets)[old]
        offsets = rest - np.where(par[:, None] >= 0, rest[par], 0.0)
        channels = [tuple(self.channels[o]) if p >= 0 or any("position" in c.lower() for c in self.channels[o])
                    else ("Xposition", "Yposition", "Zposition") + tuple(self.channels[o]) for o, p in zip(old, par)]
        ends = {new_of[j]: v.copy() for j, v in self.end_sites.items() if j in new_of}
        return BvhMotion(self.source, names, par, offsets, channels, ends, self.frame_time, rot, trans)


def _depths(parents: np.ndarray) -> np.ndarray:
    depth = np.zeros(len(parents), dtype=np.int64)
    for j, p in enumerate(parents):
        if p >= j:
            raise ValueError(f"joint {j} has parent {p}: parents must be listed before their children")
        depth[j] = 0 if p < 0 else depth[p] + 1
    return depth


def _rest_positions(parents, offsets) -> np.ndarray:
    rest = np.array(offsets, dtype=np.float64)
    for j, p in enumerate(parents):
        if p >= 0:
            rest[j] += rest[p]
    return rest


def forward_kinematics(parents, rotations, translations) -> tuple[np.ndarray, np.ndarray]:
    """World rotations and positions from local ones; one vectorized step per tree depth."""
    parents = np.asarray(parents, dtype=np.int64)
    depth = _depths(parents)
    grot = np.empty(rotations.shape, dtype=np.float64)
    gpos = np.empty(translations.shape, dtype=np.float64)
    for d in range(int(depth.max(initial=0)) + 1):
        js = np.flatnonzero(depth == d)
        if d == 0:
            grot[:, js], gpos[:, js] = rotations[:, js], translations[:, js]
            continue
        ps = parents[js]
        pr = grot[:, ps]
        grot[:, js] = qmul(pr, rotations[:, js])
        gpos[:, js] = gpos[:, ps] + qrot(pr, translations[:, js])
    return grot, gpos


# ----------------------------------------------------------------------------- parsing

_CHANNELS = {f"{a}{k}": (k, "XYZ".index(a.upper())) for a in "xyz" for k in ("position", "rotation")}
_MOTION_RE = re.compile(rb"^[ \t]*MOTION[ \t]*\r?$", re.M | re.I)
_FRAMES_RE = re.compile(rb"[ \t]*Frames[ \t]*:[ \t]*(\S*)[ \t]*\r?$", re.I)
_FTIME_RE = re.compile(rb"[ \t]*Frame[ \t]+Time[ \t]*:[ \t]*(\S*)[ \t]*\r?$", re.I)


def _tokens(text: bytes) -> tuple[list[str], list[int]]:
    toks, lines = [], []
    for i, ln in enumerate(text.decode("utf-8", "replace").split("\n"), 1):
        parts = ln.split()
        toks += parts
        lines += [i] * len(parts)
    return toks, lines


@dataclass(frozen=True)
class _Layout:
    """The hierarchy and where each joint's channels sit in a motion row. Files with byte-identical
    headers share one (a data set has a few), so it is read-only."""
    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: dict
    width: int
    pos_index: tuple  # (joint, axis, column) index arrays of the position channels
    rot_groups: tuple  # (order, joints (G,), columns (G, k)) per distinct rotation order


_LAYOUTS: dict[bytes, _Layout] = {}


def _parse_hierarchy(header: bytes, src: str, motion_line: int | None) -> _Layout:
    toks, tline = _tokens(header)
    n = len(toks)

    def fail(msg, k):
        raise MotionFormatError(src, msg, tline[min(k, n - 1)] if n else 1)

    if not n or toks[0].upper() != "HIERARCHY":
        fail(f"expected 'HIERARCHY' to start the file, found {toks[0] if n else 'no text'!r}", 0)
    names, parents, offsets, channels, lines, ends = [], [], [], [], [], {}
    stack: list[tuple[int, bool, int]] = []  # (joint, inside its End Site, line of the '{')
    i, closed = 1, None
    while i < n and closed is None:
        tok, key = toks[i], toks[i].upper()
        site = key == "END" and i + 1 < n and toks[i + 1].upper() == "SITE"
        if key in ("ROOT", "JOINT") or site:
            k = i + 1 + site
            while k < n and toks[k] != "{" and tline[k] == tline[i]:
                k += 1
            if k >= n or toks[k] != "{":
                fail(f"expected '{{' after {' '.join(toks[i:k])!r}", k)
            name = " ".join(toks[i + 1 + site:k])
            if site:
                if not stack or stack[-1][1]:
                    fail("End Site outside of a joint", i)
                stack.append((stack[-1][0], True, tline[k]))
            elif key == "ROOT" and (stack or names):
                fail("a second ROOT: one skeleton per file is supported", i)
            elif key == "JOINT" and not stack:
                fail("JOINT outside of the ROOT's braces (unbalanced braces?)", i)
            elif not name or name in names:
                fail(f"expected a joint name after {tok}" if not name else
                     f"joint name {name!r} repeats the joint at line {lines[names.index(name)]}", i)
            else:
                parents.append(stack[-1][0] if stack else -1)
                names.append(name), offsets.append(None), channels.append(()), lines.append(tline[i])
                stack.append((len(names) - 1, False, tline[k]))
            i = k + 1
        elif key == "OFFSET":
            try:
                off = [float(t) for t in toks[i + 1:i + 4]]
            except ValueError:
                off = []
            if len(off) != 3 or not all(map(math.isfinite, off)) or tline[min(i + 3, n - 1)] != tline[i]:
                fail("OFFSET needs three finite numbers on its line", i)
            if not stack:
                fail("OFFSET outside of a joint", i)
            j, in_site, _ = stack[-1]
            if (ends.get(j) if in_site else offsets[j]) is not None:
                fail(f"a second OFFSET for {'the End Site of ' if in_site else ''}{names[j]!r}", i)
            if in_site:
                ends[j] = np.array(off)
            else:
                offsets[j] = off
            i += 4
        elif key == "CHANNELS":
            if not stack or stack[-1][1] or channels[stack[-1][0]]:
                fail("CHANNELS outside of a joint, or a second CHANNELS line", i)
            count = toks[i + 1] if i + 1 < n and tline[i + 1] == tline[i] else ""
            if not count.isdigit():
                fail(f"CHANNELS must be followed by the channel count, found {count or 'nothing'!r}", i)
            k = i + 2
            while k < n and toks[k].lower() in _CHANNELS:
                k += 1
            found = toks[i + 2:k]
            if len(found) != int(count):
                fail(f"CHANNELS declares {int(count)} channels but lists {len(found)}: {' '.join(found)}", i)
            if len({_CHANNELS[c.lower()] for c in found}) != len(found):
                fail(f"CHANNELS repeats a channel: {' '.join(found)}", i)
            channels[stack[-1][0]] = tuple(found)
            i = k
        elif tok == "}":
            if not stack:
                fail("unbalanced braces: '}' closes nothing", i)
            j, in_site, _ = stack.pop()
            if (ends.get(j) if in_site else offsets[j]) is None:
                fail(f"{'End Site of ' if in_site else 'joint '}{names[j]!r} has no OFFSET", i)
            closed = None if stack else i
            i += 1
        else:
            fail(f"unexpected {tok!r}: expected ROOT, JOINT, End Site, OFFSET, CHANNELS or '}}'", i)
    last = tline[-1] if n else 1
    if stack:
        j, in_site, opened = stack[-1]
        raise MotionFormatError(src, f"unbalanced braces: the '{{' of {'End Site of ' if in_site else 'joint '}"
                                f"{names[j]!r} (line {opened}) is not closed before "
                                f"{'MOTION' if motion_line else 'the end of the file'}", motion_line or last)
    if not names:
        raise MotionFormatError(src, "expected a ROOT joint after HIERARCHY", last)
    if i < n and toks[i] == "}":
        fail(f"unbalanced braces: '}}' after the hierarchy closed at line {tline[closed]}", i)
    if i < n or motion_line is None:
        found = repr(toks[i]) if i < n else "the end of the file"
        raise MotionFormatError(src, f"expected a 'MOTION' line after the hierarchy (closed at line "
                                f"{tline[closed]}), found {found}", tline[i] if i < n else last + 1)

    pos, groups, col = ([], [], []), {}, 0
    for j, chans in enumerate(channels):
        axes, cols = "", []
        for c in chans:
            kind, axis = _CHANNELS[c.lower()]
            if kind == "position":
                pos[0].append(j), pos[1].append(axis), pos[2].append(col)
            else:
                axes, cols = axes + "XYZ"[axis], cols + [col]
            col += 1
        if axes:
            groups.setdefault(axes, ([], []))
            groups[axes][0].append(j), groups[axes][1].append(cols)
    return _Layout(tuple(names), np.array(parents, dtype=np.int64), np.array(offsets, dtype=np.float64),
                   tuple(channels), ends, col, tuple(np.array(x, dtype=np.int64) for x in pos),
                   tuple((o, np.array(js), np.array(cs)) for o, (js, cs) in groups.items()))


def _layout(header: bytes, src: str, motion_line: int | None) -> _Layout:
    lay = _LAYOUTS.get(header)
    if lay is None:
        lay = _parse_hierarchy(header, src, motion_line)
        if len(_LAYOUTS) >= 64:
            _LAYOUTS.clear()
        _LAYOUTS[header] = lay
    return lay


def _next_line(data: bytes, pos: int, src: str, regex, expected: str) -> tuple[re.Match, int, int]:
    """Match the next non-blank line at or after ``pos``: (match, its line number, end offset)."""
    n = len(data)
    while pos < n:
        end = data.find(b"\n", pos)
        end = n if end < 0 else end + 1
        if data[pos:end].strip():
            break
        pos = end
    line = data.count(b"\n", 0, pos) + 1
    found = data[pos:end].strip()[:40] if pos < n else b""
    m = regex.match(data, pos, end) if pos < n else None
    if m is None:
        raise MotionFormatError(src, f"expected {expected}, found {found.decode('utf-8', 'replace') or 'nothing'!r}",
                                line)
    return m, line, end


def _bad_row(block: bytes, first_line: int, frames: int, width: int, src: str, frames_line: int, why):
    """Runs only after the vectorized parse failed: walk the rows to name the bad one."""
    rows, last = 0, first_line - 1
    for k, raw in enumerate(block.split(b"\n")):
        vals, line = raw.split(), first_line + k
        if not vals:
            continue
        if rows == frames:
            raise MotionFormatError(src, f"a row beyond the {frames} frames declared by 'Frames:' at line "
                                    f"{frames_line}", line)
        if len(vals) != width:
            raise MotionFormatError(src, f"expected {width} values (the CHANNELS total), found {len(vals)}", line)
        for c, v in enumerate(vals, 1):
            try:
                x = float(v) if b"_" not in v else None  # float() takes 1_0, numpy does not
            except ValueError:
                x = None
            if x is None or not math.isfinite(x):
                raise MotionFormatError(src, f"value {c} is {v.decode('utf-8', 'replace')!r}, expected a "
                                        f"{'finite ' if x is not None else ''}number", line)
        rows, last = rows + 1, line
    if rows < frames:
        raise MotionFormatError(src, f"the motion block ends after {rows} of the {frames} frames declared by "
                                f"'Frames:' at line {frames_line}; expected frame {rows + 1} here", last + 1)
    raise MotionFormatError(src, f"motion block could not be read: {why}", first_line)


def parse_bvh(data: bytes | str, source: str = "<bvh>") -> BvhMotion:
    """Parse BVH text: any rotation order per joint, position channels on any joint, End Sites,
    tabs and CRLF, scientific notation."""
    src = str(source)
    data = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    data = data[3:] if data.startswith(b"\xef\xbb\xbf") else data
    if not data or data.isspace():
        raise MotionFormatError(src, "empty file, expected BVH text starting with HIERARCHY", 1)
    m = _MOTION_RE.search(data)
    lay = _layout(data[:m.start()] if m else data, src, data.count(b"\n", 0, m.start()) + 1 if m else None)
    fm, frames_line, pos = _next_line(data, m.end(), src, _FRAMES_RE, "'Frames: <count>' after MOTION")
    if not fm.group(1).isdigit():
        raise MotionFormatError(src, f"field 'Frames': expected a whole number, found {fm.group(1).decode()!r}",
                                frames_line)
    frames = int(fm.group(1))
    tm, ft_line, pos = _next_line(data, pos, src, _FTIME_RE, "'Frame Time: <seconds>' after Frames")
    try:
        frame_time = float(tm.group(1))
    except ValueError:
        frame_time = math.nan
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise MotionFormatError(src, f"field 'Frame Time': expected a positive number of seconds, found "
                                f"{tm.group(1).decode()!r}", ft_line)

    block, err = data[pos:], None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns on an empty block; 'Frames:' decides
            arr = np.loadtxt(io.BytesIO(block), dtype=np.float64, comments=None, ndmin=2)
        if arr.size == 0 and not block.strip():
            arr = np.zeros((0 if lay.width else frames, lay.width))
    except ValueError as e:
        arr, err = None, e
    if arr is None or arr.shape != (frames, lay.width) or not np.isfinite(arr).all():
        _bad_row(block, ft_line + 1, frames, lay.width, src, frames_line, err)

    translations = np.repeat(lay.offsets[None], frames, axis=0)
    rotations = np.zeros((frames, len(lay.names), 4))
    rotations[..., 0] = 1.0
    pj, pa, pc = lay.pos_index
    translations[:, pj, pa] = arr[:, pc]
    for order, js, cols in lay.rot_groups:  # one conversion per distinct rotation order
        rotations[:, js] = euler_to_quat(arr[:, cols], order)
    return BvhMotion(src, list(lay.names), lay.parents.copy(), lay.offsets.copy(), list(lay.channels),
                     {k: v.copy() for k, v in lay.end_sites.items()}, frame_time, rotations, translations)


def read_bvh(path) -> BvhMotion:
    return parse_bvh(Path(path).read_bytes(), str(path))
