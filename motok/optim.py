"""The optimizer settings and learning-rate schedule every trainer shares: AdamW with a
linear warm-up, then a step decay by ``gamma`` at each milestone (T2M-GPT Sec. 4.1)."""

from __future__ import annotations

from dataclasses import dataclass, field

from motok.ranges import In


@dataclass
class OptimConfig:
    lr: In[float, "> 0"] = 2e-4  # AdamW's peak learning rate, reached at the end of the warm-up
    betas: In[list[float], "[0, 1)"] = field(default_factory=lambda: [0.9, 0.99])  # AdamW (beta1, beta2)
    weight_decay: In[float, ">= 0"] = 0.0  # AdamW's decoupled decay (the GPT spares biases and norms)
    warmup: In[int, ">= 0"] = 200  # linear warm-up iterations
    milestones: In[list[int], ">= 0"] = field(default_factory=list)  # absolute iterations where lr *= gamma
    gamma: In[float, "> 0"] = 0.05  # lr factor at each milestone (T2M-GPT: 0.05)
    grad_clip: In[float, ">= 0"] = 0.0  # global gradient-norm clip (0 = off)


def lr_factor(it: int, cfg: OptimConfig) -> float:
    """Linear warm-up over ``warmup`` iterations, then x gamma at each milestone."""
    if it < cfg.warmup:
        return (it + 1) / (cfg.warmup + 1)
    return cfg.gamma ** sum(it >= m for m in cfg.milestones)


def optimizer_step(loss, params, opt, sched, grad_clip: float) -> None:
    """One update of a trainer on these settings: the gradients of ``loss``, their norm clipped to
    ``grad_clip`` (0: not clipped), the optimiser's step, then the schedule's."""
    import torch  # here: configs import this module, and loading a config needs no torch

    opt.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(params, grad_clip)
    opt.step()
    sched.step()
