"""Unconditional generation from a distilled prior (hybrid-latent paper section 6.2):
``motok control generate``.

Each sample starts from a reference state (a random clip and frame of the prior's dataset, the
same draw as reference state initialisation) and is then left to the prior alone: at every
control step a latent is drawn without looking at any reference and the frozen decoder acts on
the current-pose base (``q_hat = q + scale a``, as in distillation).

* discrete, hybrid-vq: one code index, uniform over the codebook;
* discrete+, hybrid: one index per codebook for the first M codebooks, each uniform and
  independent (``z_bar`` = the sum of the codes; hybrid: ``z_p(s)`` plus that sum);
* continuous: ``z ~ N(mu_p(s), sigma_p(s)^2)``, the prior Gaussian;
* hybrid-grvq, hybrid-parts: one index per (group, codebook) of the first M codebooks of every group;
  hybrid-fsq: one level per channel of the first M channel groups (a uniform code per group);
* every hybrid with M = 0: ``z_bar = z_p(s)``, the prior alone (no margin), which tells
  whether a sample's fall comes from the random margins or from the prior itself.

A sample ends at the requested length, or when it falls (the head below ``fall_height``, 0.5 m)
or the simulation diverges: it is not reset; the frames up to the last upright one are kept and
the fall time is reported per sample. The simulated bodies are written as a ``motion`` artifact
at the dataset's frame rate (:func:`motok.sim.reference.simulated_clip`), so ``motok info``,
``render``, ``export bvh`` and ``motok eval`` read it like any other motion.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.control import runs
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.resets import reference_state
from motok.control.priors.load import check_codebooks
from motok.control.priors.model import LatentPrior, load_prior
from motok.control.rl.rollout import as_tensor
from motok.sim.reference import simulated_clip
from motok.data.dataset import MotionFile, MotionWriter
from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import Humanoid

FALL_HEIGHT = 0.5  # m: the head below this ends a sample (the fall test of tasks without a reference)


@torch.no_grad()
def sample_latent(model: LatentPrior, s: torch.Tensor, m: int,
                  gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(z_bar, indices)`` for normalised observations ``s`` ``(B, obs_dim)``: ``m`` code indices
    per row (``model.columns(m)`` columns), uniform and independent (``indices`` ``(B, columns)``), or for the continuous prior a draw
    from the prior Gaussian (``indices`` None); ``m = 0`` with a prior network: ``z_p(s)``, no codes."""
    if model.quantizer is None:
        mu, log_std = model.prior_latent(s)
        return mu + torch.exp(log_std) * torch.randn(mu.shape, generator=gen), None
    if m == 0:
        return model.prior_latent(s)[0], torch.empty(len(s), 0, dtype=torch.long)
    # One uniform index per column: per codebook, per group and codebook (group RVQ), per channel (FSQ:
    # independent uniform levels are a uniform draw of each group's code).
    idx = torch.randint(model.quantizer.codebook_size, (len(s), model.columns(m)), generator=gen)
    return model.codes_to_latent(s, idx, m), idx


@torch.no_grad()
def rollout(model: LatentPrior, hum: Humanoid, sim: SimConfig, action: ActionConfig, qpos: np.ndarray,
            qvel: np.ndarray, steps: int, m: int, gen: torch.Generator, fall_height: float = FALL_HEIGHT,
            keep_qpos: bool = False, on_step=None) -> dict:
    """Simulate ``len(qpos)`` samples from the given states for ``steps`` control steps.

    Returns body positions ``pos`` ``(N, steps + 1, J, 3)`` (MuJoCo frame) with the ``alive`` mask
    of the frames each sample kept (a prefix), ``stop_step`` (the step that ended a sample, -1 if
    none), ``stop`` (``"fall"``, ``"diverged"``, ``"invalid"`` or ``""``), the drawn ``indices``
    ``(steps, N, model.columns(m))`` (None for the continuous prior) and, with ``keep_qpos``, the first
    sample's qpos per step."""
    N, head = len(qpos), hum.skeleton.head
    env = HumanoidEnv(hum, replace(sim, num_envs=N, nan_actions="terminate"))
    env.set_state(np.arange(N), qpos, qvel)
    pos = np.zeros((N, steps + 1) + env.bodies.pos.shape[1:])
    alive = np.zeros((N, steps + 1), bool)
    pos[:, 0], alive[:, 0] = env.bodies.pos, True
    stop_step, stop = np.full(N, -1), np.full(N, "", dtype=object)
    indices = torch.full((steps, N, model.columns(m)), -1, dtype=torch.long) if model.quantizer is not None else None
    first = [env.qpos[0].copy()]
    active = np.ones(N, bool)
    for t in range(steps):
        s = model.norm_obs(as_tensor(env.observation()))
        z, idx = sample_latent(model, s, m, gen)
        if idx is not None:
            indices[t] = idx
        diverged, invalid = env.step(pd_targets(action, model.decode(s, z).numpy(), env, None))
        fell = env.bodies.pos[:, head, 2] < fall_height
        for why, mask in (("invalid", invalid), ("diverged", diverged), ("fall", fell)):
            hit = active & mask & (stop_step < 0)
            stop[hit], stop_step[hit] = why, t
        active &= stop_step < 0
        pos[:, t + 1], alive[:, t + 1] = env.bodies.pos, active
        if keep_qpos and active[0]:
            first.append(env.qpos[0].copy())
        if on_step is not None:
            on_step()
        if not active.any():
            break
    return {"pos": pos, "alive": alive, "stop_step": stop_step, "stop": stop, "indices": indices,
            "qpos": np.stack(first), "dt": env.dt}


