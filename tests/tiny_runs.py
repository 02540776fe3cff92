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


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """The reference-library cache of a module's runs, away from the user's ~/.cache."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MOTOK_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.fixture(scope="module")
def controllers(cache, hum, small_dataset, tmp_path_factory):
    """``(prior, expert)`` folders: a 2-iteration hybrid prior and the 1-iteration expert it was distilled from."""
    from motok.sim.reference import load_library

    lib = load_library(hum, small_dataset, clips=[0, 1, 2])
    root = tmp_path_factory.mktemp("t2p-runs")
    return tiny_prior_bundle(root, hum, lib, small_dataset), root / "expert"


def small_prior_config(kind: str):
    from motok.control.priors.model import PriorConfig

    return PriorConfig(kind=kind, latent_dim=8, posterior_hidden=[16], prior_hidden=[16], decoder_hidden=[16],
                       num_codebooks=4, codebook_size=16, vq_codebook_size=32, kmeans_init=False)


def tiny_prior_bundle(root, hum, lib, data, kind: str = "hybrid", target_filter: float | None = None):
    """A ``kind`` prior (4 codebooks of 16 codes when residual), distilled for 2 iterations from a
    1-iteration expert (trained through ``target_filter``): untrained, but a real bundle with every
    part its readers need. Returns the prior's folder (``root/prior``; the expert is ``root/expert``)."""
    from motok.control.priors.model import DistillConfig
    from motok.control.priors.distill import train as distill
    from motok.control.expert.model import ExpertConfig
    from motok.control.expert.train import train as train_expert

    ecfg = ExpertConfig(seed=0, iterations=1, save_every=1000)
    ecfg.env.num_envs, ecfg.env.nthread, ecfg.ppo.horizon, ecfg.ppo.minibatch_size = 4, 1, 8, 32
    ecfg.net.encoder = ecfg.net.decoder = ecfg.net.value = [16]
    ecfg.net.latent_dim = 8
    ecfg.amp.enabled = False
    ecfg.action.base, ecfg.task.termination = "reference", "mean"
    ecfg.env.target_filter = target_filter
    train_expert(ecfg, root / "expert", hum, lib, data=data)
    cfg = DistillConfig(seed=0, iterations=2, save_every=1000, horizon=8, epochs=1, minibatch_size=32)
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.task.termination = "mean"
    cfg.prior = small_prior_config(kind)
    distill(cfg, root / "prior", root / "expert", lib, data=data)
    return root / "prior"
