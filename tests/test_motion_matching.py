"""Motion matching (motok.eval.motion_matching, motok.eval.nn_search, `motok eval motion-matching`):
the chunked exact search equals brute force and the faiss index equals it when exhaustive and
reaches the recall bar when not, Eq. 8 is the squared normalised distance, filtered transitions
stay out of the distance statistics, falls are counted, the state is where- and
heading-invariant, the threshold and coverage count as defined on hand-made examples, dataset
transitions are at distance 0 and noise moves them away."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.artifacts import Provenance
from motok.data.dataset import MotionFile, write_motion
from motok.eval.motion_matching import (Reference, derive_threshold, equal_size_coverage, falls, match, match_metrics,
                                        motion_matching, normaliser)
from motok.eval.nn_search import brute_force, build_index, nearest, search_index
from motok.eval.transitions import states, transitions

pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------- the search

def test_chunked_exact_search_equals_brute_force():
    rng = np.random.default_rng(0)
    keys, queries = rng.normal(size=(3000, 13)), rng.normal(size=(700, 13))
    want_d, want_i = brute_force(queries, keys)
    # small blocks: 11 query blocks x 12 key blocks, so every merge path runs
    d, i = nearest(queries, keys, query_block=64, block_bytes=4 * 64 * 256)
    assert np.array_equal(i, want_i) and np.allclose(d, want_d, atol=1e-5)
    assert np.array_equal(nearest(queries, keys)[1], want_i)  # default blocks: one key block


def test_identical_rows_are_at_exactly_zero_and_groups_exclude_their_own_rows():
    rng = np.random.default_rng(1)
    keys = rng.normal(size=(500, 8)) * 30 + 100  # large norms: where the expansion loses digits
    d, i = nearest(keys[:200], keys, query_block=50, block_bytes=4 * 50 * 128)
    assert np.array_equal(d, np.zeros(200)) and np.array_equal(i, np.arange(200))
    groups = np.arange(500) // 10  # 50 "clips" of 10 rows
    d, i = nearest(keys, keys, query_groups=groups, key_groups=groups, query_block=64, block_bytes=4 * 64 * 100)
    full = ((keys[:, None] - keys[None]) ** 2).sum(-1)  # squared: Eq. 8
    full[groups[:, None] == groups[None]] = np.inf
    assert np.array_equal(i, full.argmin(1)) and np.allclose(d, full.min(1), rtol=1e-5)
    assert (groups[i] != groups).all()
    one = np.zeros(5, dtype=int)  # a single group: no eligible neighbour
    d, i = nearest(keys[:5], keys[:5], query_groups=one, key_groups=one)
    assert np.isinf(d).all() and (i == -1).all()


@pytest.mark.parametrize("faiss_index", [False, True])
def test_threshold_on_a_small_example(faiss_index):
    # 1-D transitions in three clips: A = {0, 1}, B = {0.5, 3}, C = {10}. Leave-one-clip-out
    # nearest neighbours: 0 -> 0.5, 1 -> 0.5, 0.5 -> 0 or 1, 3 -> 1, 10 -> 3: distances
    # 0.5, 0.5, 0.5, 2, 7, squared (Eq. 8) 0.25, 0.25, 0.25, 4, 49.
    x = np.array([[0.0], [1.0], [0.5], [3.0], [10.0]], np.float32)
    groups = np.array([0, 0, 1, 1, 2])
    index = build_index(x, nlist=1, threads=1) if faiss_index else None
    # numpy's linear percentile of the five: 90 -> between the 4th (4) and 5th (49), 0.6 of the way
    for pct, want in ((50, 0.25), (75, 4.0), (100, 49.0), (90, 4 + 0.6 * 45)):
        t = derive_threshold(x, groups, percentile=pct, queries=100, index=index)
        assert t["value"] == pytest.approx(want) and t["queries"] == 5
    assert derive_threshold(x, groups, queries=100, index=index)["loco_mean"] == pytest.approx(53.75 / 5)
    sub = derive_threshold(x, groups, percentile=100, queries=3, seed=0, index=index)
    assert sub["queries"] == 3 and sub["value"] in (0.25, 4.0, 49.0)


def test_eq8_is_the_squared_distance_normalised_per_dimension():
    # two dimensions of very different spread: mean (2, 10), std (sqrt(8/3), sqrt(200/3))
    data = np.array([[0.0, 0.0], [2.0, 10.0], [4.0, 20.0]], np.float32)
    mean, std = normaliser(data)
    assert np.allclose(std ** 2, [8 / 3, 200 / 3])
    # (1, 10): to (2, 10) 1 / (8/3) = 0.375; to (0, 0) 0.375 + 100 / (200/3) = 1.875. (4, 14): to
    # (4, 20) 36 / (200/3) = 0.54, to (2, 10) 4 / (8/3) + 16 / (200/3) = 1.74: in raw units (2, 10)
    # is the nearer (|(2, 4)| < |(0, 6)|), in Eq. 8's the farther
    rows = np.array([[1.0, 10.0], [4.0, 14.0]], np.float32)
    for index in (None, build_index((data - mean) / std, nlist=1, threads=1)):
        ref = Reference("hand", None, (data - mean) / std, mean, std, None, {"value": 1.0}, index is None, index)
        d, i = match(ref, rows)
        assert i.tolist() == [1, 2] and d == pytest.approx([0.375, 0.54], rel=1e-5)


def test_filtered_transitions_stay_out_of_the_distance_statistics():
    data = np.array([[0.0], [1.0], [2.0], [3.0], [20.0]])
    gen = np.array([[0.1], [0.2], [2.9], [14.0]])
    d, i = nearest(gen, data)
    assert i.tolist() == [0, 0, 3, 4] and d == pytest.approx([0.01, 0.04, 0.01, 36.0], rel=1e-5)
    m = match_metrics(d, i, len(data), threshold=1.0)
    assert m["transitions"] == 4 and m["valid"] == 3 and m["filtered_rate"] == 0.25  # 14 is 6 (36) from the data
    assert m["coverage"] == 3 / 5  # 0, 3 and 20 are someone's nearest neighbour; 1 and 2 are not
    assert m["coverage_within_threshold"] == 2 / 5  # 20 only through the filtered transition
    # over the three valid ones: 0.06 / 3; with the filtered one it would be 36.06 / 4
    assert m["distance_mean"] == pytest.approx(0.02, rel=1e-5)
    assert m["distance_std"] == pytest.approx(np.sqrt(0.0006 / 3), rel=1e-4)
    assert m["distance_median"] == pytest.approx(0.01, rel=1e-5)
    none = match_metrics(d, i, len(data), threshold=0.001)
    assert none["filtered_rate"] == 1.0 and np.isnan(none["distance_mean"])


def _real_split(small_dataset):
    """The slice's transitions, normalised, as a reference (clips 0-15) and held-out queries (16-)."""
    from motok.eval.transitions import load_set

    ds = load_set(small_dataset)
    mean, std = normaliser(ds.x)
    x = (ds.x - mean) / std
    ref = ds.clip < 16
    return x[ref], ds.clip[ref], x[~ref]


