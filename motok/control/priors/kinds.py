"""The five bottlenecks of the hybrid-latent paper's priors, one capability row each: what the
model builds, what distillation weighs and logs, and what task learning chooses follow from these
rows, so a new kind is one row here (and a recipe), not a string test in every reader.

Importing this module is cheap (no torch): the command line lists the kinds from it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Kind:
    """What one prior kind has."""

    gaussian: bool  # posterior and prior are Gaussians (z sampled, KL(q || p)); else z is quantized
    prior_network: bool  # a prior f_theta(s) -> z_p; the hybrids quantize the margin z - sg(z_p)
    residual: bool = False  # residual VQ: several codebooks, decodable with the first M
    reg: float = 0.05  # alpha of Eq. 6 (the latent regulariser) when the recipe leaves it unset

    @property
    def quantized(self) -> bool:
        return not self.gaussian

    @property
    def margin(self) -> bool:
        """A quantized margin to a prior (the hybrids): L_mm pulls prior and posterior together."""
        return self.quantized and self.prior_network

    @property
    def losses(self) -> tuple[str, ...]:
        """The bottleneck's own terms of Eq. 6 that distillation logs."""
        return ("kl_loss",) if self.gaussian else ("commit_loss", "mm_loss") if self.margin else ("commit_loss",)

    @property
    def schedule(self) -> str | None:
        """The ramped weight (``LossConfig`` field) of its loss: ``kl``, ``mm`` or none."""
        return "kl" if self.gaussian else "mm" if self.margin else None


KINDS = {
    "continuous": Kind(gaussian=True, prior_network=True, reg=0.005),  # PULSE-style, Eq. 1-2
    "discrete": Kind(gaussian=False, prior_network=False),  # NCP-style, one VQ codebook, Eq. 3-4
    "discrete+": Kind(gaussian=False, prior_network=False, residual=True),  # residual VQ
    "hybrid": Kind(gaussian=False, prior_network=True, residual=True),  # section 4.1, Algorithm 1
    "hybrid-vq": Kind(gaussian=False, prior_network=True),  # appendix A.1: one VQ codebook for the margin
}
