"""The trained models of the Python API: loading a run, and what each one does in memory.

A run is loaded once and used many times, as ``from_pretrained`` does: :func:`load` reads the
bundle's kind and returns the object that uses it (a tokenizer, a GPT ready to sample, a
physics controller, a task policy); the typed loaders say what they expect. Every function
calls the library function its ``motok`` command calls, without the files: ``generate`` is
``gpt sample``'s sampling, ``track`` is ``control track``'s tracking, ``evaluate_task`` is
``control eval --task``'s evaluation. Heavy imports (torch, MuJoCo) happen on first use.
"""

from __future__ import annotations

__all__ = ["TaskPolicy", "TrackResult", "decode", "encode", "evaluate_task", "generate", "load", "load_controller",
           "load_gpt", "load_policy", "load_tokenizer", "track"]

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

import numpy as np

from motok.api.motion import Motion, as_clips, from_clips, motions
from motok.errors import UserError
from motok.ranges import checked  # numbers in range for callers from Python too

if TYPE_CHECKING:
    from motok.control.priors.load import Controller
    from motok.gpt.sample import Sampler
    from motok.tokenizer.tokens import Tokenizer

CONTROLLERS = ("control-expert", "control-prior")


def _kind(path) -> str:
    from motok.checkpoint import read_meta

    return str(read_meta(path).get("kind"))


def load(path, **options):
    """The run at ``path``, by the kind its ``bundle.json`` names: a tokenizer
    (:func:`load_tokenizer`), a GPT (:func:`load_gpt`), an expert or a prior
    (:func:`load_controller`) or a task policy (:func:`load_policy`); ``options`` go to that
    loader."""
    kind = _kind(path)
    loaders = {"tokenizer": load_tokenizer, "gpt": load_gpt, "control-expert": load_controller,
               "control-prior": load_controller, "control-task": load_policy}
    if kind not in loaders:
        raise UserError(f"{path}: a {kind!r} bundle has no Python loader; expected one of {sorted(loaders)}")
    return loaders[kind](path, **options)


def load_tokenizer(path) -> "Tokenizer":
    """A tokenizer run (``motok tokenize train``), for :func:`encode` and :func:`decode`."""
    from motok.tokenizer.tokens import open_tokenizer

    return open_tokenizer(path)


@checked(snap="motok.gpt.model:TrainConfig.snap")
def load_gpt(path, *, tokenizer=None, allow_mismatch: bool = False, snap: int | None = None) -> "Sampler":
    """A GPT run (``motok gpt train``) with the tokenizer that decodes its codes (its own, or the
    run at ``tokenizer``; another one needs ``allow_mismatch``) and its caption cache, for
    :func:`generate`. ``snap``: as ``gpt sample --snap`` (default: the run's)."""
    from motok.gpt.sample import load_sampler

    return load_sampler(path, tokenizer, allow_mismatch, snap=snap)


@checked(codebooks=">= 1")
def load_controller(path, *, codebooks: int | None = None) -> "Controller":
    """An expert run (``motok control expert train``) or a distilled prior (``motok control
    distill``, its posterior and decoder acting; ``codebooks``: its first M only), for
    :func:`track`."""
    from motok.control.priors.load import load_controller as load_either

    kind = _kind(path)
    if kind not in CONTROLLERS:
        raise UserError(f"{path}: expected a control-expert or control-prior bundle, found kind {kind!r}")
    if kind == "control-expert":
        if codebooks is not None:
            raise UserError(f"{path}: codebooks select a prior's codebooks; an expert has none")
        return load_either(expert=path)
    return load_either(prior=path, codebooks=codebooks)


@dataclass(repr=False)
class TaskPolicy:
    """A task policy (``motok control train --task``) over its frozen prior, for :func:`evaluate_task`."""

    path: Path
    cfg: object  # TaskTrainConfig: the task, its settings, the environment
    humanoid: object
    policy: object  # the high-level actor-critic
    prior: object  # the frozen LatentPrior it acts through
    scale: float  # the prior's action scale
    meta: dict

    @property
    def task(self) -> str:
        return self.cfg.task

    def __repr__(self) -> str:
        return f"TaskPolicy({str(self.path)!r}, task {self.task!r}, over a {self.prior.kind} prior)"


def load_policy(path) -> TaskPolicy:
    """A task policy run (``motok control train``), for :func:`evaluate_task`."""
    from motok.control.highlevel.policy import load_task_run

    return TaskPolicy(Path(path), *load_task_run(path))


@checked(num_samples=">= 1", seed=">= 0", temperature="> 0", top_k=">= 1", top_p="(0, 1]", seconds="> 0",
         guidance="motok.gpt.model:TrainConfig.guidance")
