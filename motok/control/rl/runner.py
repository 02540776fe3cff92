"""One runner for every control trainer: seeding, the run folder, checkpoints every
``save_every`` iterations with exact resume, the evaluation hook, metrics, provenance, the MJCF
and its hash, the progress bar, and ``torchrun``.

A trainer is any object with ``iteration``, ``samples``, ``wall``, ``samples_per_iteration``,
``model_state()``, ``train_state()`` (identical on every rank: optimisers, counters),
``rank_state()`` (this rank's generators and buffers), ``load(model, shared, rank)``,
``spec()`` (what a user of the bundle needs to know: dimensions, action map, clips),
``start_segment()`` (fresh episodes everywhere) and ``step() -> metrics``.

Exactness: at a checkpoint every environment restarts from a fresh start state, in an
uninterrupted run as in a resumed one, which is what makes resuming bit-exact without saving
MuJoCo's solver state. Under ``torchrun`` the networks are initialised from the same seed on
every rank, each rank then draws from its own streams (:func:`rank_seed`), and rank 0 writes the
bundle with every rank's state.
"""

from __future__ import annotations

import shutil
import time
from collections import deque
from pathlib import Path
from typing import Callable, Protocol

import torch

from motok import progress as _progress
from motok.artifacts import Provenance, command_line, hash_inputs
from motok.checkpoint import (CheckpointError, MetricsLog, load_bundle, rng_state, save_bundle, set_rng_state,
                              sha256_state)
from motok.config import to_dict
from motok.control.rl.ppo import KL_WINDOW, kl_warning
from motok.control.runs import mjcf_hash, torch_threads
from motok.distributed import Dist, gather, init_distributed, shutdown_distributed
from motok.errors import UserError
from motok.resume import carried_links, check_inputs, check_settings
from motok.sim.humanoid import Humanoid

# The option that names each run a control run is made from (motok.control.runs.link_record keys).
LINK_FLAGS = {"expert": "--expert", "prior": "--prior", "init": "--init"}
SUMMARY_KEYS = ("episode_return", "episode_seconds", "success", "r_im", "samples_per_s")
# What the progress bar shows after the rate: (label, metric key, format).
BAR_FIELDS = (("ret", "episode_return", "{:.1f}"), ("len", "episode_seconds", "{:.2f}s"), ("succ", "success", "{:.2f}"))


class Trainer(Protocol):
    iteration: int
    samples: int
    wall: float
    samples_per_iteration: int

    def model_state(self) -> dict[str, torch.Tensor]: ...

    def train_state(self) -> dict: ...

    def rank_state(self) -> dict: ...

    def load(self, model: dict, shared: dict | None, rank: dict | None) -> None: ...

    def spec(self) -> dict: ...

    def start_segment(self) -> None: ...

    def step(self) -> dict: ...


def counters(tr) -> dict:
    """The counters every trainer's ``train_state`` starts with."""
    return {"iteration": tr.iteration, "samples": tr.samples, "wall": tr.wall}


def load_counters(tr, shared: dict) -> None:
    tr.iteration, tr.samples, tr.wall = int(shared["iteration"]), int(shared["samples"]), float(shared["wall"])


def generator_state(g):
    """A generator's state for ``rank_state``: JSON for numpy's, the state tensor for torch's (an
    on-device task draws its resets from a ``torch.Generator``)."""
    import json
    return g.get_state() if isinstance(g, torch.Generator) else json.dumps(g.bit_generator.state)


def load_generator(g, state) -> None:
    import json
    if isinstance(g, torch.Generator):
        g.set_state(state)
    else:
        g.bit_generator.state = json.loads(state)


def task_rng_state(mdp) -> dict:
    """A rank's task generator (``rank_state``); :func:`load_task_rng` restores it."""
    return {"task_rng": generator_state(mdp.task.rng)}


def load_task_rng(mdp, rank: dict) -> None:
    load_generator(mdp.task.rng, rank["task_rng"])


def load_shared(tr, shared: dict, rank: dict, **optimizers) -> None:
    """What a resume restores in a trainer besides its weights: the counters, each optimiser (named
    by its ``train_state`` key) and this rank's task generator."""
    load_counters(tr, shared)
    for key, opt in optimizers.items():
        opt.load_state_dict(shared[key])
    load_task_rng(tr.mdp, rank)


def timed_step(tr, collect: Callable[[], tuple], update: Callable[..., dict]) -> dict:
    """One collect-then-learn iteration of ``tr``: ``collect() -> (*batch, stats)``, then
    ``update(*batch) -> metrics`` under the update's torch threads (``cfg.update_threads``, else
    ``cfg.torch_threads``: the rollout and the update want different numbers), counted and timed
    by :func:`finish_step`."""
    t0 = time.perf_counter()
    *batch, stats = collect()
    t1 = time.perf_counter()
    with torch_threads(tr.cfg.update_threads or tr.cfg.torch_threads):
        stats.update(update(*batch))
    return finish_step(tr, stats, t0, t1)


