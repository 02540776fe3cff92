"""Motion matching of generated motion against a dataset (hybrid-latent paper section 6.2,
Tables 1 and 4, Eq. 8): how far each generated transition is from the nearest transition of the
data, how many are too far to be data-like (filtered), how many episodes fell, and how much of
the data is reached (coverage).

**The state** ``s_t`` and transitions ``(s_t, s_{t+1})``: :mod:`motok.eval.transitions`.

**Eq. 8.** Every dimension is normalised by the mean and std of the dataset's transitions; the
distance of a generated transition ``x`` is the *squared* distance to its nearest dataset
transition ``y`` in that space, ``sum_i ((x_i - y_i) / std_i)^2``. The search
(:mod:`motok.eval.nn_search`) is a faiss IVF index by default, exact with ``exact=True``.

**Filtered.** A generated transition is filtered when its distance is above a threshold taken
from the dataset itself: the ``percentile`` (99) of the leave-one-clip-out nearest-neighbour
distances of ``queries`` dataset transitions (20,000 drawn with a fixed seed, each searched among
the transitions of every other clip). The filtered rate is the share of all generated
transitions; the distance's mean and std are over the valid (unfiltered) transitions only.

**Falls.** ``motok control generate`` ends an episode at its last upright frame, so no transition
after a fall is matched; each row counts its episodes and those that fell (``fell_at_s`` labels).

**Coverage.** The share of dataset transitions that are the nearest neighbour of at least one
generated transition; ``coverage_within_threshold`` counts only matches of valid transitions.
``coverage_equal_n`` measures every row on the same number: a fixed-seed random subset of each
row's transitions as large as the smallest row (``coverage_n``).

Also jitter (m/s^3, :mod:`motok.eval.physical`) and acceleration (m/s^2: mean norm of the second
difference of every joint times fps^2), at each artifact's own frame rate.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from motok.errors import UserError
from motok.eval.nn_search import (GROUP_K, KMEANS_ITER, NPROBE, SEARCH_BLOCK, build_index, ivf_cells, nearest,
                                  search_index)
from motok.eval.transitions import TransitionSet, load_set, transitions

KIND = "motion-matching"
PERCENTILE = 99.0
THRESHOLD_QUERIES = 20_000
STD_FLOOR = 1e-6


# --------------------------------------------------------------------------- the metrics

def normaliser(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std per dimension of the dataset's transitions (std floored at STD_FLOOR)."""
    x64 = np.asarray(x, np.float64)
    return x64.mean(0).astype(np.float32), np.maximum(x64.std(0), STD_FLOOR).astype(np.float32)


def derive_threshold(x: np.ndarray, groups: np.ndarray, percentile: float = PERCENTILE,
                     queries: int = THRESHOLD_QUERIES, seed: int = 0, index=None, advance=None) -> dict:
    """The filter threshold: the ``percentile`` of the leave-one-clip-out nearest-neighbour
    squared distances of ``queries`` dataset transitions (all of them when there are fewer),
    drawn with ``seed``, in the normalised space ``x``; searched exactly, or through the faiss
    ``index`` over ``x`` when given."""
    if len(np.unique(groups)) < 2:
        raise UserError("the threshold needs a dataset of at least two clips (leave-one-clip-out)")
    n = len(x)
    sel = np.arange(n) if queries >= n else np.sort(np.random.default_rng(seed).choice(n, queries, replace=False))
    if index is None:
        d, _ = nearest(x[sel], x, query_groups=groups[sel], key_groups=groups, advance=advance)
    else:
        d, _ = search_index(index, x, x[sel], query_groups=groups[sel], key_groups=groups, advance=advance)
    return {"value": float(np.percentile(d, percentile)), "percentile": percentile, "queries": int(len(sel)),
            "seed": seed, "loco_mean": float(d.mean()), "loco_median": float(np.median(d)),
            "definition": f"{percentile:g}th percentile of the leave-one-clip-out nearest-neighbour squared "
                          f"distances (Eq. 8) of {len(sel)} dataset transitions"}


