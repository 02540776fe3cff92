"""Quantizers shared by the stages: continuous latents to discrete codes and back.

The motion tokenizer quantizes encoder outputs ``(B, D, T)``; latent priors of the physics
stage quantize one latent per step, ``(B, D)``. Every quantizer takes both layouts (see
:class:`motok.quantize.base.Quantizer` for the shapes).

Modules, each importing only those above it (the package itself imports nothing, so loading
one module never loads the rest):

- :mod:`motok.quantize.base`: :class:`QuantizerConfig`, :class:`QuantizeOutput`, the
  :class:`Quantizer` base class, the straight-through estimator, the float32 region, the
  row layout and the collectives every kind shares.
- :mod:`motok.quantize.vq`: :class:`VectorQuantizer`, kinds ``vq``, ``ema``, ``reset``,
  ``ema_reset`` (VQ-VAE / T2M-GPT), and how codebooks start (``QuantizerConfig.init``:
  :data:`~motok.quantize.vq.INITS`, :func:`~motok.quantize.vq.init_method`).
- :mod:`motok.quantize.rvq`: :class:`ResidualVQ`, kind ``rvq`` (residual VQ, MoMask).
- :mod:`motok.quantize.fsq`: :class:`FSQuantizer`, kind ``fsq`` (Mentzer et al. 2023).
- :mod:`motok.quantize.registry`: :data:`KINDS`, :func:`validate`, :func:`build_quantizer`.
"""
