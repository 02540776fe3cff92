"""The text-to-motion metric suite of Guo et al. (CVPR 2022, "Generating Diverse and Natural 3D
Human Motions from Text", Sec. 5) as T2M-GPT (Zhang et al. 2023, Table 1) reports it, plus the
reconstruction errors of a tokenizer.

All functions take embeddings from the co-embedding evaluator (:mod:`motok.eval.evaluator`):
``(N, d)`` arrays of text or motion vectors, row ``i`` of the text array describing row ``i``
of the motion array.

- R-precision top-k: shuffled batches of 32 pairs (the remainder is dropped, as the reference
  loader's ``drop_last``); within a batch each caption ranks the 32 motions by Euclidean
  distance; a hit when its own motion is among the k nearest.
- MM-Dist: mean Euclidean distance between a caption and its own motion (same batches).
- FID: Frechet distance between Gaussian fits of two embedding sets.
- Diversity: mean distance between 300 random pairs of one set.
- MModality: mean distance between pairs of samples generated for the same caption.
- Every metric is repeated (20 times) and reported as mean and 95% confidence interval
  ``1.96 * std / sqrt(repeats)``.

The reconstruction errors at the end (:func:`mpjpe`, :func:`velocity_error`,
:func:`acceleration_error`) are the one implementation every stage uses (tokenizer eval,
``eval recon``, control eval). Importing this module costs numpy only (scipy is imported by the
FID functions when called), so any stage can use it without pulling in the evaluator.
"""

from __future__ import annotations

import warnings

import numpy as np

# The reconstruction metrics are the kinematics' joint-trajectory errors, named here with the others.
from motok.features.kinematics import acceleration_error, mpjpe, velocity_error  # noqa: F401

R_PRECISION_BATCH = 32
DIVERSITY_TIMES = 300
MM_PAIRS = 10


def euclidean_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(N, d), (M, d) -> (N, M)`` Euclidean distances through one matrix product."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    # The expansion cancels catastrophically for near-identical rows and can dip below zero.
    return np.sqrt(np.maximum(sq, 0.0))


# --------------------------------------------------------------------------- R-precision, MM-Dist

def r_precision_hits(text: np.ndarray, motion: np.ndarray, top_k: int = 3) -> np.ndarray:
    """One batch: ``(top_k,)`` number of captions whose motion is among their k nearest."""
    d = euclidean_distances(text, motion)
    own = np.diag(d)[:, None]
    # Rank of the true motion = how many other motions are at least as close: a tie counts
    # against it, so a collapsed evaluator (all embeddings equal) scores 0, not 1.
    rank = (d <= own).sum(1) - 1
    return np.array([(rank < k).sum() for k in range(1, top_k + 1)], dtype=np.int64)


def r_precision(text: np.ndarray, motion: np.ndarray, rng: np.random.Generator,
                batch: int = R_PRECISION_BATCH, top_k: int = 3) -> tuple[np.ndarray, float]:
    """Shuffled batches of ``batch`` pairs -> (R-precision top-1..k, MM-Dist) over the kept pairs.

    With fewer than ``batch`` pairs, one batch of all of them is used (chance is then 1/N).
    """
    n = len(text)
    if n != len(motion):
        raise ValueError(f"r_precision: {n} captions but {len(motion)} motions")
    if n < 2:
        raise ValueError("r_precision needs at least 2 caption-motion pairs")
    order = rng.permutation(n)
    size = min(batch, n)
    hits = np.zeros(top_k, dtype=np.int64)
    dist, kept = 0.0, 0
    for s in range(0, n - size + 1, size):
        sel = order[s:s + size]
        hits += r_precision_hits(text[sel], motion[sel], top_k)
        dist += float(np.linalg.norm(text[sel] - motion[sel], axis=1).sum())
        kept += size
    return hits / kept, dist / kept


def mm_dist(text: np.ndarray, motion: np.ndarray) -> float:
    """Mean distance between each caption and its own motion."""
    return float(np.linalg.norm(np.asarray(text) - np.asarray(motion), axis=1).mean())


# --------------------------------------------------------------------------- FID

def gaussian_fit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, np.float64)
    return x.mean(0), np.cov(x, rowvar=False)