def match_metrics(dist: np.ndarray, index: np.ndarray, num_data: int, threshold: float) -> dict:
    """Eq. 8 summary of generated transitions whose nearest dataset transitions (among
    ``num_data``) are ``index`` at squared distance ``dist``: mean, std and median over the valid
    transitions (``dist <= threshold``) only, the filtered rate over all, and coverage."""
    valid = dist <= threshold
    v, nan = dist[valid].astype(np.float64), float("nan")
    return {"transitions": int(len(dist)), "valid": int(valid.sum()),
            "distance_mean": float(v.mean()) if len(v) else nan, "distance_std": float(v.std()) if len(v) else nan,
            "distance_median": float(np.median(v)) if len(v) else nan,
            "filtered_rate": float(1.0 - valid.mean()) if len(dist) else nan,
            "coverage": float(len(np.unique(index)) / num_data),
            "coverage_within_threshold": float(len(np.unique(index[valid])) / num_data)}


def equal_size_coverage(indices: list[np.ndarray], num_data: int, seed: int = 0) -> tuple[int, list[float]]:
    """Coverage of each row's nearest-neighbour ``indices`` on a random subset (fixed ``seed``) of
    as many transitions as the smallest non-empty row has, so that rows compare at equal size."""
    n = min((len(i) for i in indices if len(i)), default=0)
    rng = np.random.default_rng(seed)
    return n, [float(len(np.unique(rng.choice(i, n, replace=False))) / num_data) if len(i) else float("nan")
               for i in indices]


def falls(path) -> dict:
    """``{"episodes", "fell", "fall_rate"}`` of a ``motok control generate`` output, from the
    ``fell_at_s`` label of each clip; empty for motion whose clips carry no such label."""
    from motok.artifacts import read_strings
    from motok.data.dataset import MotionFile

    with MotionFile(path) as mf:
        c = mf.h5["clips"]
        labels = [json.loads(s or "{}") for s in read_strings(c["labels"])] if "labels" in c else []
    if not any("fell_at_s" in x for x in labels):
        return {}
    fell = sum(x.get("fell_at_s") is not None for x in labels)
    return {"episodes": len(labels), "fell": fell, "fall_rate": fell / len(labels)}


@dataclass
class Reference:
    """The dataset side of Eq. 8: its transitions normalised by their own mean and std, the
    filter threshold (derived, or given) and, unless ``exact``, the faiss index over them."""

    data: str
    dataset: TransitionSet
    x: np.ndarray  # (n, D) normalised
    mean: np.ndarray
    std: np.ndarray
    skeleton: object
    threshold: dict
    exact: bool = True
    index: object = field(default=None, repr=False)

    @property
    def fps(self) -> float:
        return self.dataset.fps

    def search(self, xn: np.ndarray, advance=None) -> tuple[np.ndarray, np.ndarray]:
        """Squared distance to, and index of, the nearest reference transition of normalised rows."""
        if self.exact:
            return nearest(xn, self.x, advance=advance)
        return search_index(self.index, self.x, xn, advance=advance)

    def search_settings(self) -> dict:
        if self.exact:
            return {"search": "exact (torch blocks)"}
        return {"search": "faiss IndexIVFFlat", "nlist": int(self.index.nlist), "nprobe": int(self.index.nprobe),
                "kmeans_iterations": KMEANS_ITER, "group_k": GROUP_K}


def reference(data, names: list[str] | None = None, *, threshold: float | None = None,
              percentile: float = PERCENTILE, queries: int = THRESHOLD_QUERIES, seed: int = 0,
              exact: bool = True, bar=None) -> Reference:
    """The clips ``names`` (all by default) of the motion-dataset ``data`` as the reference of
    Eq. 8, with the threshold of the module docstring unless ``threshold`` is given; ``exact``
    False builds the faiss index (:mod:`motok.eval.nn_search`) and searches through it, the
    threshold's too; ``bar``: a progress bar to advance."""
    from motok.data.dataset import MotionFile

    with MotionFile(data) as mf:
        skeleton = mf.skeleton
    ds = load_set(data, names)
    mean, std = normaliser(ds.x)
    xd = (ds.x - mean) / std
    index = None if exact else build_index(xd, nlist=ivf_cells(len(xd)), nprobe=NPROBE, seed=seed)
    if threshold is None:
        task = bar.add_task("threshold (leave-one-clip-out)", total=min(queries, len(xd))) if bar else None
        thr = derive_threshold(xd, ds.clip, percentile, queries, seed, index=index,
                               advance=(lambda n: bar.advance(task, n)) if bar else None)
    else:
        thr = {"value": float(threshold), "definition": "given (--threshold)"}
    return Reference(str(data), ds, xd, mean, std, skeleton, thr, exact, index)


