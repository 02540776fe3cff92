"""What each logged metric is, for people: a label and a unit for the keys that motok's training
loops write to ``metrics.jsonl``, and the quantity a key measures, so that ``motok plot`` titles,
labels and overlays its panels (``loss``, ``val_loss`` and ``eval_loss`` are one quantity on
training, validation and evaluation data: one panel, three curves).

A key the tables do not know gets a readable fallback: its words, and a unit guessed from its
suffix (``_mm``, ``_s``, ``_m``, ``_per_s``, ``_share``), so a new metric is never shown raw.
"""

from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True)
class Metric:
    label: str  # what is measured, as a panel title
    unit: str  # the y axis' unit; for a pure number, what kind of number it is


# Prefix of a key -> the data it was measured on, as the legend says it; a key without one of
# these prefixes is the training value. ``eval_ref_`` (an evaluation's reference clips measured over
# the same frames: the feet of the mocap beside the simulated ones) comes before ``eval_``, which
# would otherwise claim it.
ROLES = {"val_": "validation", "eval_ref_": "the clips themselves", "eval_": "evaluation", "train_": "train clips"}
TRAIN = "training"

_FRACTION = "fraction, 0-1"
COMMON: dict[str, Metric] = {
    # the loop itself
    "iteration": Metric("Iteration", "optimizer steps"),
    "samples": Metric("Environment samples", "simulated steps"),
    "wall_s": Metric("Wall time", "s"),
    "lr": Metric("Learning rate", "step size"),
    "it_s": Metric("Training speed", "iterations/s"),
    "frames_s": Metric("Throughput", "motion frames/s"),
    "tokens_s": Metric("Throughput", "tokens/s"),
    "samples_per_s": Metric("Throughput", "simulated steps/s"),
    "rollout_s": Metric("Rollout time per iteration", "s"),
    "update_s": Metric("Update time per iteration", "s"),
    "difficulty_s": Metric("Difficulty evaluation time", "s"),
    "grad_norm": Metric("Gradient norm", "L2 norm, before clipping"),
    "loss": Metric("Loss", "sum of the weighted terms"),
    # tokenizer (VQ-VAE)
    "recon": Metric("Reconstruction loss", "smooth L1, normalized features"),
    "vel": Metric("Velocity loss", "smooth L1, normalized features"),
    "commit": Metric("Commitment loss", "MSE, latent"),
    "codebook": Metric("Codebook loss", "MSE, latent"),
    "usage": Metric("Codebook usage", "fraction of codes used"),
    "perplexity": Metric("Codebook perplexity", "codes (exp entropy)"),
    "dead": Metric("Dead codes", "codes per codebook"),
    # GPT
    "acc": Metric("Next-token accuracy", _FRACTION),
    "tau_measured": Metric("Corrupted input tokens", _FRACTION),
    # physics: rollouts and PPO
    "episode_return": Metric("Episode return", "sum of rewards"),
    "episode_r_im": Metric("Episode imitation reward", "mean per step"),
    "episode_r_task": Metric("Episode task reward", "mean per step"),
    "episode_seconds": Metric("Episode length", "s"),
    "episodes": Metric("Episodes ended", "per iteration"),
    "success": Metric("Success rate", _FRACTION),
    "success_any_body": Metric("Success, every body within the distance", _FRACTION),
    "seconds": Metric("Time tracked per clip", "s"),
    "mpjpe_mm": Metric("MPJPE (root-relative)", "mm"),
    "g_mpjpe_mm": Metric("Global MPJPE", "mm"),
    "skate_cm_s": Metric("Foot skating (toe joint)", "cm/s"),
    "sole_slip_cm_s": Metric("Sole slip", "cm/s"),
    "sole_penetration_mm": Metric("Sole penetration", "mm"),
    "jitter_m_s3": Metric("Jitter (mean jerk)", "m/s³"),
    "ref_skate_cm_s": Metric("Foot skating of the clips (toe joint)", "cm/s"),
    "ref_sole_slip_cm_s": Metric("Sole slip of the clips", "cm/s"),
    "ref_sole_penetration_mm": Metric("Sole penetration of the clips", "mm"),
    "ref_jitter_m_s3": Metric("Jitter of the clips (mean jerk)", "m/s³"),
    "reward": Metric("Reward", "mean per step"),
    "r_im": Metric("Imitation reward", "mean per step"),
    "r_style": Metric("Style reward (AMP)", "mean per step"),
    "r_task": Metric("Task reward", "mean per step"),
    "policy_loss": Metric("Policy loss (PPO)", "clipped surrogate"),
    "value_loss": Metric("Value loss", "MSE of returns"),
    "entropy": Metric("Policy entropy", "nats"),
    "approx_kl": Metric("Approximate KL to the old policy", "nats"),
    "clip_frac": Metric("Clipped ratios", _FRACTION),
    "explained_var": Metric("Explained variance of the value", "1 = perfect"),
    "disc_loss": Metric("Discriminator loss", "binary cross-entropy"),
    "disc_gp": Metric("Discriminator gradient penalty", "squared gradient norm"),
    "disc_ref": Metric("Discriminator on reference motion", "probability"),
    "disc_pol": Metric("Discriminator on policy motion", "probability"),
    "hard_clips": Metric("Clips failed", "clips"),
    "hard_share": Metric("Draws from failed clips", _FRACTION),
    # physics: prior distillation
    "action_loss": Metric("Action loss", "MSE to the expert's action"),
    "rollout_action_err": Metric("Action error on the student's rollouts", "MSE to the expert's action"),
    "reg_loss": Metric("Regularization loss", "weighted sum"),
    "commit_loss": Metric("Commitment loss", "MSE, latent"),
    "mm_loss": Metric("Motion-matching loss", "MSE, latent"),
    "kl_loss": Metric("KL loss", "nats"),
    "code_usage": Metric("Code usage", "fraction of codes used"),
    "code_perplexity": Metric("Code perplexity", "codes (exp entropy)"),
    "codes_reset": Metric("Codes reset", "codes per iteration"),
    "active_codebooks": Metric("Active codebooks", "codebooks"),
    "w_mm": Metric("Motion-matching loss weight", "weight"),
    # physics: navigation evaluation
    "targets": Metric("Targets set", "targets"),
    "reached_share": Metric("Targets reached", _FRACTION),
    "time_to_reach_mean_s": Metric("Time to reach a target, mean", "s"),
    "time_to_reach_median_s": Metric("Time to reach a target, median", "s"),
    "falls_per_episode": Metric("Falls", "per episode"),
    "diverged": Metric("Diverged episodes", "episodes"),
    "mean_reward": Metric("Reward", "mean per step"),
    "goal_speed_mean": Metric("Speed toward the target, mean", "m/s"),
    "goal_speed_median": Metric("Speed toward the target, median", "m/s"),
    "start_distance_mean_m": Metric("Distance to the target at the start", "m"),
    "closest_distance_mean_m": Metric("Closest approach to the target", "m"),
    "approach_share": Metric("Distance to the target closed", _FRACTION),
}

