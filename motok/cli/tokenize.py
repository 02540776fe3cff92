"""``motok tokenize``: train, encode, decode and evaluate the motion tokenizer (argument parsing only)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (H5, JsonOut, Resume, Sets, data_option, number_option, output_option, recipe_option,
                              report, results, run, split_option)
from motok.cli.conventions import examples, renamed
from motok.cli.outputs import Force, train_into

app = typer.Typer(help="Motion tokenizer (T2M-GPT VQ-VAE): train, encode, decode, eval.", no_args_is_help=True)

Tokenizer = typer.Option(..., "--tokenizer", "-t", help="A tokenizer run folder (from `tokenize train`).")
NumCodebooks = number_option(None, "--codebooks", "-m", help="Use only the first M codebooks (residual VQ).",
                             within=">= 1")
Split = split_option("test", help="The split of --data to evaluate.")


def _report(summary: dict, as_json: bool, title: str):
    report(summary, as_json, title, hide=("codebooks",))
    if as_json or not summary.get("codebooks"):
        return
    from rich.table import Table

    cb = Table(title="codebooks")
    for col in ("codebook", "usage", "perplexity", "used", "dead"):
        cb.add_column(col, justify="right")
    for c in summary["codebooks"]:
        cb.add_row(str(c["codebook"]), f"{c['usage']:.3f}", f"{c['perplexity']:.1f}", str(c["used"]), str(c["dead"]))
    results.print(cb)


@app.command(epilog=examples(
    "motok tokenize train -d runs/bandai2.h5 --recipe recipes/tokenizer/default.yaml -o runs/tok",
    "motok tokenize train -d runs/bandai2.h5 --recipe recipes/tokenizer/demo.yaml --set iterations=50 -o runs/tok"))
def train(
    data: Path = data_option("Training motion-dataset (.h5)."),
    out: Path = output_option(help="Run folder (checkpoint bundle + metrics.jsonl).", folder=True),
    recipe: Optional[Path] = recipe_option("recipes/tokenizer/"), sets: list[str] = Sets,
    resume: bool = Resume, force: bool = Force, as_json: bool = JsonOut,
):
    """Train the VQ-VAE; runs unchanged under `torchrun --nproc_per_node N --no-python motok ...`."""
    from motok.tokenizer.train import resolve_config
    from motok.tokenizer.train import train as _train
    cfg = run(resolve_config, recipe, sets, out, resume)
    summary = train_into(out, lambda where: _train(cfg, data, where, resume=resume), resume=resume, force=force)
    if int(os.environ.get("RANK", "0")) == 0:  # every torchrun rank returns the summary; one prints it
        _report(summary, as_json, "tokenize train")


@app.command(epilog=examples("motok tokenize encode -t runs/tok -d runs/bandai2.h5 -o runs/tokens.h5",
                             "motok tokenize encode -t runs/rvq -d runs/bandai2.h5 -m 2 --split test -o test.h5"))
@renamed(num_codebooks="--codebooks")
def encode(
    tokenizer: Path = Tokenizer,
    data: Path = data_option("A motion or motion-dataset artifact."),
    out: Path = output_option(help="Output tokens artifact (.h5).", suffixes=H5),
    split: Optional[str] = split_option(help="Only this split (default: every clip)."),
    num_codebooks: Optional[int] = NumCodebooks, as_json: bool = JsonOut,
):
    """Motion -> code indices, per clip (frames // rate, codebooks), with the tokenizer's hash and config."""
    from motok.tokenizer.tokens import encode as _encode
    _report(run(_encode, tokenizer, data, out, num_codebooks, split), as_json, "tokenize encode")


@app.command(epilog=examples("motok tokenize decode -d runs/tokens.h5 -t runs/tok -o recon.h5"))
@renamed(positional="--data", num_codebooks="--codebooks")
def decode(
    tokens: Path = data_option("A tokens artifact (from `tokenize encode`)."),
    tokenizer: Path = Tokenizer,
    out: Path = output_option(help="Output motion artifact (.h5).", suffixes=H5),
    num_codebooks: Optional[int] = NumCodebooks,
    allow_mismatch: bool = typer.Option(False, "--allow-mismatch", help="Decode tokens made by another tokenizer."),
    as_json: bool = JsonOut,
):
    """Tokens -> a motion artifact that `motok render` and `motok export bvh` accept."""
    from motok.tokenizer.tokens import decode as _decode
    _report(run(_decode, tokenizer, tokens, out, num_codebooks, allow_mismatch), as_json, "tokenize decode")


@app.command("eval", epilog=examples("motok tokenize eval -t runs/tok -d runs/bandai2.h5 --split test",
                                     "motok tokenize eval -t runs/rvq -d runs/bandai2.h5 -m 1 --json"))
@renamed(num_codebooks="--codebooks")
def evaluate(
    tokenizer: Path = Tokenizer,
    data: Path = data_option("A motion-dataset artifact."),
    split: str = Split,
    num_codebooks: Optional[int] = NumCodebooks, as_json: bool = JsonOut,
):
    """Reconstruction MPJPE (mm), acceleration error, per-codebook usage, perplexity and dead codes."""
    from motok.tokenizer.tokens import evaluate as _evaluate
    _report(run(_evaluate, tokenizer, data, split, num_codebooks), as_json, f"tokenize eval ({split})")