def test_faiss_equals_exact_when_exhaustive_and_reaches_the_recall_bar_when_not(small_dataset):
    keys, groups, queries = _real_split(small_dataset)
    want_d, want_i = nearest(queries, keys)
    one_cell = build_index(keys, nlist=1, threads=1)  # one inverted list: every key is scanned
    d, i = search_index(one_cell, keys, queries)
    assert np.array_equal(i, want_i) and np.allclose(d, want_d, rtol=1e-5)
    # leave-one-clip-out through the index, 4 neighbours only: most queries see only their own
    # clip's frames among them and take the exact fallback; all must equal the exact answer
    gd, gi = search_index(one_cell, keys, keys, query_groups=groups, key_groups=groups, group_k=4)
    wd, wi = nearest(keys, keys, query_groups=groups, key_groups=groups)
    assert np.allclose(gd, wd, rtol=1e-5) and (groups[gi] != groups).all()
    # the default index (n / 64 cells, 16 probed) is approximate: recall by distance, ties counted
    ivf = build_index(keys, threads=1)
    assert ivf.nlist == len(keys) // 64 and ivf.nlist > ivf.nprobe
    d, i = search_index(ivf, keys, queries)
    assert (d >= want_d * (1 - 1e-5)).all()  # never nearer than the nearest: distances are re-measured
    assert np.mean(d <= want_d * (1 + 1e-5) + 1e-7) >= 0.95