# Where a stage's key means something of its own (every stage has a "loss").
BY_KIND: dict[str, dict[str, Metric]] = {
    "tokenizer": {"loss": Metric("Tokenizer loss", "reconstruction + velocity + commitment")},
    "gpt": {"loss": Metric("Next-token loss", "cross-entropy, nats/token")},
    "evaluator": {"loss": Metric("Contrastive loss (InfoNCE)", "nats")},
    "control-prior": {"loss": Metric("Distillation loss", "action + regularization")},
}

_SUFFIX_UNITS = (("_per_s", "per second"), ("_mm", "mm"), ("_s", "s"), ("_m", "m"), ("_share", _FRACTION),
                 ("_rate", _FRACTION))


def split_key(key: str) -> tuple[str, str]:
    """``(quantity, role)``: ``val_loss`` -> ``("loss", "validation")``, ``loss`` -> ``("loss", "training")``."""
    for prefix, role in ROLES.items():
        if key.startswith(prefix) and len(key) > len(prefix):
            return key[len(prefix):], role
    return key, TRAIN


def describe(key: str, kind: str | None = None) -> Metric:
    """Label and unit of a quantity (a key without its role prefix), for a run of ``kind``."""
    known = {**COMMON, **BY_KIND.get(kind or "", {})}
    if key in known:
        return known[key]
    m = re.fullmatch(r"(.+)_(\d+)", key)  # per codebook: code_usage_3
    if m and m[1] in known:
        return Metric(f"{known[m[1]].label}, codebook {m[2]}", known[m[1]].unit)
    for suffix, unit in _SUFFIX_UNITS:
        if key.endswith(suffix) and len(key) > len(suffix):
            words = key[:-len(suffix)]
            break
    else:  # no unit to guess: the axis names the key, which says where the number comes from
        words, unit = key, key
    label = words.replace("_", " ").strip()
    return Metric(label[:1].upper() + label[1:], unit)


def axis_label(key: str, kind: str | None = None) -> str:
    """``Wall time (s)``: an axis titled by a key's label and unit."""
    m = describe(split_key(key)[0], kind)
    return f"{m.label} ({m.unit})"
