"""The one place that maps ``QuantizerConfig.kind`` to a quantizer class.

Kinds: ``vq``, ``ema``, ``reset``, ``ema_reset`` (:mod:`motok.quantize.vq`: VQ-VAE / T2M-GPT
Sec. 3.1), ``rvq`` (:mod:`motok.quantize.rvq`: residual VQ, MoMask) and ``fsq``
(:mod:`motok.quantize.fsq`: Mentzer et al. 2023). No module of the package imports this one.
"""

from __future__ import annotations

from motok.quantize.base import Quantizer, QuantizerConfig
from motok.quantize.fsq import FSQuantizer
from motok.quantize.rvq import ResidualVQ
from motok.quantize.vq import INITS, VQ_KINDS, VectorQuantizer

KINDS = (*VQ_KINDS, "rvq", "fsq")


def validate(cfg: QuantizerConfig) -> None:
    """Raise ValueError naming every value of ``cfg`` that no quantizer accepts."""
    problems = []
    if cfg.kind not in KINDS:
        problems.append(f"kind {cfg.kind!r} is not one of {KINDS}")
    if cfg.kind == "rvq" and cfg.rvq_base not in VQ_KINDS:
        problems.append(f"rvq_base {cfg.rvq_base!r} is not one of {VQ_KINDS}")
    if cfg.kind != "rvq" and cfg.num_codebooks != 1:
        problems.append(f"num_codebooks={cfg.num_codebooks} needs kind 'rvq' (kind is {cfg.kind!r})")
    if cfg.codebook_size < 1 or cfg.dim < 1 or cfg.num_codebooks < 1 or cfg.reset_window < 1:
        problems.append("codebook_size, dim, num_codebooks and reset_window must be >= 1")
    if not 0.0 <= cfg.decay < 1.0 or cfg.eps < 0 or not 0.0 <= cfg.quantizer_dropout <= 1.0:
        problems.append("need 0 <= decay < 1, eps >= 0 and 0 <= quantizer_dropout <= 1")
    if cfg.init not in INITS:
        problems.append(f"init {cfg.init!r} is not one of {INITS}")
    elif cfg.kmeans_init and cfg.init not in ("uniform", "kmeans"):
        problems.append(f"kmeans_init=true contradicts init={cfg.init!r}; set init='kmeans' alone")
    if cfg.kind == "fsq" and (not cfg.fsq_levels or min(cfg.fsq_levels) < 2):
        problems.append(f"fsq_levels must be a non-empty list of integers >= 2, got {cfg.fsq_levels}")
    if problems:
        raise ValueError("bad QuantizerConfig: " + "; ".join(problems))


def build_quantizer(cfg: QuantizerConfig) -> Quantizer:
    """The quantizer of kind ``cfg.kind``, after :func:`validate`; draws its initial state
    from the global torch RNG."""
    validate(cfg)
    if cfg.kind == "rvq":
        return ResidualVQ(cfg)
    if cfg.kind == "fsq":
        return FSQuantizer(cfg)
    return VectorQuantizer(cfg)