def test_coverage_at_equal_size_subsamples_every_row_to_the_smallest():
    long, short = np.array([0, 1, 2, 3, 0, 1, 2, 3]), np.array([4, 4])
    n, cov = equal_size_coverage([long, short, np.array([], int)], num_data=5, seed=0)
    assert n == 2 and cov[1] == 1 / 5 and np.isnan(cov[2])
    assert cov[0] in (1 / 5, 2 / 5)  # two of the long row's matches: one or two distinct neighbours
    # unequal rows: the long row's plain coverage is 4/5, at equal size never more than 2/5
    spread = {equal_size_coverage([long, short], 5, seed)[1][0] for seed in range(20)}
    assert spread == {1 / 5, 2 / 5}


# ---------------------------------------------------------------------- the state

def test_the_state_does_not_depend_on_where_the_motion_is_or_which_way_it_faces(small_dataset):
    with MotionFile(small_dataset) as mf:
        j, sk, fps = mf.frames("joints", 0).astype(np.float64), mf.skeleton, mf.fps
    a = 2.0
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])  # about +Y
    moved = j @ rot.T + np.array([3.0, 0.0, -7.0])
    s, s2 = states(j, fps, sk), states(moved, fps, sk)
    assert s.shape == (len(j) - 1, 3 * 21 + 2) and np.allclose(s, s2, atol=1e-9)
    assert np.allclose(s[:, 0], j[1:, 0, 1])  # the root height
    assert np.allclose(np.linalg.norm(s[:, -4:-1], axis=1), np.linalg.norm(np.diff(j[:, 0], axis=0), axis=1) * fps)
    t = transitions(j, fps, sk)
    assert t.shape == (len(j) - 2, 2 * s.shape[1]) and np.array_equal(t[:, s.shape[1]:], s[1:])


# ---------------------------------------------------------------------- motion against data

def _noisy(small_dataset, out, sigma: float, seed: int = 0, labels=lambda i: {}):
    rng = np.random.default_rng(seed)
    with MotionFile(small_dataset) as mf:
        clips = [mf.clip(i) for i in range(len(mf))]
        sk, offsets, fps, legacy = mf.skeleton, mf.offsets, mf.fps, mf.legacy
    noisy = [replace(c, joints=c.joints + rng.normal(0, sigma, c.joints.shape).astype(np.float32), labels=labels(i))
             for i, c in enumerate(clips)]
    write_motion(out, "motion", Provenance(command="test", config={"sigma": sigma}), noisy, sk, offsets, fps, legacy)
    return out


