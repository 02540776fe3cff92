"""Training plumbing shared by every stage that trains under ``torchrun``: joining and leaving
the process group, gathering per-rank values, averaging gradients over ranks, picking the
device, and writing a checkpoint
bundle whose metadata records every rank's state hash (so a divergence is visible)."""

from __future__ import annotations

import gc
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from motok.artifacts import Provenance, command_line
from motok.checkpoint import rng_state, save_bundle, set_rng_state, sha256_state
from motok.config import to_dict
from motok import progress as _progress


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    owned: bool = False  # we initialized the process group, so we tear it down

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed() -> Dist:
    """Join the process group torchrun describes in the environment (a no-op when alone)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    owned = False
    if not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        owned = True
    return Dist(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")), owned)


def shutdown_distributed(d: Dist) -> None:
    """Leave the process group we joined. Leaving while a peer is still in a collective aborts
    gloo's threads, and so does a DDP reducer that outlives its process group (seen as
    'terminate called without an active exception' at exit): collect it, then barrier."""
    if d.owned:
        gc.collect()
        dist.barrier()
        dist.destroy_process_group()


def gather(obj, d: Dist) -> list:
    if d.world == 1:
        return [obj]
    out = [None] * d.world
    dist.all_gather_object(out, obj)
    return out


def world_size() -> int:
    """Ranks in the process group (1 when alone)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def average_gradients(params: list[torch.Tensor]) -> None:
    """All-reduce mean of the gradients over ranks, flattened into one collective: what DDP would do,
    for the trainers that step their own optimisers (PPO, AMP's discriminator, distillation)."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= world_size()
    o = 0
    for g in grads:
        g.copy_(flat[o:o + g.numel()].view_as(g))
        o += g.numel()


def average_scalar(x: torch.Tensor) -> torch.Tensor:
    """The mean of ``x`` over ranks (a collective: every rank calls it)."""
    y = x.detach().clone().reshape(1)
    dist.all_reduce(y)
    return y[0] / world_size()


def pick_device(name: str, d: Dist, error: type[Exception] = ValueError) -> torch.device:
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise error("device=cuda but no GPU is available")
    return torch.device("cuda", d.local_rank)


def save_checkpoint(run, kind: str, model: torch.nn.Module, opt, sched, data_gen: torch.Generator, d: Dist,
                    cfg, inputs: dict, extra: dict, it: int, last: dict, command: str | None = None) -> None:
    """Collective (every rank calls it): gather data-RNG states and state hashes, then rank 0
    writes the bundle with everything exact resume needs."""
    states = gather(data_gen.get_state(), d)
    hashes = gather(sha256_state(model.state_dict()), d)
    if not d.main:
        return
    if len(set(hashes)) > 1:
        _progress.info(f"[bold red]warning:[/] ranks diverged at iteration {it}: {hashes}")
    ts = {"iteration": it, "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
          "rng": rng_state(), "data_rng": torch.stack(states), "world_size": d.world}
    prov = Provenance(command=command or command_line(), config=to_dict(cfg), inputs=inputs)
    save_bundle(run, kind, model.state_dict(), to_dict(cfg), prov, train_state=ts,
                extra={**extra, "iteration": it, "world_size": d.world, "rank_state_sha256": hashes,
                       "last_metrics": last})


def restore_checkpoint(model: torch.nn.Module, opt, sched, data_gen: torch.Generator, d: Dist, state: dict,
                       train_state: dict) -> int:
    """The inverse of :func:`save_checkpoint` for one rank; returns the iteration to continue from."""
    model.load_state_dict(state)
    opt.load_state_dict(train_state["optimizer"])
    sched.load_state_dict(train_state["scheduler"])
    set_rng_state(train_state["rng"])
    data_gen.set_state(train_state["data_rng"][d.rank].clone())
    return int(train_state["iteration"])
