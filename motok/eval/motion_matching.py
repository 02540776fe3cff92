"""Motion matching of generated motion against a dataset (hybrid-latent paper section 6.2,
Table 1, Eq. 8): how far each generated transition is from the nearest transition of the data,
how many are too far to be data-like (filtered), and how much of the data is reached (coverage).

**The state** ``s_t`` and transitions ``(s_t, s_{t+1})``: :mod:`motok.eval.transitions`.

**Eq. 8.** Every dimension is normalised by the mean and std of the dataset's transitions; the
distance of a generated transition is the Euclidean distance to its nearest dataset transition
in that space (exact search: :func:`nearest`).

**Filtered.** A generated transition is filtered when it is farther than a threshold taken from
the dataset itself: the ``percentile`` (95) of the leave-one-clip-out nearest-neighbour distances
of dataset transitions (``queries`` of them, 20,000 drawn with a fixed seed, each searched among
the transitions of every other clip). By construction 5 % of the dataset's own transitions are
that far from the rest of the data; a generator with a higher filtered rate makes transitions
the data does not have.

**Coverage.** The share of dataset transitions that are the nearest neighbour of at least one
generated transition; ``coverage_within_threshold`` counts only matches of transitions that are not
filtered. Coverage grows with the number of generated transitions, and generations that fall stop
early, so ``coverage_equal_n`` measures every row on the same number: a fixed-seed random subset of
each row's transitions as large as the smallest row (``coverage_n``).

Also jitter (m/s^3, :mod:`motok.eval.physical`) and acceleration (m/s^2: mean norm of the second
difference of every joint times fps^2), at each artifact's own frame rate. Importing this
module costs numpy only; torch is imported by the search.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from motok.errors import UserError
from motok.eval.transitions import TransitionSet, load_set, transitions

KIND = "motion-matching"
PERCENTILE = 95.0
THRESHOLD_QUERIES = 20_000
CANDIDATES = 4  # per query, re-measured exactly after the matrix-product search (see nearest)
BLOCK_BYTES = 128 << 20  # per block of distances: 2,048 queries x 16,384 keys in float32
QUERY_BLOCK = 2048
STD_FLOOR = 1e-6


# --------------------------------------------------------------------------- exact search

def nearest(queries, keys, *, query_groups=None, key_groups=None, candidates: int = CANDIDATES,
            block_bytes: int = BLOCK_BYTES, query_block: int = QUERY_BLOCK, advance=None):
    """Exact nearest neighbours: ``(distance (nq,), index (nq,))`` of every query row among the
    key rows (Euclidean), in blocks of ``query_block`` x ``block_bytes / (4 query_block)`` keys
    (memory-bounded whatever the sizes). With groups, a key of the query's own group is never
    its neighbour (leave-one-clip-out); a query with no eligible key gets ``inf`` and -1.

    Each block ranks keys by ``|k|^2 - 2 q.k`` (one matrix product, the query's own norm left
    out: it does not change the ranking) and keeps its ``candidates`` best; the survivors are
    then measured exactly as ``||q - k||``. The expansion loses digits when two rows are nearly
    equal, so ranking by it alone could return a neighbour 1e-3 away instead of an identical row
    at 0; the re-measurement makes identical rows come out at exactly 0."""
    import torch

    q = torch.as_tensor(np.asarray(queries, np.float32))
    k = torch.as_tensor(np.asarray(keys, np.float32))
    nq, nk = len(q), len(k)
    if q.shape[1:] != k.shape[1:]:
        raise ValueError(f"queries have {q.shape[1:]} columns, keys {k.shape[1:]}")
    grouped = query_groups is not None
    if grouped:
        qg, kg = torch.as_tensor(np.asarray(query_groups)), torch.as_tensor(np.asarray(key_groups))
    kn = (k * k).sum(1)
    bk = max(1, block_bytes // (4 * query_block))
    c = max(1, min(candidates, nk))
    dist, index = torch.empty(nq), torch.empty(nq, dtype=torch.long)
    inf = float("inf")
    for a in range(0, nq, query_block):
        qb = q[a:a + query_block]
        best_d = torch.full((len(qb), c), inf)
        best_i = torch.zeros((len(qb), c), dtype=torch.long)
        for b in range(0, nk, bk):
            d2 = torch.addmm(kn[b:b + bk][None], qb, k[b:b + bk].T, alpha=-2.0)
            if grouped:
                d2.masked_fill_(qg[a:a + query_block, None] == kg[None, b:b + bk], inf)
            cd, ci = d2.topk(min(c, d2.shape[1]), dim=1, largest=False)
            md, mi = torch.cat([best_d, cd], 1), torch.cat([best_i, ci + b], 1)
            best_d, sel = md.topk(c, dim=1, largest=False)
            best_i = mi.gather(1, sel)
        exact = (qb[:, None] - k[best_i]).norm(dim=-1).masked_fill_(torch.isinf(best_d), inf)
        d, j = exact.min(1)
        dist[a:a + len(qb)] = d
        index[a:a + len(qb)] = torch.where(torch.isinf(d), -1, best_i.gather(1, j[:, None])[:, 0])
        if advance is not None:
            advance(len(qb))
    return dist.numpy(), index.numpy()


def brute_force(queries, keys) -> tuple[np.ndarray, np.ndarray]:
    """The reference: each query against every key in float64, one query at a time."""
    k = np.asarray(keys, np.float64)
    d, i = np.empty(len(queries)), np.empty(len(queries), dtype=np.int64)
    for r, row in enumerate(np.asarray(queries, np.float64)):
        e = np.sqrt(((k - row) ** 2).sum(1))
        i[r] = e.argmin()
        d[r] = e[i[r]]
    return d, i


# --------------------------------------------------------------------------- the metrics

def normaliser(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std per dimension of the dataset's transitions (std floored at STD_FLOOR)."""
    x64 = np.asarray(x, np.float64)
    return x64.mean(0).astype(np.float32), np.maximum(x64.std(0), STD_FLOOR).astype(np.float32)


