"""The T2M-GPT motion VQ-VAE (Zhang et al. 2023, Sec. 3.1 and appendix F): a 1D convolutional
encoder that downsamples time by ``2**down_t``, a quantizer (:mod:`motok.quantize`),
and a mirrored decoder with nearest-neighbour upsampling; and its training loss (Eq. 2-3).

Shapes follow the motion artifacts: features are ``(B, T, D)`` with ``D = 12J - 1``; the
convolutions see ``(B, D, T)``; the latent is ``(B, C, T / 2**down_t)``; indices are
``(B, T / 2**down_t, N)`` for ``N`` codebooks. The model owns the dataset's mean/std as buffers,
so a bundle alone maps raw features to tokens and back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from motok.checkpoint import load_model, register_kind
from motok.config import from_dict
from motok.errors import MotokError
from motok.features.humanml3d import feature_slices
from motok.optim import OptimConfig
from motok.quantize.base import QuantizerConfig
from motok.quantize.registry import build_quantizer
from motok.ranges import In

ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU, "gelu": nn.GELU}


@dataclass
class ModelConfig:
    """Encoder/decoder shape. The code dimension is ``quantizer.dim`` (one source of truth)."""
    width: In[int, ">= 1"] = 128  # 512 in the paper; recipes/tokenizer/paper.yaml
    down_t: In[int, ">= 0"] = 2  # number of stride-2 stages: temporal rate 2**down_t
    depth: In[int, ">= 1"] = 3  # residual blocks per stage
    dilation_growth: In[int, ">= 1"] = 3  # dilations growth**k, applied largest first: (9, 3, 1)
    activation: str = "relu"  # relu (T2M-GPT) | silu | gelu: the encoder's, decoder's and residual blocks' nonlinearity


class ResBlock(nn.Module):
    """act -> dilated conv k3 -> act -> conv k1, plus the identity (T2M-GPT appendix F)."""

    def __init__(self, width: int, dilation: int, activation: str):
        super().__init__()
        self.net = nn.Sequential(
            ACTIVATIONS[activation](),
            nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation),
            ACTIVATIONS[activation](),
            nn.Conv1d(width, width, 1),
        )

    def forward(self, x):
        return x + self.net(x)


def res_stack(width: int, depth: int, growth: int, activation: str) -> nn.Sequential:
    # Largest dilation first in encoder and decoder alike, as in the official Resnet1D default.
    dilations = [growth ** k for k in reversed(range(depth))]
    return nn.Sequential(*[ResBlock(width, d, activation) for d in dilations])


class Encoder(nn.Module):
    """Conv k3 + act, ``down_t`` x (conv k4 stride 2 + residual stack), conv k3 to the code dim."""

    def __init__(self, in_dim: int, code_dim: int, cfg: ModelConfig):
        super().__init__()
        w, act = cfg.width, cfg.activation
        layers: list[nn.Module] = [nn.Conv1d(in_dim, w, 3, padding=1), ACTIVATIONS[act]()]
        for _ in range(cfg.down_t):
            # kernel 4, stride 2, padding 1 halves an even length exactly
            layers += [nn.Conv1d(w, w, 4, stride=2, padding=1), res_stack(w, cfg.depth, cfg.dilation_growth, act)]
        layers.append(nn.Conv1d(w, code_dim, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, x):
        return self.net(x)


class Decoder(nn.Module):
    """Mirror of :class:`Encoder`: residual stack, nearest x2 upsampling, conv k3, per stage."""

    def __init__(self, out_dim: int, code_dim: int, cfg: ModelConfig):
        super().__init__()
        w, act = cfg.width, cfg.activation
        layers: list[nn.Module] = [nn.Conv1d(code_dim, w, 3, padding=1), ACTIVATIONS[act]()]
        for _ in range(cfg.down_t):
            layers += [res_stack(w, cfg.depth, cfg.dilation_growth, act),
                       nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv1d(w, w, 3, padding=1)]
        layers += [nn.Conv1d(w, w, 3, padding=1), ACTIVATIONS[act](), nn.Conv1d(w, out_dim, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, z):
        return self.net(z)


@dataclass
class LossConfig:
    alpha_vel: In[float, ">= 0"] = 0.5  # weight of the velocity term (paper: 0.5)
    vel_block: str = "ric"  # "ric": root-relative joint positions (official block) | "all": every feature
    vel_diff: bool = True  # frame-to-frame difference as in Eq. 3; false reproduces the official code
    beta_commit: In[float, ">= 0"] = 0.02  # commitment weight beta; multiplied by quantizer.beta (default 1)
    codebook: In[float, ">= 0"] = 1.0  # weight of the codebook term ||sg(Z) - Z_q||^2 (Eq. 2); zero for EMA kinds


@dataclass
class VQVAEOutput:
    recon: torch.Tensor  # (B, T, D) normalized features
    indices: torch.Tensor  # (B, T / rate, N)
    losses: dict
    stats: dict


class VQVAE(nn.Module):
    """Encoder -> quantizer -> decoder on normalized features (T2M-GPT Eq. 1-3).

    ``forward`` and ``reconstruct`` take normalized features; ``encode_features`` and
    ``decode_features`` work on raw features and (de)normalize with the stored statistics.
    """

    def __init__(self, feature_dim: int, model: ModelConfig, quantizer: QuantizerConfig):
        super().__init__()
        if model.activation not in ACTIVATIONS:
            raise ValueError(f"model.activation {model.activation!r}: choose from {sorted(ACTIVATIONS)}")
        if model.down_t < 0 or model.depth < 1:
            raise ValueError("model.down_t must be >= 0 and model.depth >= 1")
        self.feature_dim = feature_dim
        self.rate = 2 ** model.down_t
        self.encoder = Encoder(feature_dim, quantizer.dim, model)
        self.quantizer = build_quantizer(quantizer)
        self.decoder = Decoder(feature_dim, quantizer.dim, model)
        self.register_buffer("mean", torch.zeros(feature_dim))
        self.register_buffer("std", torch.ones(feature_dim))

    @property
    def num_codebooks(self) -> int:
        return int(self.quantizer.num_codebooks)

    def set_stats(self, mean, std) -> None:
        self.mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.std.copy_(torch.as_tensor(std, dtype=torch.float32))

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.std + self.mean

    def crop(self, x: torch.Tensor) -> torch.Tensor:
        """Drop the trailing ``T mod rate`` frames: one token covers exactly ``rate`` frames."""
        return x[:, : x.shape[1] // self.rate * self.rate]

    def forward(self, x: torch.Tensor, num_codebooks: int | None = None) -> VQVAEOutput:
        x = self.crop(x)
        z = self.encoder(x.transpose(1, 2))
        q = self.quantizer(z, num_codebooks=num_codebooks)
        recon = self.decoder(q.z_q).transpose(1, 2)
        return VQVAEOutput(recon, q.indices, q.losses, q.stats)

    @torch.no_grad()
    def encode(self, x: torch.Tensor, num_codebooks: int | None = None) -> torch.Tensor:
        """Normalized ``(B, T, D)`` -> indices ``(B, T // rate, N)``."""
        z = self.encoder(self.crop(x).transpose(1, 2))
        return self.quantizer.encode(z, num_codebooks=num_codebooks)

    @torch.no_grad()
    def decode(self, indices: torch.Tensor, num_codebooks: int | None = None) -> torch.Tensor:
        """Indices ``(B, L, N)`` -> normalized ``(B, L * rate, D)``; entries -1 (dropped) are ignored."""
        return self.decoder(self.quantizer.decode(indices, num_codebooks=num_codebooks)).transpose(1, 2)

    @torch.no_grad()
    def encode_features(self, feats: torch.Tensor, num_codebooks: int | None = None) -> torch.Tensor:
        return self.encode(self.normalize(feats), num_codebooks)

    @torch.no_grad()
    def decode_features(self, indices: torch.Tensor, num_codebooks: int | None = None) -> torch.Tensor:
        return self.denormalize(self.decode(indices, num_codebooks))


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def vqvae_loss(recon: torch.Tensor, target: torch.Tensor, losses: dict, cfg: LossConfig,
               num_joints: int, beta_scale: float = 1.0) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """T2M-GPT Eq. 2-3 with the official smooth-L1; returns the total and its detached parts.

    ``SL1(X, X_re) + alpha SL1(V(X), V(X_re)) + beta ||Z - sg(Z_q)||^2 + w ||sg(Z) - Z_q||^2``: ``V`` is
    the frame-to-frame difference (``vel_diff``) of the joint-position block (``vel_block=ric``)
    or of every feature (``all``); the codebook term exists only for gradient-learned codebooks.
    """
    target = target[:, : recon.shape[1]]
    rec = F.smooth_l1_loss(recon, target)
    if cfg.vel_block == "ric":
        sl = feature_slices(num_joints)["ric"]
        a, b = recon[..., sl], target[..., sl]
    elif cfg.vel_block == "all":
        a, b = recon, target
    else:
        raise ValueError(f"loss.vel_block {cfg.vel_block!r}: choose ric or all")
    if cfg.vel_diff:
        a, b = a[:, 1:] - a[:, :-1], b[:, 1:] - b[:, :-1]
    vel = F.smooth_l1_loss(a, b)
    commit = losses["commit"]
    codebook = losses.get("codebook", torch.zeros((), device=recon.device))
    total = rec + cfg.alpha_vel * vel + cfg.beta_commit * beta_scale * commit + cfg.codebook * codebook
    parts = {"loss": total, "recon": rec, "vel": vel, "commit": commit, "codebook": codebook}
    return total, {k: v.detach() for k, v in parts.items()}


KIND = "tokenizer"
register_kind(KIND, (1,))


@dataclass
class TrainConfig:
    model: ModelConfig = field(default_factory=ModelConfig)  # the convolutional encoder and decoder
    # init="t2m_gpt": codebooks start as in T2M-GPT's code (uniform for vq, the first batch for
    # the EMA and reset kinds); "uniform" is the start of motok 0.1.0 for every kind.
    quantizer: QuantizerConfig = field(
        default_factory=lambda: QuantizerConfig(codebook_size=512, dim=128, init="t2m_gpt"))
    loss: LossConfig = field(default_factory=LossConfig)  # the terms of the training loss and their weights
    optim: OptimConfig = field(default_factory=OptimConfig)  # AdamW and its schedule (paper: 300K its, x0.05 at 200K)
    iterations: In[int, ">= 1"] = 2000  # optimiser steps, one batch each (the paper's: 300K)
    batch_size: In[int, ">= 1"] = 64  # global: split evenly over the ranks
    window: In[int, ">= 1"] = 64  # frames per training crop
    split: str = "train"  # the data set's split the crops come from
    seed: In[int, ">= 0"] = 123  # weights, codebook starts and resets, and the crops drawn
    log_every: In[int, ">= 1"] = 50  # iterations per metrics.jsonl row (their mean); the last is always logged
    save_every: In[int, ">= 1"] = 500  # iterations between checkpoints; the last is always saved
    device: str = "auto"  # auto | cpu | cuda
    threads: In[int, ">= 0"] = 0  # torch intra-op threads; 0 = torch's default

    def resume_may_change(self) -> set[str]:
        """What ``--resume`` may change (motok.resume): the run's length (the schedule's milestones
        are absolute iterations) and how often it logs and saves, none of which changes a step."""
        return {"iterations", "log_every", "save_every"}


class TokenizerError(MotokError, ValueError):
    pass


def build_model(meta_or_cfg: dict | TrainConfig, feature_dim: int) -> VQVAE:
    cfg = meta_or_cfg if isinstance(meta_or_cfg, TrainConfig) else from_dict(TrainConfig, meta_or_cfg)
    return VQVAE(feature_dim, cfg.model, cfg.quantizer)


def load_tokenizer(run: str | Path, device: str | torch.device = "cpu") -> tuple[VQVAE, dict]:
    """A trained tokenizer in eval mode and its bundle metadata (config, dataset meta)."""
    return load_model(run, KIND, lambda meta: build_model(meta["config"], int(meta["extra"]["feature_dim"])), device)
