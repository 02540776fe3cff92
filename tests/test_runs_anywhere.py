"""Runs that work from anywhere: references stored relative to the bundle (old cwd-relative ones
still found), a missing reference named, weights verified against model_sha256 on every load,
damaged weights a clear error, and `motok info RUN/` for any checkpoint folder."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from motok.checkpoint import CheckpointError, bundle_ref, load_bundle, read_meta
from motok.cli.main import app
from motok.errors import MissingFileError

from tiny_runs import tree  # noqa: F401  (a fixture)

pytestmark = pytest.mark.usefixtures("one_thread")
runner = CliRunner()


def _sample(gpt, out, *extra):
    return runner.invoke(app, ["-q", "gpt", "sample", "-g", str(gpt), "--text", "a person walks", "--seconds", "1",
                               "-o", str(out), "--json", *extra])


def test_references_are_relative_to_the_bundle_and_work_from_anywhere(tree, tmp_path, monkeypatch):
    meta = read_meta(tree / "gpt")
    assert meta["refs"] == ["text_cache", "tokenizer", "tokens"]
    assert meta["extra"]["tokenizer"] == "../tok" and meta["extra"]["tokens"] == "../tokens.h5"
    assert read_meta(tree / "tok")["extra"]["dataset"].startswith("..")  # the dataset, seen from the run
    monkeypatch.chdir(tmp_path)  # not where the runs were made
    r = _sample(tree / "gpt", tmp_path / "a.h5")
    assert r.exit_code == 0, r.output
    moved = tmp_path / "elsewhere" / "runs"
    shutil.copytree(tree, moved)  # the whole tree moved: still complete
    r = _sample(moved / "gpt", tmp_path / "b.h5")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["tokens"] == json.loads(_sample(tree / "gpt", tmp_path / "c.h5").stdout)["tokens"]


def test_old_cwd_relative_references_are_still_found(tree, tmp_path):
    old = tmp_path / "project"
    shutil.copytree(tree, old / "runs")
    meta = json.loads((old / "runs/gpt/bundle.json").read_text())
    meta.pop("refs")
    meta["extra"].update(tokenizer="runs/tok", tokens="runs/tokens.h5", text_cache="runs/tokens.text-embeddings.h5")
    (old / "runs/gpt/bundle.json").write_text(json.dumps(meta))
    assert bundle_ref(old / "runs/gpt", meta, "tokenizer") == old / "runs/tok"  # found under a folder above
    r = _sample(old / "runs/gpt", tmp_path / "a.h5")
    assert r.exit_code == 0, r.output


def test_a_missing_reference_is_named(tree, tmp_path):
    lone = tmp_path / "lone"
    shutil.copytree(tree / "gpt", lone / "gpt")
    with pytest.raises(MissingFileError, match=r"its tokenizer '\.\./tok' does not exist.*--tokenizer"):
        bundle_ref(lone / "gpt", read_meta(lone / "gpt"), "tokenizer", hint="; pass --tokenizer")
    r = _sample(lone / "gpt", tmp_path / "a.h5")
    assert r.exit_code == 2 and "its tokenizer '../tok' does not exist" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1
    r = _sample(lone / "gpt", tmp_path / "a.h5", "-t", str(tree / "tok"))  # an explicit tokenizer instead
    assert r.exit_code == 0, r.output


@pytest.mark.parametrize("damage", ["zeroed", "truncated", "missing"])
def test_weights_are_verified_on_load(tree, tmp_path, damage):
    runs = tmp_path / "runs"
    shutil.copytree(tree, runs)
    weights = runs / "tok/model.safetensors"
    if damage == "zeroed":  # a valid file whose tensors are not the trained ones
        save_file({k: torch.zeros_like(v) for k, v in load_file(weights).items()}, weights)
        says = "does not match the bundle"
    elif damage == "truncated":
        weights.write_bytes(weights.read_bytes()[:1000])
        says = "truncated or corrupted"
    else:
        weights.unlink()
        says = "no model.safetensors"
    with pytest.raises(CheckpointError, match=says):
        load_bundle(runs / "tok")
    r = _sample(runs / "gpt", tmp_path / "a.h5")
    assert r.exit_code == 2 and says in r.output and str(runs / "tok") in r.output, r.output
    assert "Traceback" not in r.output and not (tmp_path / "a.h5").exists()
    r = runner.invoke(app, ["info", str(runs / "tok"), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["weights"] in ("REFUSED", "missing"), r.output


@pytest.mark.parametrize("run", ["tok", "gpt"])
def test_info_on_a_checkpoint_folder(tree, run):
    r = runner.invoke(app, ["info", str(tree / run), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["kind"] == {"tok": "tokenizer", "gpt": "gpt"}[run] and d["schema_version"] == 1
    assert d["provenance"]["command"] == "pytest" and d["config"] and d["weights"].startswith("verified")
    assert d["parameters"] == sum(v.numel() for v in load_file(tree / run / "model.safetensors").values())
    assert all(len(t["shape"]) >= 1 for t in d["tensors"].values())
    assert all(r["found"] for r in d["references"].values())
    r = runner.invoke(app, ["info", str(tree / run)], terminal_width=200)
    assert r.exit_code == 0 and "parameters" in r.stdout and "verified" in r.stdout


def test_info_on_things_that_are_not_quite_artifacts(tmp_path):
    import h5py
    p = tmp_path / "kind_only.h5"
    with h5py.File(p, "w") as f:
        f.attrs["kind"], f.attrs["schema_version"] = "motion", 1
    r = runner.invoke(app, ["info", str(p)])
    assert r.exit_code == 0 and "without a provenance attribute" in r.output, r.output
    (tmp_path / "empty_dir").mkdir()
    r = runner.invoke(app, ["info", str(tmp_path / "empty_dir")])
    assert r.exit_code == 2 and "not a motok checkpoint bundle" in r.output
