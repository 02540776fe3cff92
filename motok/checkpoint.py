"""Checkpoint bundles: a folder that loads without running code.

```
RUN/
  bundle.json          kind, schema_version, provenance, config, extra metadata (JSON)
  model.safetensors    model weights (safetensors: tensors only)
  train_state.pt       optimizer, scheduler, RNG states, iteration; read with
                       torch.load(weights_only=True), which refuses anything but tensors and
                       plain containers
  metrics.jsonl        one JSON object per logged step (appended during training)
```

Writes go to temporary names, and only when all are written are they renamed into place, model
first and ``bundle.json`` last (:func:`motok.atomic.atomic_paths`): a bundle whose ``bundle.json``
exists is complete, and a checkpoint interrupted while saving leaves the previous one whole. Loading checks the weights against
``model_sha256``: a bundle whose weights were replaced or damaged refuses to load instead of
producing plausible-looking nonsense.

A bundle that points at other files (a GPT at its tokenizer, tokens and text cache; a run at
its dataset) passes them to :func:`save_bundle` as ``Path`` values in ``extra``. They are stored
relative to the bundle folder, so a tree of runs works from any directory and after being moved
as a whole, and listed under ``refs``; :func:`bundle_ref` resolves them (and the paths of older
bundles, which were relative to the directory they were trained in).
"""

from __future__ import annotations

import hashlib
import json
import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from motok.artifacts import Provenance
from motok.atomic import atomic_paths, strict_json
from motok.errors import MissingFileError, MotokError
from motok.machine import arithmetic_differences
from motok.progress import info
from motok.runfolder import publish_staged
from motok.safeload import state_refusal, write_state

BUNDLE_KINDS: dict[str, tuple[int, ...]] = {}  # kind -> supported versions; stages register theirs


class CheckpointError(MotokError, ValueError):
    pass


def register_kind(kind: str, versions: tuple[int, ...] = (1,)) -> None:
    BUNDLE_KINDS[kind] = versions


def rng_state() -> dict[str, Any]:
    st = {
        "torch": torch.get_rng_state(),
        "numpy": torch.from_numpy(np.frombuffer(json.dumps(_np_state()).encode(), dtype=np.uint8).copy()),
        "python": torch.from_numpy(np.frombuffer(json.dumps(_py_state()).encode(), dtype=np.uint8).copy()),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():  # a rollout on the GPU draws its noise there
        st["cuda"] = torch.stack(torch.cuda.get_rng_state_all())
    return st


def _np_state():
    s = np.random.get_state()
    return [s[0], s[1].tolist(), int(s[2]), int(s[3]), float(s[4])]


def _py_state():
    v, state, g = random.getstate()
    return [v, list(state), g]


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(list(state["cuda"]))
    s = json.loads(bytes(state["numpy"].numpy()).decode())
    np.random.set_state((s[0], np.array(s[1], dtype=np.uint32), s[2], s[3], s[4]))
    v, st, g = json.loads(bytes(state["python"].numpy()).decode())
    random.setstate((v, tuple(st), g))


def save_bundle(run: str | Path, kind: str, model_state: dict[str, torch.Tensor], config: dict,
                provenance: Provenance, train_state: dict | None = None, extra: dict | None = None,
                schema_version: int = 1) -> Path:
    run = Path(run)
    run.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model_state.items()}
    extra = dict(extra or {})
    refs = sorted(k for k, v in extra.items() if isinstance(v, os.PathLike))
    for k in refs:
        extra[k] = relative_to(extra[k], run)
    meta = {
        "kind": kind, "schema_version": schema_version, "provenance": json.loads(provenance.to_json()),
        "config": config, "extra": extra, "refs": refs, "model_sha256": sha256_state(tensors),
    }
    # One set: a training killed while saving (a session's end) keeps its last checkpoint whole,
    # instead of new weights beside a bundle.json whose hash refuses them.
    files = ["model.safetensors"] + (["train_state.pt"] if train_state is not None else []) + ["bundle.json"]
    with atomic_paths(*(run / f for f in files)) as tmps:
        save_file(tensors, str(tmps[0]))
        if train_state is not None:
            write_state(train_state, tmps[1], run / "train_state.pt")  # a full disk as OSError (motok.safeload)
        tmps[-1].write_text(strict_json(meta) + "\n", encoding="utf-8")
    publish_staged(run)  # a new run folder appears at its first complete checkpoint (motok.runfolder)
    return run


