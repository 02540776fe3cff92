"""A tiny tree of real runs (tokenizer, tokens, GPT) for the tests of the command line, made the
way a user makes them: from the folder that holds runs/. Import ``tree`` into a test module to
use it (module scope: a few seconds per module)."""

from __future__ import annotations

import pytest

TINY_GPT = ["model.num_layers=1", "model.dim=32", "model.heads=2", "model.block_size=24", "text_encoder=bow",
            "batch_size=4", "log_every=2", "eval_every=2", "save_every=2", "threads=1", "iterations=2"]


@pytest.fixture(scope="module")
def tree(tmp_path_factory, small_dataset):
    """runs/{tok, tokens.h5, gpt}: a 4-iteration tokenizer and a 2-iteration GPT on the walk slice,
    made from inside the folder that holds runs/, as a user would."""
    import os

    from motok.gpt.train import resolve_config
    from motok.gpt.train import train as train_gpt
    from motok.quantize.base import QuantizerConfig
    from motok.tokenizer.model import ModelConfig
    from motok.tokenizer.tokens import encode
    from motok.tokenizer.train import TrainConfig
    from motok.tokenizer.train import train as train_tokenizer

    root = tmp_path_factory.mktemp("project")
    here = os.getcwd()
    os.chdir(root)
    try:
        cfg = TrainConfig(model=ModelConfig(width=32, depth=1), quantizer=QuantizerConfig(codebook_size=32, dim=16),
                          iterations=4, batch_size=8, window=32, log_every=2, save_every=4, threads=1)
        train_tokenizer(cfg, small_dataset, "runs/tok", command="pytest")
        encode("runs/tok", small_dataset, "runs/tokens.h5", command="pytest")
        train_gpt(resolve_config(None, TINY_GPT), "runs/tokens.h5", "runs/gpt", command="pytest")
    finally:
        os.chdir(here)
    return root / "runs"
