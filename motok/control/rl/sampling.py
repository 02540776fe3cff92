"""Which reference clips episodes start from: difficulty-weighted sampling (PHC's hard-negative
mining, PULSE's failure-weighted sampling), for an expert that must cover a whole dataset.

Every ``every`` iterations an evaluation plays every training clip from its first frame
(``motok.control.tasks.imitation``) and sets each clip's **failure** ``f_c = 1 - played_c / playable_c``
(0 for a clip played to its end, 1 for a fall at the first step; graded, so a clip lost near its
end weighs less than one lost at once). Start clips are then drawn with

    p_c = (1 - beta) * L_c / sum_k L_k  +  beta * L_c f_c / sum_k L_k f_k

with ``L_c`` the clip's usable length (the frames a start can be drawn from) and ``beta`` the
``hard_fraction``: a share ``1 - beta`` of starts keeps the length-proportional draw of plain
reference state initialisation (nothing learned is forgotten), a share ``beta`` goes to failed
clips in proportion to how much of them is failed. Before the first evaluation, or when every
clip succeeds, ``p_c = L_c / sum L``. Start frames stay uniform within the clip. The failures and
the iteration they were measured at are saved with the run, so resuming is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from motok.errors import UserError
from motok.ranges import In


@dataclass
class SamplingConfig:
    hard_fraction: In[float, "[0, 1]"] = 0.0  # beta; 0: plain length-proportional reference state initialisation
    every: In[int, ">= 0"] = 0  # iterations between difficulty evaluations (0: never)
    eval_batch: In[int, ">= 1"] = 256  # environments per evaluation chunk (clips of similar length together)

    def __post_init__(self):
        if not 0.0 <= self.hard_fraction <= 1.0:
            raise UserError(f"sampling.hard_fraction must be in [0, 1], not {self.hard_fraction}")


def clip_probabilities(usable: np.ndarray, failure: np.ndarray, hard_fraction: float) -> np.ndarray:
    """``p_c`` of the module docstring, ``(C,)`` summing to 1."""
    usable = np.asarray(usable, dtype=np.float64)
    base = usable / usable.sum()
    hard = usable * np.clip(failure, 0.0, 1.0)
    if hard_fraction == 0.0 or hard.sum() <= 0.0:
        return base
    return (1.0 - hard_fraction) * base + hard_fraction * hard / hard.sum()


def failures(per_clip: dict, names: list[str]) -> np.ndarray:
    """``f_c`` from an evaluation's per-clip results (``seconds`` played of ``clip_seconds``)."""
    out = np.zeros(len(names))
    for i, n in enumerate(names):
        r = per_clip[n]
        out[i] = 0.0 if r["success"] else 1.0 - min(r["seconds"] / max(r["clip_seconds"], 1e-9), 1.0)
    return out


class DifficultySampler:
    """The failures of the last difficulty evaluation and the start-clip probabilities they give."""

    def __init__(self, cfg: SamplingConfig, usable: np.ndarray):
        self.cfg, self.usable = cfg, np.asarray(usable)
        self.failure = np.zeros(len(usable))
        self.measured_at = -1  # iteration of the last evaluation (-1: none yet)

    @property
    def active(self) -> bool:
        return self.cfg.every > 0 and self.cfg.hard_fraction > 0.0

    def due(self, iteration: int) -> bool:
        return self.active and iteration % self.cfg.every == 0

    def probabilities(self) -> np.ndarray | None:
        """``None`` until a first evaluation: the task then keeps its own length-proportional draw."""
        if self.measured_at < 0:
            return None
        return clip_probabilities(self.usable, self.failure, self.cfg.hard_fraction)

    def update(self, failure: np.ndarray, iteration: int) -> dict[str, float]:
        self.failure, self.measured_at = np.asarray(failure, dtype=np.float64), int(iteration)
        p = self.probabilities()
        failed = self.failure > 0
        return {"hard_clips": int(failed.sum()), "hard_share": float(p[failed].sum()) if failed.any() else 0.0,
                "train_success": float(1.0 - failed.mean())}

    def state(self) -> dict:
        return {"failure": torch.from_numpy(self.failure.copy()), "measured_at": self.measured_at}

    def load(self, st: dict) -> None:
        self.failure = st["failure"].numpy().astype(np.float64)
        self.measured_at = int(st["measured_at"])
