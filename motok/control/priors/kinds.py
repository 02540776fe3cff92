"""The five bottlenecks of the hybrid-latent paper's priors, and three from its future work (the
margin quantized by FSQ or group RVQ, and a margin split by body part), one capability row each:
what the model builds, what distillation weighs and logs, and what task learning chooses follow
from these rows, so a new kind is one row here (and a recipe), not a string test in every reader.

Importing this module is cheap (no torch): the command line lists the kinds from it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Kind:
    """What one prior kind has."""

    gaussian: bool  # posterior and prior are Gaussians (z sampled, KL(q || p)); else z is quantized
    prior_network: bool  # a prior f_theta(s) -> z_p; the hybrids quantize the margin z - sg(z_p)
    # How z (or the margin) is quantized, a name of model.QUANTIZERS: "vq" one codebook, "rvq" residual
    # codebooks decodable with the first M, "fsq" grouped finite scalar quantization, "grvq" group RVQ
    quantizer: str = "vq"
    commitment: bool = True  # the quantizer has a commitment loss (FSQ has none: its tanh bound keeps z in range)
    parts: bool = False  # the margin's groups are body parts (lower, upper), each read from its part's reference
    reg: float = 0.05  # alpha of Eq. 6 (the latent regulariser) when the recipe leaves it unset

    @property
    def quantized(self) -> bool:
        return not self.gaussian

    @property
    def residual(self) -> bool:
        """Several codebooks (or channel groups), decodable with the first M."""
        return self.quantized and self.quantizer != "vq"

    @property
    def margin(self) -> bool:
        """A quantized margin to a prior (the hybrids): L_mm pulls prior and posterior together."""
        return self.quantized and self.prior_network

    @property
    def losses(self) -> tuple[str, ...]:
        """The bottleneck's own terms of Eq. 6 that distillation logs."""
        if self.gaussian:
            return ("kl_loss",)
        return ("commit_loss",) * self.commitment + ("mm_loss",) * self.margin + ("part_loss",) * self.parts

    @property
    def schedule(self) -> str | None:
        """The ramped weight (``LossConfig`` field) of its loss: ``kl``, ``mm`` or none."""
        return "kl" if self.gaussian else "mm" if self.margin else None


KINDS = {
    "continuous": Kind(gaussian=True, prior_network=True, reg=0.005),  # PULSE-style, Eq. 1-2
    "discrete": Kind(gaussian=False, prior_network=False),  # NCP-style, one VQ codebook, Eq. 3-4
    "discrete+": Kind(gaussian=False, prior_network=False, quantizer="rvq"),  # residual VQ
    "hybrid": Kind(gaussian=False, prior_network=True, quantizer="rvq"),  # section 4.1, Algorithm 1
    "hybrid-vq": Kind(gaussian=False, prior_network=True),  # appendix A.1: one VQ codebook for the margin
    # The paper's future work (docs/control/priors.md): the margin by FSQ (Mentzer et al. 2023), by
    # group RVQ (HiFi-Codec), and split into a lower-body and an upper-body group under one z_p.
    "hybrid-fsq": Kind(gaussian=False, prior_network=True, quantizer="fsq", commitment=False),
    "hybrid-grvq": Kind(gaussian=False, prior_network=True, quantizer="grvq"),
    "hybrid-parts": Kind(gaussian=False, prior_network=True, quantizer="grvq", parts=True),
}
