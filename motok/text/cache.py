"""Caption embeddings computed once and kept in a ``text-embeddings`` artifact.

The GPT never runs its text encoder inside the training loop (T2M-GPT Sec. 3.2 freezes the
encoder, so its outputs are constants): every caption is embedded once, up front, and looked up
by ``(encoder name, exact caption text)``. Layout (HDF5, see docs/gpt.md)::

    /encoders/<name>/text        (n,) utf-8 strings, unique
    /encoders/<name>/embedding   (n, d) float32; attrs dim

New captions are appended by rewriting the file atomically, so a reader never sees half a file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motok.artifacts import Provenance, command_line, open_artifact, read_strings, write_artifact, write_strings
from motok.text.encoders import get_encoder, overlong

KIND = "text-embeddings"


class TextEmbeddingCache:
    """An in-memory view of a cache file; ``hits``/``misses`` count lookups since it was opened."""

    def __init__(self, path: str | Path | None):
        self.path = Path(path) if path is not None else None
        self.table: dict[str, dict[str, np.ndarray]] = {}
        self.hits = self.misses = 0
        self.truncated: dict[str, int] = {}  # text -> its length in encoder tokens, past the window
        if self.path is not None and self.path.exists():
            with open_artifact(self.path, KIND) as f:
                for name, g in f["encoders"].items():
                    emb = g["embedding"][()]
                    self.table[name] = dict(zip(read_strings(g["text"]), emb))

    def __contains__(self, key: tuple[str, str]) -> bool:
        name, text = key
        return text in self.table.get(name, {})

    def embed(self, texts: list[str], encoder: str = "minilm", write: bool = True) -> np.ndarray:
        """Embeddings ``(len(texts), d)`` float32; only captions not yet cached reach the encoder."""
        known = self.table.setdefault(encoder, {})
        missing = list(dict.fromkeys(t for t in texts if t not in known))
        # A miss is one encoder call per distinct new caption; every other lookup is a hit.
        self.misses += len(missing)
        self.hits += len(texts) - len(missing)
        if missing:
            enc = get_encoder(encoder)
            self.truncated.update(overlong(enc, missing))
            vecs = enc.encode(missing)
            known.update(zip(missing, vecs.astype(np.float32)))
            if write and self.path is not None:
                self.save()
        if not texts:
            return np.zeros((0, self.dim(encoder)), dtype=np.float32)
        return np.stack([known[t] for t in texts]).astype(np.float32)

    def dim(self, encoder: str) -> int:
        rows = self.table.get(encoder)
        return len(next(iter(rows.values()))) if rows else int(get_encoder(encoder).dim)

    def save(self) -> Path:
        prov = Provenance(command=command_line(),
                          config={"encoders": {k: len(v) for k, v in self.table.items()}})
        with write_artifact(self.path, KIND, prov) as f:
            root = f.create_group("encoders")
            for name, rows in sorted(self.table.items()):
                if not rows:
                    continue
                g = root.create_group(name)
                write_strings(g, "text", list(rows))
                emb = np.stack(list(rows.values())).astype(np.float32)
                g.create_dataset("embedding", data=emb)
                g.attrs["dim"] = emb.shape[1]
        return self.path


def embed_texts(texts: list[str], encoder: str = "minilm", cache: str | Path | None = None) -> np.ndarray:
    """One-shot helper: embed ``texts`` through the cache file ``cache`` (created or extended)."""
    return TextEmbeddingCache(cache).embed(list(texts), encoder)