def sha256_state(tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for k in sorted(tensors):
        h.update(k.encode())
        h.update(tensors[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def read_meta(run: str | Path, kind: str | None = None) -> dict:
    """``bundle.json`` of ``run``, checked for kind and version (the weights are not read)."""
    run = Path(run)
    meta_path = run / "bundle.json"
    if not run.exists():
        raise MissingFileError(f"{run}: no such checkpoint bundle (the folder does not exist)")
    if not meta_path.is_file():
        raise CheckpointError(f"{run}: not a motok checkpoint bundle (no bundle.json)")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{meta_path}: not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{meta_path}: not a bundle description (a JSON object is expected)")
    found, version = meta.get("kind"), meta.get("schema_version")
    if kind is not None and found != kind:
        raise CheckpointError(f"{run}: expected a {kind} bundle, found kind {found!r}")
    if found in BUNDLE_KINDS and version not in BUNDLE_KINDS[found]:
        raise CheckpointError(f"{run}: {found} bundle schema version {version} is not supported "
                              f"(supported: {list(BUNDLE_KINDS[found])})")
    return meta


def read_weights(run: str | Path, meta: dict, verify: bool = True) -> dict[str, torch.Tensor]:
    """The tensors of ``run/model.safetensors``; with ``verify``, checked against the bundle's
    ``model_sha256`` (weights replaced, zeroed or damaged after training are refused)."""
    run = Path(run)
    path = run / "model.safetensors"
    if not path.is_file():
        raise CheckpointError(f"{run}: the bundle has no model.safetensors")
    try:
        state = load_file(str(path))
    except Exception as e:  # safetensors raises its own error types (and OSError) for damaged files
        raise CheckpointError(f"{path}: unreadable weights, the file is truncated or corrupted "
                              f"({type(e).__name__}: {e})") from None
    if verify:
        want = meta.get("model_sha256")
        if not want:
            raise CheckpointError(f"{run}: bundle.json records no model_sha256 to check the weights against")
        got = sha256_state(state)
        if got != want:
            raise CheckpointError(f"{run}: model.safetensors does not match the bundle (sha256 {got[:12]}, "
                                  f"bundle.json records {want[:12]}): the weights were changed or damaged "
                                  f"after training")
    return state


def load_bundle(run: str | Path, kind: str | None = None, with_train_state: bool = False):
    """Returns ``(meta, model_state, train_state_or_None)``; refuses wrong kinds and versions and
    weights that do not match ``model_sha256``."""
    run = Path(run)
    meta = read_meta(run, kind)
    state = read_weights(run, meta)
    train_state = None
    if with_train_state:
        p = run / "train_state.pt"
        if not p.exists():
            raise CheckpointError(f"{run}: no train_state.pt to resume from")
        if (refused := state_refusal(p)) is not None:  # a pickle is never opened (motok.safeload)
            raise CheckpointError(refused)
        try:
            train_state = torch.load(p, weights_only=True, map_location="cpu")  # a GPU run resumes or loads anywhere
        except Exception as e:  # pickle, zip and torch errors: say which
            raise CheckpointError(state_refusal(p, e)) from None
        changed = arithmetic_differences((meta.get("provenance") or {}).get("machine"))
        if changed:  # resuming is still right; only repeating the run to the digit is off
            info(f"[bold yellow]warning:[/] {run}: resuming on other arithmetic than the checkpoint was made "
                 f"with, so the run will not repeat an uninterrupted one to the digit ({'; '.join(changed)})")
    return meta, state, train_state


def load_model(run: str | Path, kind: str, build, device: str | torch.device = "cpu"):
    """``(model, meta)``: the network ``build(meta)`` makes for the bundle in ``run``, with its
    checked weights, on ``device`` and in eval mode (the loaders of the tokenizer and the GPT)."""
    meta, state, _ = load_bundle(run, kind)
    model = build(meta)
    model.load_state_dict(state)
    return model.to(device).eval(), meta


# --------------------------------------------------------------------------- references

def relative_to(path: str | os.PathLike, folder: str | os.PathLike) -> str:
    """``path`` as seen from ``folder`` (both made absolute first), with forward slashes."""
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(folder))).as_posix()


def resolve_ref(value: str | os.PathLike, base: str | os.PathLike) -> list[Path]:
    """Where a stored path may point, most likely first: relative to ``base`` (how motok writes
    them), then as written, then under each folder above ``base``: older files stored paths
    relative to the directory they were made in, which was usually one of those folders."""
    p = Path(value)
    if p.is_absolute():
        return [p]
    places = [Path(os.path.normpath(Path(base) / p)), p]
    if not p.parts or p.parts[0] != "..":
        places += [q / p for q in Path(os.path.abspath(base)).parents]
    return list(dict.fromkeys(places))


def bundle_ref(run: str | Path, meta: dict, key: str, *, required: bool = True, hint: str = "") -> Path | None:
    """The file ``meta["extra"][key]`` of the bundle ``run`` refers to. Missing: ``None`` when not
    ``required``, else an error naming the bundle, the reference and where it was looked for."""
    value = meta.get("extra", {}).get(key)
    if not value:
        if required:
            raise CheckpointError(f"{run}: bundle.json records no {key}{hint}")
        return None
    places = resolve_ref(value, run)
    for p in places:
        if p.exists():
            return p
    if not required:
        return None
    raise MissingFileError(f"{run}: its {key} {value!r} does not exist (looked for {places[0]}"
                           f"{' and ' + str(places[1]) if len(places) > 1 else ''}){hint}")


class MetricsLog:
    """Append-only JSONL of training metrics; on resume, lines past the resumed step are dropped."""

    def __init__(self, path: str | Path, resume_from: int | None = None, key: str = "iteration"):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if resume_from is None:
            self.path.write_text("")
        elif self.path.exists():
            kept = [ln for ln in self.path.read_text().splitlines()
                    if ln.strip() and json.loads(ln).get(key, 0) <= resume_from]
            self.path.write_text("".join(ln + "\n" for ln in kept))

    def log(self, record: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(record, default=float) + "\n")