def generate(prior_run, out, *, codebooks: int | None = None, seconds: float = 30.0, num_samples: int = 10,
             seed: int = 0, data=None, clips: str | None = None, split: str | None = None, render=None,
             fall_height: float = FALL_HEIGHT, batch: int = 256) -> dict:
    """``num_samples`` motions of ``seconds`` from the prior in ``prior_run``, started from
    random reference states of its dataset (or of ``data``, ``clips``, ``split``), written to
    ``out``; see the module docstring. The same seed gives the same motion."""
    from motok.progress import make_progress

    if seconds <= 0 or num_samples < 1:
        raise UserError("--seconds must be positive and -n at least 1")
    prior_run, out = Path(prior_run), Path(out)
    cfg, hum, model, meta = load_prior(prior_run)
    m = check_codebooks(model, codebooks)
    hz = float(cfg.env.control_hz or hum.control_hz)
    src, lib = runs.run_library(prior_run, meta, hum, hz, data, clips, split)
    with MotionFile(src) as mf:
        fps, skeleton, legacy, offsets = mf.fps, mf.skeleton, mf.legacy, np.asarray(mf.offsets, np.float64)
    steps = max(1, int(round(seconds * hz)))
    rng, gen = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    start_clips, start_frames = lib.sample(num_samples, rng, horizon=1)
    qpos, qvel = reference_state(lib, start_clips, start_frames)
    tag = model.kind if model.quantizer is None else f"{model.kind}-m{m}"
    names = [f"{tag}-{i:03d}" for i in range(num_samples)]
    written, frames, per, video = 0, 0, {}, None
    prov = Provenance(command=command_line(), config={
        "prior": str(prior_run), "kind": model.kind, "codebooks": m, "seconds": seconds, "num_samples": num_samples,
        "seed": seed, "data": str(src), "clips": clips, "split": split, "fall_height": fall_height,
        "control_hz": hz}, inputs={**hash_inputs([src]), "prior#weights": meta.get("model_sha256")})
    # each batch's clips go to the file as soon as they are simulated: Table 1's 800,000 frames per
    # row would otherwise be held whole (about 1.3 GB of frames)
    with runs.torch_threads(cfg.torch_threads), make_progress("steps") as bar, \
            MotionWriter(out, "motion", prov, skeleton, offsets.astype(np.float32), fps, legacy) as writer:
        task = bar.add_task(f"generate {tag}", total=steps * len(range(0, num_samples, batch)))
        for a in range(0, num_samples, batch):
            ids = np.arange(a, min(a + batch, num_samples))
            res = rollout(model, hum, cfg.env, cfg.action, qpos[ids], qvel[ids], steps, m, gen, fall_height,
                          keep_qpos=render is not None and a == 0, on_step=lambda: bar.advance(task))
            if render is not None and a == 0:
                video = res["qpos"]
            batch_clips = []
            for k, i in enumerate(ids):
                p = res["pos"][k, res["alive"][k]]
                stopped = res["stop"][k]
                per[names[i]] = {"start_clip": lib.names[start_clips[i]], "start_frame": int(start_frames[i]),
                                 "seconds": float((len(p) - 1) / hz), "stopped": stopped or None,
                                 "fell_at_s": float((res["stop_step"][k] + 1) / hz) if stopped == "fall" else None}
                if len(p) * fps / hz < 2:
                    per[names[i]]["error"] = "ended before two frames at the dataset's rate: nothing written"
                    continue
                labels = {"prior": model.kind, "codebooks": m, "seed": seed, "sample": int(i),
                          **{k2: per[names[i]][k2] for k2 in ("start_clip", "start_frame", "fell_at_s")}}
                batch_clips.append(simulated_clip(names[i], p, hz, fps, skeleton, offsets, legacy, str(prior_run),
                                                  split="none", labels=labels))
            writer.add(batch_clips)
            written += len(batch_clips)
            frames += sum(c.num_frames for c in batch_clips)
            del res, batch_clips
        if not written:
            raise UserError(f"{prior_run}: every sample ended before two frames at {fps:g} fps (all fell at once?)")
    fell = [v["fell_at_s"] for v in per.values() if v["stopped"] == "fall"]
    summary = {"output": str(out), "prior": str(prior_run), "kind": model.kind,
               "codebooks": m if model.quantizer is not None else None,
               "samples": num_samples, "written": written, "seconds": seconds,
               "seconds_played_mean": float(np.mean([v["seconds"] for v in per.values()])),
               "fell": len(fell), "stopped_other": sum(v["stopped"] not in (None, "fall") for v in per.values()),
               "frames": int(frames), "fps": fps}
    if video is not None:
        from motok.sim.render import render_trajectory
        how = ("prior draws" if model.quantizer is None else "the prior's z_p alone" if m == 0
               else f"uniform codes of {m} codebook{'s' * (m > 1)}")
        path, backend = render_trajectory(hum, video, render, hz, title=f"{names[0]}: {how}")
        summary["video"] = f"{path} ({backend})"
    return {**summary, "per_sample": per}