def derive_threshold(x: np.ndarray, groups: np.ndarray, percentile: float = PERCENTILE,
                     queries: int = THRESHOLD_QUERIES, seed: int = 0, advance=None) -> dict:
    """The filter threshold: the ``percentile`` of the leave-one-clip-out nearest-neighbour
    distances of ``queries`` dataset transitions (all of them when there are fewer), drawn with
    ``seed``, in the normalised space ``x``."""
    if len(np.unique(groups)) < 2:
        raise UserError("the threshold needs a dataset of at least two clips (leave-one-clip-out)")
    n = len(x)
    sel = np.arange(n) if queries >= n else np.sort(np.random.default_rng(seed).choice(n, queries, replace=False))
    d, _ = nearest(x[sel], x, query_groups=groups[sel], key_groups=groups, advance=advance)
    return {"value": float(np.percentile(d, percentile)), "percentile": percentile, "queries": int(len(sel)),
            "seed": seed, "loco_mean": float(d.mean()), "loco_median": float(np.median(d)),
            "definition": f"{percentile:g}th percentile of the leave-one-clip-out nearest-neighbour distances of "
                          f"{len(sel)} dataset transitions"}


def match_metrics(dist: np.ndarray, index: np.ndarray, num_data: int, threshold: float) -> dict:
    """Distance summary, filtered rate and coverage of generated transitions whose nearest
    dataset transitions (among ``num_data``) are ``index`` at ``dist``."""
    kept = dist <= threshold
    return {"transitions": int(len(dist)), "distance_mean": float(dist.mean()),
            "distance_median": float(np.median(dist)), "distance_p95": float(np.percentile(dist, 95)),
            "filtered_rate": float(1.0 - kept.mean()),
            "coverage": float(len(np.unique(index)) / num_data),
            "coverage_within_threshold": float(len(np.unique(index[kept])) / num_data)}


def equal_size_coverage(indices: list[np.ndarray], num_data: int, seed: int = 0) -> tuple[int, list[float]]:
    """Coverage of each row's nearest-neighbour ``indices`` on a random subset (fixed ``seed``) of
    as many transitions as the smallest non-empty row has, so that rows compare at equal size."""
    n = min((len(i) for i in indices if len(i)), default=0)
    rng = np.random.default_rng(seed)
    return n, [float(len(np.unique(rng.choice(i, n, replace=False))) / num_data) if len(i) else float("nan")
               for i in indices]


@dataclass
class Reference:
    """The dataset side of Eq. 8: its transitions normalised by their own mean and std, and the
    filter threshold (derived, or given)."""

    data: str
    dataset: TransitionSet
    x: np.ndarray  # (n, D) normalised
    mean: np.ndarray
    std: np.ndarray
    skeleton: object
    threshold: dict

    @property
    def fps(self) -> float:
        return self.dataset.fps


def reference(data, names: list[str] | None = None, *, threshold: float | None = None,
              percentile: float = PERCENTILE, queries: int = THRESHOLD_QUERIES, seed: int = 0,
              bar=None) -> Reference:
    """The clips ``names`` (all by default) of the motion-dataset ``data`` as the reference of
    Eq. 8, with the threshold of the module docstring unless ``threshold`` is given; ``bar``: a
    progress bar to advance."""
    from motok.data.dataset import MotionFile

    with MotionFile(data) as mf:
        skeleton = mf.skeleton
    ds = load_set(data, names)
    mean, std = normaliser(ds.x)
    xd = (ds.x - mean) / std
    if threshold is None:
        task = bar.add_task("threshold (leave-one-clip-out)", total=min(queries, len(xd))) if bar else None
        thr = derive_threshold(xd, ds.clip, percentile, queries, seed,
                               advance=(lambda n: bar.advance(task, n)) if bar else None)
    else:
        thr = {"value": float(threshold), "definition": "given (--threshold)"}
    return Reference(str(data), ds, xd, mean, std, skeleton, thr)


