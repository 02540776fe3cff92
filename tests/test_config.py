"""Recipes and overrides fill config dataclasses, and reject what they don't know."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from motok.config import ConfigError, load_config


@dataclass
class Optim:
    lr: float = 1e-3
    betas: list[float] = field(default_factory=lambda: [0.9, 0.99])


@dataclass
class Cfg:
    name: str = "x"
    steps: int = 10
    flag: bool = False
    maybe: int | None = None
    optim: Optim = field(default_factory=Optim)


def test_recipe_then_overrides(tmp_path):
    r = tmp_path / "r.yaml"
    r.write_text("steps: 20\noptim:\n  lr: 0.01\n")
    cfg = load_config(Cfg, r, ["optim.betas=[0.5, 0.9]", "flag=true", "maybe=3"])
    assert cfg.steps == 20 and cfg.optim.lr == 0.01 and cfg.optim.betas == [0.5, 0.9]
    assert cfg.flag is True and cfg.maybe == 3 and isinstance(cfg.optim, Optim)


def test_unknown_and_mistyped_keys(tmp_path):
    r = tmp_path / "r.yaml"
    r.write_text("stepz: 20\n")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['stepz'\]"):
        load_config(Cfg, r)
    with pytest.raises(ConfigError, match="expected an integer"):
        load_config(Cfg, None, ["steps=ten"])
    with pytest.raises(ConfigError, match="expected key=value"):
        load_config(Cfg, None, ["steps"])
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Cfg, tmp_path / "missing.yaml")


def test_base_is_not_mutated_and_exponents_parse():
    base = {"name": "x", "steps": 1, "flag": False, "maybe": None, "optim": {"lr": 0.1, "betas": [0.9, 0.99]}}
    cfg = load_config(Cfg, None, ["optim.lr=1e-3"], base=base)
    assert cfg.optim.lr == 1e-3 and base["optim"]["lr"] == 0.1

