"""Run folders of the control stage, for their trainers and their readers alike: a run's bundle
and humanoid (its MJCF checked against the hash the bundle records), the runs it was made from
(a prior's expert, a task policy's prior), the clips it was trained on, and what an evaluation
says about the checkpoint it measured; and the torch threads a phase of a run uses. Nothing here
trains: loaders, sampling and evaluations read runs through this module, never through a trainer."""

from __future__ import annotations

import hashlib
from contextlib import contextmanager
from pathlib import Path

import torch

from motok.checkpoint import CheckpointError, load_bundle, read_meta
from motok.config import from_dict
from motok.sim.humanoid import Humanoid, load_humanoid


def mjcf_hash(hum: Humanoid) -> str:
    return hashlib.sha256(Path(hum.path).read_bytes()).hexdigest()


def load_run(run, kind: str) -> tuple[dict, dict, Humanoid]:
    """``(meta, weights, humanoid)`` of a control run, its ``humanoid.xml`` checked against the hash."""
    run = Path(run)
    meta, state, _ = load_bundle(run, kind)
    hum = load_humanoid(run / "humanoid.xml")
    if mjcf_hash(hum) != meta["extra"]["mjcf_sha256"]:
        raise CheckpointError(f"{run}/humanoid.xml does not match the checkpoint's MJCF hash")
    return meta, state, hum


def load_run_model(run, kind: str, config_cls, prefix: str, build) -> tuple[object, Humanoid, torch.nn.Module, dict]:
    """``(cfg, humanoid, model, meta)`` of a control run: its recipe as ``config_cls`` (physics on C
    MuJoCo, :meth:`~motok.sim.env.SimConfig.portable`), the network ``build(cfg, meta)`` makes
    (from the sizes in ``meta["extra"]``; a task policy also from the prior the run links),
    loaded with the bundle's weights under ``prefix`` (``ac.``, ``model.``)."""
    meta, state, hum = load_run(run, kind)
    cfg = from_dict(config_cls, meta["config"])
    cfg.env.portable()  # trained on a GPU or not, used on C MuJoCo unless told otherwise
    model = build(cfg, meta)
    model.load_state_dict(split_state(state, prefix))
    return cfg, hum, model, meta


def resumed_meta(run, kind: str, resume: bool) -> dict | None:
    """The metadata of the checkpoint a resume of ``run`` continues, for what must be known before
    anything is built (what the run holds, settings it resolved); None when not resuming, or when
    ``run`` has no checkpoint yet (a resume that starts it)."""
    if resume and (Path(run) / "bundle.json").exists():
        return read_meta(run, kind)
    return None


def run_library(run, meta: dict, hum: Humanoid, control_hz, data=None, clips: str | None = None,
                split: str | None = None, hint: str = ": pass --data"):
    """``(dataset, library)`` to evaluate a run on: its own dataset and clips unless ``data``,
    ``clips`` (a glob) or ``split`` say otherwise."""
    from motok.checkpoint import bundle_ref
    from motok.data.dataset import select_clips
    from motok.sim.reference import load_library

    src = data or bundle_ref(Path(run), meta, "data", hint=hint)
    names = select_clips(src, clips, split) if clips or split else meta["extra"]["clips"]
    return src, load_library(hum, src, control_hz=control_hz, clips=names)


def link_record(key: str, linked_run, kind: str) -> dict:
    """A run this one was made from (a prior's expert, a task policy's prior), for the bundle's
    metadata: ``key``, a path the bundle stores relative to itself (so the two can move
    together), and ``KEY_info``: its absolute path (found from anywhere on this machine) and what
    identifies its weights."""
    meta = read_meta(linked_run, kind)
    ex, path = meta["extra"], Path(linked_run).resolve()
    return {key: path, f"{key}_info": {"absolute": str(path), "model_sha256": meta.get("model_sha256"),
                                       "iteration": ex.get("iteration"), "samples": ex.get("samples")}}


def linked_path(run, meta: dict, key: str) -> Path:
    """Where the run linked as ``key`` (:func:`link_record`) is: relative to ``run`` first, then absolute."""
    from motok.checkpoint import bundle_ref

    found = bundle_ref(run, meta, key, required=False)
    if found is not None and (found / "bundle.json").exists():
        return found
    absolute = Path(meta["extra"][f"{key}_info"]["absolute"])
    if (absolute / "bundle.json").exists():
        return absolute
    raise CheckpointError(f"{run}: its {key} is neither at {meta['extra'].get(key)!r} (from the bundle) "
                          f"nor at {absolute}")


def checkpoint_info(meta: dict) -> dict:
    """What an evaluation says about the checkpoint it measured."""
    ex = meta["extra"]
    return {"iteration": ex["iteration"], "samples": ex["samples"], "wall_s": ex.get("last_metrics", {}).get("wall_s"),
            "mjcf_sha256": ex["mjcf_sha256"]}


def split_state(state: dict, prefix: str) -> dict:
    """The entries of a bundle's weights under ``prefix`` (``ac.``, ``model.``), without it."""
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


@contextmanager
def torch_threads(n: int):
    """``n`` torch threads inside the block: on a 2-core machine the rollout wants 1 (MuJoCo's
    workers have the cores) and the learning steps 2 (the physics is idle then)."""
    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _what_was_measured(report: dict) -> tuple:
    """An evaluation's settings and the content of its inputs, whatever the paths they were named by."""
    prov = report.get("provenance") or {}
    config = {k: v for k, v in (prov.get("config") or {}).items() if k not in ("run", "prior")}
    return config, sorted((prov.get("inputs") or {}).values())


def write_evaluation(path, report: dict) -> Path:
    """Write the evaluation ``report`` to ``path`` in its run. An evaluation there of other inputs or
    settings (other clips, data, episodes, seed, task settings) is moved aside to
    ``NAME.replaced-TIME.json``, with a note, never lost: the run's evaluation must not be replaced
    by a quick check on one clip. One of the same inputs and settings is replaced (a later checkpoint)."""
    import datetime as _dt
    import json
    import os

    from motok.atomic import write_json
    from motok.runfolder import info

    path = Path(path)
    if path.is_file():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            old = {}
        if not isinstance(old, dict) or _what_was_measured(old) != _what_was_measured(report):
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            aside, n = path.with_name(f"{path.stem}.replaced-{stamp}{path.suffix}"), 1
            while aside.exists():
                n += 1
                aside = path.with_name(f"{path.stem}.replaced-{stamp}-{n}{path.suffix}")
            os.replace(path, aside)
            info(f"note: {path} held an evaluation of other inputs or settings; it is kept as {aside.name}")
    return write_json(path, report)