def match(ref: Reference, rows: np.ndarray, advance=None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8 for raw transitions ``rows``: distance to, and index of, the nearest reference transition."""
    return nearest((rows - ref.mean) / ref.std, ref.x, advance=advance)


def no_transitions(threshold: float = float("nan")) -> dict:
    """What :func:`match_joints` reports for motion without a single transition."""
    nan = float("nan")
    return {"transitions": 0, "segments": 0, "distance_mean": nan, "distance_median": nan, "filtered_rate": nan,
            "threshold": threshold}


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


def motion_matching(data, motions, *, clips: str | None = None, split: str | None = None,
                    threshold: float | None = None, percentile: float = PERCENTILE,
                    queries: int = THRESHOLD_QUERIES, seed: int = 0) -> dict:
    """Table 1 for each motion artifact in ``motions`` against the clips of ``data`` (all, or
    ``split`` / the ``clips`` glob); ``threshold`` skips its derivation. One row per artifact."""
    from motok.artifacts import Provenance, command_line, hash_inputs
    from motok.data.dataset import MotionFile, select_clips
    from motok.progress import make_progress

    t0 = time.perf_counter()
    names = select_clips(data, clips, split) if clips or split else None
    with MotionFile(data) as mf:
        skeleton, fps = mf.skeleton, mf.fps
    gens = [load_set(p, fps=fps, skeleton=skeleton) for p in motions]  # a wrong file fails before the search
    with make_progress("transitions") as bar:
        ref = reference(data, names, threshold=threshold, percentile=percentile, queries=queries, seed=seed,
                        bar=bar)
        ds, xd, thr = ref.dataset, ref.x, ref.threshold["value"]
        out = {"kind": KIND, "schema_version": 1, "data": str(data), "clips": clips, "split": split,
               "state": "(s_t, s_{t+1}); s = root height, root-relative joints in the heading frame, root velocity "
                        "in the heading frame, yaw rate (backward differences); each dimension normalised by the "
                        "dataset's transitions", "transition_dim": int(xd.shape[1]), "fps": ref.fps,
               "dataset": {"clips": len(ds.names), "transitions": int(len(xd)), "jitter_m_s3": ds.jitter_m_s3,
                           "acceleration_m_s2": ds.acceleration_m_s2}, "threshold": ref.threshold}
        rows, found = [], []
        for g in gens:
            task = bar.add_task(f"match {g.path}", total=len(g.x))
            t1 = time.perf_counter()
            d, i = match(ref, g.x, advance=lambda n, t=task: bar.advance(t, n))
            dt = time.perf_counter() - t1
            row = {"motion": g.path, "clips": len(g.names), **match_metrics(d, i, len(xd), thr),
                   "jitter_m_s3": g.jitter_m_s3, "acceleration_m_s2": g.acceleration_m_s2,
                   "search_s": round(dt, 2), "pairs_per_s": float(len(d) * len(xd) / max(dt, 1e-9))}
            row["per_clip"] = {n: {"transitions": int((g.clip == c).sum()),
                                   "distance_mean": float(d[g.clip == c].mean()),
                                   "filtered_rate": float((d[g.clip == c] > thr).mean())}
                               for c, n in enumerate(g.names)}
            rows.append(row)
            found.append(i)
    n, cov = equal_size_coverage(found, len(xd), seed)
    for row, c in zip(rows, cov):
        row["coverage_equal_n"], row["coverage_n"] = c, n
    out["rows"] = rows
    out["seconds"] = round(time.perf_counter() - t0, 2)
    out["provenance"] = json.loads(Provenance(command=command_line(), config={
        "clips": clips, "split": split, "threshold": threshold, "percentile": percentile, "queries": queries,
        "seed": seed, "candidates": CANDIDATES}, inputs=hash_inputs([data, *motions])).to_json())
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
           ("filtered_rate", "filtered ↓", "{:.1%}"), ("coverage", "coverage ↑", "{:.1%}"),
           ("coverage_within_threshold", "coverage ≤ thr ↑", "{:.1%}"),
           ("coverage_equal_n", "coverage, equal n ↑", "{:.1%}"), ("jitter_m_s3", "jitter m/s³", "{:.1f}"),
           ("acceleration_m_s2", "accel. m/s²", "{:.2f}"))


def cells(row: dict) -> list[str]:
    """One row's :data:`COLUMNS` as text; a column the row lacks (the dataset's own row has no
    distance or coverage) is blank."""
    return [f.format(row[k]) if k in row else "" for k, _, f in COLUMNS]


def markdown(rep: dict) -> str:
    """The rows as a Markdown table, with the dataset's own jitter and acceleration and the threshold."""
    head = "| motion | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for r in rep["rows"]:
        lines.append(f"| {r['motion']} | " + " | ".join(cells(r)) + " |")
    lines.append(f"| dataset ({rep['data']}) | " + " | ".join(cells(rep["dataset"])) + " |")
    t, n = rep["threshold"], rep["rows"][0]["coverage_n"] if rep["rows"] else 0
    return "\n".join(lines) + (f"\n\nThreshold {t['value']:.3f}: {t['definition']}. Coverage at equal n: "
                                f"{n} transitions of each row, drawn at random.\n")