def match(ref: Reference, rows: np.ndarray, advance=None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8 for raw transitions ``rows``: squared distance to, and index of, the nearest
    reference transition; normalised a block at a time, so only one block's copy is held."""
    d, i = np.empty(len(rows), np.float32), np.empty(len(rows), np.int64)
    for a in range(0, len(rows), SEARCH_BLOCK):
        d[a:a + SEARCH_BLOCK], i[a:a + SEARCH_BLOCK] = ref.search((rows[a:a + SEARCH_BLOCK] - ref.mean) / ref.std,
                                                                  advance=advance)
    return d, i


def no_transitions(threshold: float = float("nan")) -> dict:
    """What :func:`match_joints` reports for motion without a single transition."""
    nan = float("nan")
    return {"transitions": 0, "segments": 0, "distance_mean": nan, "distance_std": nan, "distance_median": nan,
            "filtered_rate": nan, "threshold": threshold}


def match_joints(ref: Reference, segments, fps: float) -> dict:
    """:func:`match_metrics` of the transitions of joint segments ``(T, J, 3)`` (the dataset's
    frame, at ``fps``; resampled to the reference's rate), with their count; NaN metrics when
    no segment has the 3 frames a transition needs. For motion that is no artifact, such as the
    steps a navigation policy spends at its target."""
    from motok.features.resample import resample_positions

    rows = []
    for j in segments:
        j = np.asarray(j, np.float64)
        if abs(fps - ref.fps) > 1e-6 and len(j) > 1:
            j = resample_positions(j, fps, ref.fps)
        t = transitions(j, ref.fps, ref.skeleton)
        if len(t):
            rows.append(t.astype(np.float32))
    if not rows:
        return no_transitions(ref.threshold["value"])
    d, i = match(ref, np.concatenate(rows))
    return {**match_metrics(d, i, len(ref.x), ref.threshold["value"]), "segments": len(rows),
            "threshold": ref.threshold["value"]}


def _row(ref: Reference, g: TransitionSet, label: str, bar) -> tuple[dict, np.ndarray]:
    """One row of the table: ``g``'s transitions matched against ``ref``."""
    thr = ref.threshold["value"]
    task = bar.add_task(f"match {label}", total=len(g.x))
    t1 = time.perf_counter()
    d, i = match(ref, g.x, advance=lambda n: bar.advance(task, n))
    dt = time.perf_counter() - t1
    row = {"motion": label, "clips": len(g.names), **match_metrics(d, i, len(ref.x), thr),
           "jitter_m_s3": g.jitter_m_s3, "acceleration_m_s2": g.acceleration_m_s2, "search_s": round(dt, 2),
           "transitions_per_s": float(len(d) / max(dt, 1e-9))}
    row["per_clip"] = {}
    for c, n in enumerate(g.names):
        dc = d[g.clip == c]
        ok = dc <= thr
        row["per_clip"][n] = {"transitions": int(len(dc)), "filtered_rate": float(1.0 - ok.mean()),
                              "distance_mean": float(dc[ok].mean()) if ok.any() else float("nan")}
    return row, i


def motion_matching(data, motions, *, clips: str | None = None, split: str | None = None,
                    heldout: str | None = None, threshold: float | None = None, percentile: float = PERCENTILE,
                    queries: int = THRESHOLD_QUERIES, seed: int = 0, exact: bool = False) -> dict:
    """Tables 1 and 4 for each motion artifact in ``motions`` against the clips of ``data`` (all,
    or ``split`` / the ``clips`` glob); ``threshold`` skips its derivation; ``heldout``: a split of
    ``data`` matched as one more row (its filtered rate checks the threshold on clips the reference
    lacks); ``exact``: exact search instead of the faiss index. One row per artifact."""
    from motok.artifacts import Provenance, command_line, hash_inputs
    from motok.data.dataset import MotionFile, select_clips
    from motok.progress import make_progress

    t0 = time.perf_counter()
    names = select_clips(data, clips, split) if clips or split else None
    held = select_clips(data, None, heldout) if heldout else None
    if held is not None and names is not None and set(held) & set(names):
        raise UserError(f"--heldout {heldout}: its clips are part of the reference (--split/--clips); "
                        "expected a split the reference does not contain")
    with MotionFile(data) as mf:
        skeleton, fps = mf.skeleton, mf.fps
    gens = [(load_set(p, fps=fps, skeleton=skeleton), str(p), falls(p)) for p in motions]  # a wrong file fails now
    if held is not None:
        gens.append((load_set(data, held), f"{heldout} split (held out)", {}))
    with make_progress("transitions") as bar:
        ref = reference(data, names, threshold=threshold, percentile=percentile, queries=queries, seed=seed,
                        exact=exact, bar=bar)
        ds = ref.dataset
        out = {"kind": KIND, "schema_version": 2, "data": str(data), "clips": clips, "split": split,
               "heldout": heldout,
               "state": "(s_t, s_{t+1}); s = root height, root-relative joints in the heading frame, root velocity "
                        "in the heading frame, yaw rate (backward differences); each dimension normalised by the "
                        "dataset's transitions",
               "distance": "Eq. 8: squared distance to the nearest dataset transition in the normalised space; "
                           "mean and std over the valid (unfiltered) transitions",
               "transition_dim": int(ref.x.shape[1]), "fps": ref.fps,
               "dataset": {"clips": len(ds.names), "transitions": int(len(ref.x)), "jitter_m_s3": ds.jitter_m_s3,
                           "acceleration_m_s2": ds.acceleration_m_s2}, "threshold": ref.threshold,
               "search": ref.search_settings()}
        rows, found = [], []
        for g, label, fell in gens:
            row, i = _row(ref, g, label, bar)
            rows.append({**row, **fell})
            found.append(i)
    if held is not None:  # data, not generation: it sets no common size for the generated rows
        found = found[:-1]
    n, cov = equal_size_coverage(found, len(ref.x), seed)
    for row, c in zip(rows, cov):
        row["coverage_equal_n"], row["coverage_n"] = c, n
    out["rows"] = rows
    out["seconds"] = round(time.perf_counter() - t0, 2)
    out["provenance"] = json.loads(Provenance(command=command_line(), config={
        "clips": clips, "split": split, "heldout": heldout, "threshold": threshold, "percentile": percentile,
        "queries": queries, "seed": seed, **ref.search_settings()}, inputs=hash_inputs([data, *motions])).to_json())
    return out


def save(rep: dict, paths) -> None:
    """The whole report to each ``.json`` path, the table (:func:`markdown`) to each ``.md``."""
    from motok.atomic import atomic_path, write_json

    for p in map(Path, paths):
        if p.suffix.lower() == ".json":
            write_json(p, rep)
        else:
            with atomic_path(p) as tmp:
                from motok.marks import MD_MARK  # how motok knows its own report again
                tmp.write_text(MD_MARK + "\n" + markdown(rep))


COLUMNS = (("transitions", "transitions", "{:d}"), ("distance_mean", "distance ↓", "{:.3f}"),
           ("distance_std", "± std", "{:.3f}"), ("filtered_rate", "filtered ↓", "{:.2%}"),
           ("fell", "fell", "{:d}"), ("fall_rate", "fell %", "{:.1%}"), ("coverage", "coverage ↑", "{:.1%}"),
           ("coverage_within_threshold", "coverage ≤ thr ↑", "{:.1%}"),
           ("coverage_equal_n", "coverage, equal n ↑", "{:.1%}"), ("jitter_m_s3", "jitter m/s³", "{:.1f}"),
           ("acceleration_m_s2", "accel. m/s²", "{:.2f}"))


def cells(row: dict) -> list[str]:
    """One row's :data:`COLUMNS` as text; a column the row lacks (the dataset's own row has no
    distance or coverage, motion that is no generation no falls) is blank."""
    return [f.format(row[k]) if k in row else "" for k, _, f in COLUMNS]


def markdown(rep: dict) -> str:
    """The rows as a Markdown table, with the dataset's own jitter and acceleration and the threshold."""
    head = "| motion | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for r in rep["rows"]:
        lines.append(f"| {r['motion']} | " + " | ".join(cells(r)) + " |")
    lines.append(f"| dataset ({rep['data']}) | " + " | ".join(cells(rep["dataset"])) + " |")
    t, n = rep["threshold"], rep["rows"][0].get("coverage_n", 0) if rep["rows"] else 0
    return "\n".join(lines) + (f"\n\nThreshold {t['value']:.3f}: {t['definition']}. Distance: mean and std "
                                f"of the valid transitions. Coverage at equal n: {n} transitions of each row, "
                                f"drawn at random. Search: {rep['search']['search']}.\n")