def finish_step(tr, stats: dict, t0: float, t1: float) -> dict:
    """Count one iteration that started at ``t0`` (collection ended at ``t1``) and add the step's
    timing to ``stats``: iteration, samples, training wall time, samples/s, rollout and update seconds."""
    n = tr.samples_per_iteration
    tr.iteration += 1
    tr.samples += n
    dt = time.perf_counter() - t0
    tr.wall += dt
    stats.update(iteration=tr.iteration, samples=tr.samples, wall_s=round(tr.wall, 2), samples_per_s=n / dt,
                 rollout_s=t1 - t0, update_s=dt - (t1 - t0))
    return stats


def rank_seed(seed: int, rank: int) -> int:
    """Rank 0 keeps ``seed`` (a single-process run is the 1-rank case); others get their own stream."""
    return seed if rank == 0 else seed + 100_003 * rank


class _StopSignal:
    """SIGTERM asks a training to stop at its next checkpoint (``kill -TERM PID``, or a session's end
    that sends it), so a run interrupted on purpose loses nothing and resumes exactly; a second
    SIGTERM, or any signal before training starts, ends the process at once as usual."""

    def __init__(self):
        self.requested, self._previous = False, None

    def install(self) -> None:
        import signal
        import threading

        self.requested = False
        if threading.current_thread() is not threading.main_thread():
            return  # signal handlers live on the main thread only

        def handler(signum, frame):
            if self.requested:
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
                signal.raise_signal(signal.SIGTERM)
            self.requested = True
            _progress.info("SIGTERM: stopping at the next checkpoint (send it again to stop now)")

        self._previous = signal.signal(signal.SIGTERM, handler)

    def restore(self) -> None:
        import signal

        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)
            self._previous = None


stop_signal = _StopSignal()


def stop_message(run: Path, iteration: int) -> str:
    """What a training stopped by SIGTERM says: where it stopped and, run from the command line,
    the exact command that continues it (the one the Ctrl-C message prints)."""
    import sys

    from motok.runfolder import final_path, resume_command
    where = f"stopped at iteration {iteration} on request (SIGTERM); last checkpoint: iteration {iteration} in " \
            f"{final_path(run)}"
    if Path(sys.argv[0]).name == "motok":
        return f"{where}; continue exactly from there with: {resume_command()}"
    return f"{where}; continue exactly from there with the same call and resume=True"  # called from Python


def _stopped_on_request(run: Path, iteration: int) -> None:
    from rich.markup import escape
    # not quiet-gated, as Ctrl-C's is not: it is how the user learns how to go on
    _progress.console.print(escape(stop_message(run, iteration)), highlight=False, soft_wrap=True)


def _note_inexact(run: Path, start: int, stop: int, cfg, resumed: bool, main: bool) -> None:
    """Say when a run will not repeat an uninterrupted one to the digit, or has nothing to do: every
    environment restarts at a checkpoint, so a checkpoint between save_every multiples (an --until
    that is not one) is a restart an uninterrupted run does not make."""
    if not main:
        return
    if resumed and start >= stop:
        _progress.info(f"note: {run} is already at iteration {start}: nothing to train (it stops at {stop})")
    elif resumed and start % cfg.save_every and start < cfg.iterations:
        _progress.info(f"note: {run} stopped at iteration {start}, between checkpoints (save_every "
                       f"{cfg.save_every}): resuming restarts every environment there, which an uninterrupted "
                       f"run does not, so it will not repeat one to the digit")
    elif stop % cfg.save_every and stop < cfg.iterations and stop > start:
        _progress.info(f"note: --until {stop} is between checkpoints (save_every {cfg.save_every}): a --resume from "
                       f"it will not repeat an uninterrupted run to the digit (a multiple of {cfg.save_every} would)")


def train(make_trainer: Callable[[Dist], Trainer], cfg, run, hum: Humanoid, *, kind: str, resume: bool = False,
          until: int | None = None, data=None, command: str | None = None, extra: dict | None = None,
          evaluate: Callable[[Trainer], dict] | None = None, label: str = "train",
          fields: tuple = BAR_FIELDS, summary_keys: tuple = SUMMARY_KEYS) -> dict:
    """Train (or resume) into ``run`` until ``cfg.iterations`` (or ``until``); returns a summary
    (the last values of ``summary_keys``). ``cfg`` needs ``seed``, ``iterations``, ``save_every``,
    ``eval_every`` and ``torch_threads``; ``fields`` are the progress bar's metrics."""
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, cfg.torch_threads))
    d = init_distributed()
    try:
        return _train(make_trainer, cfg, Path(run), hum, kind, resume, until, data, command, extra or {},
                      evaluate, label, d, tuple(fields), tuple(summary_keys))
    finally:
        stop_signal.restore()
        shutdown_distributed(d)
        torch.set_num_threads(threads)