def generate(gpt: "Sampler", texts: str | Iterable[str], *, num_samples: int = 1, seed: int = 0,
             temperature: float = 1.0, top_k: int | None = None, top_p: float | None = None, argmax: bool = False,
             seconds: float | None = None, guidance: float | None = None) -> list[Motion]:
    """Motions from text: ``num_samples`` per text (sample ``j`` seeded ``seed + j``), in the
    order text by text, each decoded on the tokenizer's skeleton; the options are those of
    ``motok gpt sample``. A motion's ``labels`` hold its text, seed and codes."""
    from motok.gpt.sample import sample_clips

    texts = [texts] if isinstance(texts, str) else list(texts)
    made = sample_clips(gpt, texts, num_samples=num_samples, seed=seed, temperature=temperature, top_k=top_k,
                        top_p=top_p, argmax=argmax, seconds=seconds, guidance=guidance)
    tok = gpt.tokenizer
    skeleton, offsets = tok.skeleton, tok.offsets
    return [Motion(c, skeleton, tok.fps, offsets, tok.legacy) for c in made.clips]


@checked(codebooks=">= 1")
def encode(tokenizer: "Tokenizer", motion: Motion, *, codebooks: int | None = None) -> np.ndarray:
    """The motion's codes ``(L, M)`` (``M`` codebooks, all by default), one per ``rate`` frames;
    the trailing frames that fill no code are dropped, as ``motok tokenize encode`` does."""
    from motok.tokenizer.tokens import check_codebooks, check_motion

    m = motions(motion)[0]
    check_motion(tokenizer.meta, f"motion {m.name!r}", m.features.shape[1], m.fps, m.skeleton.joints, m.legacy)
    if m.num_frames < tokenizer.rate:
        raise UserError(f"motion {m.name!r}: {m.num_frames} frames, fewer than one code ({tokenizer.rate})")
    return tokenizer.encode(m.features, check_codebooks(tokenizer.model, codebooks))


@checked(codebooks=">= 1")
def decode(tokenizer: "Tokenizer", codes, *, codebooks: int | None = None, name: str = "decoded",
           caption: str | None = None) -> Motion:
    """Codes ``(L,)`` or ``(L, N)`` back to a motion of ``L * rate`` frames on the tokenizer's
    skeleton (its first ``codebooks`` columns; by default as many as both have), as ``motok
    tokenize decode`` decodes each clip."""
    from motok.tokenizer.tokens import check_codebooks

    arr = np.asarray(codes)
    if arr.ndim == 1:
        arr = arr[:, None]
    size = int(tokenizer.model.quantizer.codebook_size)
    if arr.ndim != 2 or not len(arr) or not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 \
            or arr.max() >= size:
        raise UserError(f"codes must be integers in 0..{size - 1}, shaped (L,) or (L, N) with L >= 1; "
                        f"got {arr.dtype} {arr.shape}")
    m = check_codebooks(tokenizer.model, codebooks or min(arr.shape[1], tokenizer.model.num_codebooks),
                        ("the array", arr.shape[1]))
    caps = [(caption, "", 0.0, 0.0)] if caption else []
    clip = tokenizer.decode(name, arr, m, split="none", captions=caps)
    return Motion(clip, tokenizer.skeleton, tokenizer.fps, tokenizer.offsets, tokenizer.legacy)


@dataclass
class TrackResult:
    """What :func:`track` returns: the simulated motions and the report ``control track`` writes
    beside them (overall, and per clip: tracked to the end, seconds played, MPJPE, G-MPJPE, sole
    slip, or why a clip was not tracked)."""

    motions: list[Motion]  # one per clip played for at least two frames, in the input's order
    summary: dict
    per_clip: dict[str, dict]


@checked(batch=">= 1")
def track(controller: "Controller", motion: Motion | Iterable[Motion], *, render=None,
          batch: int = 256) -> TrackResult:
    """Track each motion in MuJoCo with ``controller`` (:func:`load_controller`) from its first
    frame until it ends or the controller's failure test stops it, as ``motok control track``
    does; ``render``: a video (.mp4/.gif) of the first one over its kinematic ghost."""
    from motok.control.track import track_clips

    done = track_clips(controller, as_clips(motion), render=render, batch=batch)
    return TrackResult(from_clips(done.motion), done.summary, done.per_clip)


@checked(episodes=">= 1", seed=">= 0")
def evaluate_task(policy: TaskPolicy, *, episodes: int = 16, seed: int = 0, render=None) -> dict:
    """The task's own evaluation of ``policy`` (``motok control eval --task``) on ``episodes``
    episodes from its own clips: targets reached, falls, time, as the task reports them;
    ``render``: a video of one more episode with the task's markers. Nothing is written."""
    from motok.control.highlevel.evaluate import evaluate_loaded

    loaded = (policy.cfg, policy.humanoid, policy.policy, policy.prior, policy.scale, policy.meta)
    return evaluate_loaded(policy.path, loaded, episodes=episodes, seed=seed, render=render)[0]