def frechet_distance(mu1, sigma1, mu2, sigma2, eps: float = 1e-6) -> float:
    """``||mu1 - mu2||^2 + Tr(S1 + S2 - 2 (S1 S2)^(1/2))`` (Dowson and Landau 1982).

    ``sqrtm`` of a product of two PSD matrices is real in exact arithmetic; round-off leaves a
    tiny imaginary part, which is dropped. A singular product (fewer samples than dimensions)
    gets ``eps`` added to both diagonals first, as in the reference implementation.
    """
    from scipy import linalg

    mu1, mu2 = np.atleast_1d(mu1), np.atleast_1d(mu2)
    s1, s2 = np.atleast_2d(sigma1), np.atleast_2d(sigma2)
    if mu1.shape != mu2.shape or s1.shape != s2.shape:
        raise ValueError(f"frechet_distance: shapes differ ({mu1.shape} vs {mu2.shape})")
    diff = mu1 - mu2
    with warnings.catch_warnings():
        # scipy warns when the product is singular; the finite check below handles it.
        warnings.simplefilter("ignore")
        covmean = linalg.sqrtm(s1 @ s2)
        if not np.isfinite(covmean).all():
            off = np.eye(len(s1)) * eps
            covmean = linalg.sqrtm((s1 + off) @ (s2 + off))
    if np.iscomplexobj(covmean):
        imag = np.abs(np.diagonal(covmean).imag).max()
        scale = max(1.0, np.abs(np.diagonal(covmean).real).max())
        if imag > 1e-3 * scale:
            raise ValueError(f"frechet_distance: sqrtm has an imaginary part of {imag:.3g}, beyond round-off")
        covmean = covmean.real
    # Round-off can also make a tiny negative result for identical sets.
    return max(0.0, float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * np.trace(covmean)))


def fid(x: np.ndarray, y: np.ndarray) -> float:
    """FID between two embedding sets ``(N, d)`` and ``(M, d)``."""
    return frechet_distance(*gaussian_fit(x), *gaussian_fit(y))


def fid_gaussians_closed_form(mu1, cov1, mu2, cov2) -> float:
    """Closed form for commuting covariances (e.g. diagonal): the sqrtm of the product is the
    product of the square roots; used to check :func:`frechet_distance`."""
    from scipy import linalg

    r1, r2 = linalg.sqrtm(cov1).real, linalg.sqrtm(cov2).real
    d = np.asarray(mu1) - np.asarray(mu2)
    return float(d @ d + np.trace(cov1) + np.trace(cov2) - 2.0 * np.trace(r1 @ r2))


# --------------------------------------------------------------------------- Diversity, MModality

def diversity(x: np.ndarray, rng: np.random.Generator, times: int = DIVERSITY_TIMES) -> float:
    """Mean distance between ``times`` pairs: two independent draws of ``times`` distinct rows.

    With ``times >= N`` (small sets) it falls back to ``N - 1`` pairs.
    """
    x = np.asarray(x, np.float64)
    n = len(x)
    if n < 2:
        raise ValueError("diversity needs at least 2 embeddings")
    t = min(times, n - 1)
    a = rng.choice(n, t, replace=False)
    b = rng.choice(n, t, replace=False)
    return float(np.linalg.norm(x[a] - x[b], axis=1).mean())


def multimodality(groups: list[np.ndarray], rng: np.random.Generator, pairs: int = MM_PAIRS,
                  resample_captions: bool = False) -> float:
    """Mean distance between ``pairs`` pairs of samples within each caption's group.

    ``groups``: one ``(k_i, d)`` array per caption, ``k_i >= 2`` samples generated for it. Pairs
    are two distinct samples (the reference code draws both ends independently and can pair a
    sample with itself, which biases the value down by about 1/k); with ``k_i`` samples a group
    gives ``min(pairs, k_i (k_i - 1) / 2)`` distinct pairs.

    ``resample_captions``: the groups are drawn with replacement first (a bootstrap over
    captions). The reference draws new captions and new samples in every repeat; samples made once
    and re-paired would give a confidence interval of the pair draw alone, too narrow by the
    spread between captions.
    """
    if resample_captions:
        groups = [groups[i] for i in rng.integers(len(groups), size=len(groups))]
    dists = []
    for g in groups:
        g = np.asarray(g, np.float64)
        k = len(g)
        if k < 2:
            continue
        all_pairs = np.array([(i, j) for i in range(k) for j in range(i + 1, k)])
        sel = all_pairs[rng.choice(len(all_pairs), min(pairs, len(all_pairs)), replace=False)]
        dists.append(np.linalg.norm(g[sel[:, 0]] - g[sel[:, 1]], axis=1).mean())
    if not dists:
        raise ValueError("multimodality needs at least one caption with 2 or more samples")
    return float(np.mean(dists))


# --------------------------------------------------------------------------- repeats

def mean_ci(values, z: float = 1.96) -> tuple[float, float]:
    """Mean and 95% confidence half-width ``z * std / sqrt(n)`` (population std, as numpy's default
    and the reference evaluation)."""
    v = np.asarray(values, np.float64)
    return float(v.mean()), float(z * v.std() / np.sqrt(len(v)))