def _train(make_trainer, cfg, run: Path, hum, kind, resume, until, data, command, extra, evaluate, label,
           d: Dist, fields: tuple, summary_keys: tuple) -> dict:
    saved = load_bundle(run, kind, with_train_state=True) if resume else None
    if until is not None and until > cfg.iterations:  # stopping at cfg.iterations instead would be silent
        raise UserError(f"--until {until} is past the run's {cfg.iterations} iterations, where its schedules end: "
                        f"set iterations to train longer")
    inputs = hash_inputs([data]) if data and (d.main or saved) else {}
    if saved:  # every input the run records, before anything is built or written
        check_settings(run, saved[0]["config"], cfg)
        check_inputs(run, saved[0], data_hash=next(iter(inputs.values()), None), links=extra, flags=LINK_FLAGS)
        extra = {**carried_links(run, saved[0], extra), **extra}
    if saved and saved[0]["extra"].get("mjcf_sha256") != mjcf_hash(hum):
        raise CheckpointError(f"{run}: the checkpoint was trained on another humanoid (MJCF hash differs)")
    if saved and int(saved[2].get("world_size", 0)) != d.world:
        raise CheckpointError(f"{run}: saved by {saved[2].get('world_size', '?')} ranks (an older layout when '?'); "
                              f"resume it with the same number of ranks, not {d.world}")
    torch.manual_seed(cfg.seed)  # identical initial weights on every rank, whatever the trainer seeds
    tr = make_trainer(d)
    if d.rank:
        torch.manual_seed(rank_seed(cfg.seed, d.rank))
    if saved:
        ts = saved[2]
        tr.load(saved[1], ts["shared"], ts["ranks"][d.rank])
        set_rng_state(ts["ranks"][d.rank]["rng"])
    if saved:
        check_inputs(run, saved[0], clips=tr.spec().get("clips"))
    if d.main:
        run.mkdir(parents=True, exist_ok=True)
        if Path(hum.path).resolve() != (run / "humanoid.xml").resolve():
            shutil.copyfile(hum.path, run / "humanoid.xml")
    prov = Provenance(command=command or command_line(), config=to_dict(cfg), inputs=inputs)
    extra = {"mjcf_sha256": mjcf_hash(hum), **tr.spec(), **extra, "data": Path(data) if data else None, "world_size": d.world}
    log = MetricsLog(run / "metrics.jsonl", resume_from=tr.iteration if saved else None) if d.main else None
    stop = min(cfg.iterations, until if until is not None else cfg.iterations)
    per_it = tr.samples_per_iteration
    _note_inexact(run, tr.iteration, stop, cfg, saved is not None, d.main)
    last: dict = {}

    def save():
        ranks = gather({**tr.rank_state(), "rng": rng_state()}, d)
        hashes = gather(sha256_state(tr.model_state()), d)  # equal on every rank, or the ranks diverged
        if d.main:
            if len(set(hashes)) > 1:
                _progress.info(f"[bold red]warning:[/] ranks diverged at iteration {tr.iteration}: {hashes}")
            save_bundle(run, kind, tr.model_state(), to_dict(cfg), prov,
                        train_state={"world_size": d.world, "shared": tr.train_state(), "ranks": ranks},
                        extra={**extra, "iteration": tr.iteration, "samples": tr.samples, "last_metrics": last,
                               "rank_state_sha256": hashes})

    wrote = False
    kls: deque = deque(maxlen=KL_WINDOW)  # PPO trainers' approx_kl: a diverging run says so once
    kl_warned = False
    stop_signal.install()
    tr.start_segment()
    bar = _progress.make_progress("samples", " ".join(f"{name} {{task.fields[{name}]}}" for name, _, _ in fields))
    if not d.main:
        bar.disable = True
    with bar:
        task = bar.add_task(label, total=stop * per_it, completed=tr.iteration * per_it,
                            **{name: "-" for name, _, _ in fields})
        while tr.iteration < stop:
            stats = tr.step()
            if evaluate is not None and cfg.eval_every and tr.iteration % cfg.eval_every == 0 and d.main:
                stats.update(evaluate(tr))
            last = {**last, **stats}
            if "approx_kl" in stats and not kl_warned:
                kls.append(stats["approx_kl"])
                if len(kls) == kls.maxlen and (msg := kl_warning(kls)) and d.main:
                    _progress.info(msg)
                    kl_warned = True
            if log is not None:
                log.log(stats)
            bar.update(task, advance=per_it, **{name: fmt.format(last[key]) if key in last else "-"
                                                for name, key, fmt in fields})
            if tr.iteration % cfg.save_every == 0 or tr.iteration == stop:
                save()
                wrote = True
                if any(gather(stop_signal.requested, d)):  # every rank stops at the same checkpoint
                    _stopped_on_request(run, tr.iteration)
                    break
                tr.start_segment()
    # Decided from state every rank shares: a file check could race rank 0's write and leave one
    # rank alone in a collective.
    if not wrote and not saved:
        save()
    return {"run": str(run), "iterations": tr.iteration, "samples": tr.samples, "wall_s": round(tr.wall, 1),
            **{k: round(v, 4) for k, v in last.items() if k in summary_keys}}
