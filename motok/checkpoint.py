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

Writes go to temporary names and are renamed into place, model first and ``bundle.json``
last, so a bundle whose ``bundle.json`` exists is complete.
"""

from __future__ import annotations

import hashlib
import json
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from motok.artifacts import Provenance
from motok.atomic import atomic_path
from motok.errors import MotokError

BUNDLE_KINDS: dict[str, tuple[int, ...]] = {}  # kind -> supported versions; stages register theirs


class CheckpointError(MotokError, ValueError):
    pass


def register_kind(kind: str, versions: tuple[int, ...] = (1,)) -> None:
    BUNDLE_KINDS[kind] = versions


def rng_state() -> dict[str, Any]:
    return {
        "torch": torch.get_rng_state(),
        "numpy": torch.from_numpy(np.frombuffer(json.dumps(_np_state()).encode(), dtype=np.uint8).copy()),
        "python": torch.from_numpy(np.frombuffer(json.dumps(_py_state()).encode(), dtype=np.uint8).copy()),
    }


def _np_state():
    s = np.random.get_state()
    return [s[0], s[1].tolist(), int(s[2]), int(s[3]), float(s[4])]


def _py_state():
    v, state, g = random.getstate()
    return [v, list(state), g]


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
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
    with atomic_path(run / "model.safetensors") as tmp:
        save_file(tensors, str(tmp))
    if train_state is not None:
        with atomic_path(run / "train_state.pt") as tmp:
            torch.save(train_state, tmp)
    meta = {
        "kind": kind, "schema_version": schema_version, "provenance": json.loads(provenance.to_json()),
        "config": config, "extra": extra or {}, "model_sha256": sha256_state(tensors),
    }
    with atomic_path(run / "bundle.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2, default=str))
    return run


def sha256_state(tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for k in sorted(tensors):
        h.update(k.encode())
        h.update(tensors[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def load_bundle(run: str | Path, kind: str | None = None, with_train_state: bool = False):
    """Returns ``(meta, model_state, train_state_or_None)``; refuses wrong kinds and versions."""
    run = Path(run)
    meta_path = run / "bundle.json"
    if not meta_path.exists():
        raise CheckpointError(f"{run}: not a motok checkpoint bundle (no bundle.json)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{meta_path}: not valid JSON ({e})") from None
    found, version = meta.get("kind"), meta.get("schema_version")
    if kind is not None and found != kind:
        raise CheckpointError(f"{run}: expected a {kind} bundle, found kind {found!r}")
    if found in BUNDLE_KINDS and version not in BUNDLE_KINDS[found]:
        raise CheckpointError(f"{run}: {found} bundle schema version {version} is not supported "
                              f"(supported: {list(BUNDLE_KINDS[found])})")
    state = load_file(str(run / "model.safetensors"))
    train_state = None
    if with_train_state:
        p = run / "train_state.pt"
        if not p.exists():
            raise CheckpointError(f"{run}: no train_state.pt to resume from")
        train_state = torch.load(p, weights_only=True)
    return meta, state, train_state


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
