"""Nearest-neighbour search of motion matching (:mod:`motok.eval.motion_matching`): squared
Euclidean distances (Eq. 8 in the normalised space), exact or through a faiss index.

**Exact** (:func:`nearest`, ``--exact``): torch blocks, memory-bounded whatever the sizes; the
reference the approximate search is measured against.

**Approximate** (:func:`build_index`, :func:`search_index`): a faiss ``IndexIVFFlat`` (inverted
lists over k-means cells, vectors stored uncompressed). ``nlist`` cells (:func:`ivf_cells`: 1,024 for a
set of 65,536 transitions or more), k-means of :data:`KMEANS_ITER` iterations on at most
:data:`TRAIN_PER_LIST` x nlist transitions drawn with a fixed seed; a query scans the
:data:`NPROBE` cells nearest to it. The neighbour it returns is then re-measured exactly, so a
distance is always a true distance to a real dataset transition, only perhaps not the nearest one.

**Groups** (leave-one-clip-out): a key of the query's own group is never its neighbour. The index
returns a query's :data:`GROUP_K` nearest keys and the first of another group is kept; a query
whose ``GROUP_K`` all belong to its own clip (slow motion: its own neighbouring frames come first)
is searched again exactly among the keys of the other groups. Importing this module costs numpy
only; torch and faiss are imported by the searches.
"""

from __future__ import annotations

import numpy as np

CANDIDATES = 4  # per query, re-measured exactly after the matrix-product search (see nearest)
BLOCK_BYTES = 128 << 20  # per block of distances: 2,048 queries x 16,384 keys in float32
QUERY_BLOCK = 2048
NLIST = 1024  # k-means cells of the IVF index for a large set (ivf_cells)
NPROBE = 16  # cells a query scans
TRAIN_PER_LIST = 64  # k-means training transitions per cell (faiss wants at least 39)
KMEANS_ITER = 10  # k-means iterations (faiss's default is 25; 10 loses no recall, measured)
GROUP_K = 32  # neighbours a grouped query looks through for one of another group
SEARCH_BLOCK = 65_536  # queries per faiss call: the normalised copy of a block is all that is held


# --------------------------------------------------------------------------- exact search

def nearest(queries, keys, *, query_groups=None, key_groups=None, candidates: int = CANDIDATES,
            block_bytes: int = BLOCK_BYTES, query_block: int = QUERY_BLOCK, advance=None):
    """Exact nearest neighbours: ``(squared distance (nq,), index (nq,))`` of every query row among
    the key rows, in blocks of ``query_block`` x ``block_bytes / (4 query_block)`` keys
    (memory-bounded whatever the sizes). With groups, a key of the query's own group is never
    its neighbour (leave-one-clip-out); a query with no eligible key gets ``inf`` and -1.

    Each block ranks keys by ``|k|^2 - 2 q.k`` (one matrix product, the query's own norm left
    out: it does not change the ranking) and keeps its ``candidates`` best; the survivors are
    then measured exactly as ``sum (q - k)^2``. The expansion loses digits when two rows are nearly
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
        exact = ((qb[:, None] - k[best_i]) ** 2).sum(-1).masked_fill_(torch.isinf(best_d), inf)
        d, j = exact.min(1)
        dist[a:a + len(qb)] = d
        index[a:a + len(qb)] = torch.where(torch.isinf(d), -1, best_i.gather(1, j[:, None])[:, 0])
        if advance is not None:
            advance(len(qb))
    return dist.numpy(), index.numpy()


def brute_force(queries, keys) -> tuple[np.ndarray, np.ndarray]:
    """The reference: each query against every key in float64, one query at a time; squared distances."""
    k = np.asarray(keys, np.float64)
    d, i = np.empty(len(queries)), np.empty(len(queries), dtype=np.int64)
    for r, row in enumerate(np.asarray(queries, np.float64)):
        e = ((k - row) ** 2).sum(1)
        i[r] = e.argmin()
        d[r] = e[i[r]]
    return d, i


def squared(queries: np.ndarray, keys: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``sum (q - k[index])^2`` per row, in float32 like the exact search (inf where index is -1)."""
    d = ((np.asarray(queries, np.float32) - keys[np.maximum(index, 0)]) ** 2).sum(1)
    return np.where(index < 0, np.inf, d).astype(np.float32)


# --------------------------------------------------------------------------- faiss

def ivf_cells(n: int) -> int:
    """IVF cells for ``n`` keys: :data:`NLIST`, fewer for a small set (each keeps 64 keys to train on)."""
    return int(max(1, min(NLIST, n // TRAIN_PER_LIST)))


def build_index(keys: np.ndarray, *, nlist: int | None = None, nprobe: int = NPROBE, seed: int = 0,
                threads: int | None = None):
    """A faiss ``IndexIVFFlat`` over ``keys`` (module docstring); ``nlist`` defaults to :func:`ivf_cells`,
    ``threads`` (OpenMP) to torch's thread count, so faiss takes no more cores than the rest of motok."""
    import faiss
    import torch

    faiss.omp_set_num_threads(int(threads or torch.get_num_threads()))
    x = np.ascontiguousarray(keys, dtype=np.float32)
    n, dim = x.shape
    nlist = ivf_cells(n) if nlist is None else int(nlist)
    index = faiss.IndexIVFFlat(faiss.IndexFlatL2(dim), dim, nlist)
    index.cp.niter, index.cp.seed = KMEANS_ITER, seed
    index.cp.max_points_per_centroid = TRAIN_PER_LIST  # faiss samples that many itself above it
    train = x if n <= TRAIN_PER_LIST * nlist else x[np.sort(np.random.default_rng(seed).choice(
        n, TRAIN_PER_LIST * nlist, replace=False))]
    index.train(train)
    index.add(x)
    index.nprobe = min(nprobe, nlist)
    return index


def search_index(index, keys: np.ndarray, queries: np.ndarray, *, query_groups=None, key_groups=None,
                 group_k: int = GROUP_K, advance=None) -> tuple[np.ndarray, np.ndarray]:
    """``(squared distance, index)`` of each query's neighbour found by ``index`` (built over
    ``keys``), re-measured exactly; with groups, leave-one-group-out (module docstring)."""
    q = np.ascontiguousarray(queries, dtype=np.float32)
    grouped = query_groups is not None
    k = max(1, min(group_k, len(keys))) if grouped else 1
    _, found = index.search(q, k)
    if not grouped:
        idx = found[:, 0]
    else:
        qg, kg = np.asarray(query_groups), np.asarray(key_groups)
        other = (found >= 0) & (kg[np.maximum(found, 0)] != qg[:, None])
        first = other.argmax(1)
        idx = np.where(other.any(1), found[np.arange(len(q)), first], -1)
        rest = np.flatnonzero(idx < 0)
        if len(rest):  # every one of the k was of the query's own clip: exact among the other clips
            idx[rest] = nearest(q[rest], keys, query_groups=qg[rest], key_groups=kg)[1]
    if advance is not None:
        advance(len(q))
    return squared(q, keys, idx), idx.astype(np.int64)