def test_dataset_transitions_are_at_zero_and_noise_moves_them_away(small_dataset, tmp_path):
    paths = [small_dataset] + [_noisy(small_dataset, tmp_path / f"n{s}.h5", s) for s in (0.002, 0.01, 0.03)]
    rep = motion_matching(small_dataset, paths, queries=3000)
    own, *noisy = rep["rows"]
    n = rep["dataset"]["transitions"]
    assert rep["kind"] == "motion-matching" and rep["transition_dim"] == 130 and own["transitions"] == n
    assert own["distance_mean"] == 0.0 and own["filtered_rate"] == 0.0 and own["coverage"] > 0.999
    assert 0 < rep["threshold"]["value"] and rep["threshold"]["queries"] == 3000
    # the mean is over valid transitions only, at most the threshold; 1 and 3 cm leave none valid
    assert 0 < noisy[0]["distance_mean"] <= rep["threshold"]["value"]
    assert noisy[0]["filtered_rate"] < noisy[1]["filtered_rate"] <= noisy[2]["filtered_rate"]
    assert noisy[2]["filtered_rate"] > 0.5  # 3 cm of noise per joint and frame is nothing like the data
    jit = [own["jitter_m_s3"]] + [r["jitter_m_s3"] for r in noisy]
    acc = [own["acceleration_m_s2"]] + [r["acceleration_m_s2"] for r in noisy]
    assert jit == sorted(jit) and acc == sorted(acc) and own["jitter_m_s3"] == rep["dataset"]["jitter_m_s3"]
    assert sum(c["transitions"] for c in own["per_clip"].values()) == n


def test_eval_motion_matching_command(small_dataset, tmp_path):
    from motok.cli.main import app

    gen = _noisy(small_dataset, tmp_path / "gen.h5", 0.01)
    out_json, out_md = tmp_path / "r.json", tmp_path / "r.md"
    args = ["--quiet", "eval", "motion-matching", "-d", str(small_dataset), "--motions", str(gen),
            "--clips", "dataset-2_walk_normal_00*", "--threshold-queries", "500"]
    r = CliRunner().invoke(app, [*args, "-o", str(out_json), "-o", str(out_md), "--json"])
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    assert rep == json.loads(out_json.read_text()) and rep["dataset"]["clips"] == 9
    assert rep["provenance"]["config"]["queries"] == 500 and "| motion |" in out_md.read_text()
    row = rep["rows"][0]  # one row: its equal-size subset is all of it
    assert row["coverage_n"] == row["transitions"] and row["coverage_equal_n"] == row["coverage"]
    r = CliRunner().invoke(app, [*args, "--threshold", "1.5"])
    assert r.exit_code == 0 and "threshold 1.500" in r.stdout, r.output
    # the held-out split as one more row, searched exactly: the slice has 3 test clips
    held = ["--quiet", "eval", "motion-matching", "-d", str(small_dataset), "--motions", str(gen), "--split", "train",
            "--threshold", "20", "--exact", "--json"]
    r = CliRunner().invoke(app, [*held, "--heldout", "test"])
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    gen_row, test_row = rep["rows"]
    assert test_row["motion"] == "test split (held out)" and test_row["clips"] == 3 and "fell" not in test_row
    assert rep["search"] == {"search": "exact (torch blocks)"} and "coverage_equal_n" not in test_row
    assert gen_row["coverage_n"] == gen_row["transitions"]  # the held-out row sets no common size
    r = CliRunner().invoke(app, [*held, "--heldout", "train"])
    assert r.exit_code != 0 and "--heldout train" in r.output and "part of the reference" in r.output


def test_falls_are_counted_apart_from_the_generation_labels(small_dataset, tmp_path):
    # what `control generate` writes: fell_at_s on every clip, None for an episode that stayed up
    gen = _noisy(small_dataset, tmp_path / "gen.h5", 0.002,
                 labels=lambda i: {"fell_at_s": 2.5 if i in (3, 7, 11) else None, "prior": "hybrid"})
    assert falls(gen) == {"episodes": 24, "fell": 3, "fall_rate": 3 / 24}
    assert falls(small_dataset) == {}  # no generation: no fall column
    rep = motion_matching(small_dataset, [gen, small_dataset], threshold=50.0)
    fell, own = rep["rows"]
    assert (fell["episodes"], fell["fell"], fell["fall_rate"]) == (24, 3, 0.125) and "fell" not in own
    assert rep["search"]["search"] == "faiss IndexIVFFlat" and own["distance_mean"] == 0.0
