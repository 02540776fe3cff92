"""``motok tokenize``: train, encode, decode and evaluate the motion tokenizer (argument parsing only)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(help="Motion tokenizer (T2M-GPT VQ-VAE): train, encode, decode, eval.", no_args_is_help=True)

Tokenizer = typer.Option(..., "--tokenizer", "-t", help="A tokenizer run folder (from `tokenize train`).")
NumCodebooks = typer.Option(None, "--num-codebooks", "-m", help="Use only the first M codebooks (residual VQ).")


def _run(fn, *args, **kwargs):
    """User errors become one line and exit code 2 (the root CLI's convention)."""
    from motok.checkpoint import CheckpointError
    from motok.tokenizer.train import TokenizerError
    from motok.cli.main import run
    return run(fn, *args, catch=(CheckpointError, TokenizerError), **kwargs)


def _report(summary: dict, as_json: bool, title: str):
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    from rich.table import Table

    from motok.progress import console
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        if k == "codebooks":
            continue
        t.add_row(k, f"{v:.4g}" if isinstance(v, float) else str(v))
    console.print(t)
    if summary.get("codebooks"):
        cb = Table(title="codebooks")
        for col in ("codebook", "usage", "perplexity", "used", "dead"):
            cb.add_column(col, justify="right")
        for c in summary["codebooks"]:
            cb.add_row(str(c["codebook"]), f"{c['usage']:.3f}", f"{c['perplexity']:.1f}", str(c["used"]), str(c["dead"]))
        console.print(cb)


@app.command()
def train(
    data: Path = typer.Option(..., "--data", help="Training motion-dataset (.h5)."),
    out: Path = typer.Option(..., "-o", "--out", help="Run folder (checkpoint bundle + metrics.jsonl)."),
    recipe: Optional[Path] = typer.Option(None, "--recipe", help="YAML recipe (recipes/tokenizer/)."),
    sets: list[str] = typer.Option([], "--set", help="Override a config key: --set key=value (repeatable)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in -o exactly where it stopped."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """Train the VQ-VAE; runs unchanged under `torchrun --nproc_per_node N --no-python motok ...`."""
    from motok.tokenizer.train import resolve_config
    from motok.tokenizer.train import train as _train
    cfg = _run(resolve_config, recipe, sets, out, resume)
    summary = _run(_train, cfg, data, out, resume=resume)
    import os
    if int(os.environ.get("RANK", "0")) == 0:
        _report(summary, as_json, "tokenize train")


@app.command()
def encode(
    tokenizer: Path = Tokenizer,
    data: Path = typer.Option(..., "--data", help="A motion or motion-dataset artifact."),
    out: Path = typer.Option(..., "-o", "--out", help="Output tokens artifact (.h5)."),
    split: Optional[str] = typer.Option(None, "--split", help="Only this split (default: every clip)."),
    num_codebooks: Optional[int] = NumCodebooks,
    as_json: bool = typer.Option(False, "--json"),
):
    """Motion -> code indices, per clip (frames // rate, codebooks), with the tokenizer's hash and config."""
    from motok.tokenizer.tokens import encode as _encode
    _report(_run(_encode, tokenizer, data, out, num_codebooks, split), as_json, "tokenize encode")


@app.command()
def decode(
    tokens: Path = typer.Argument(..., help="A tokens artifact."),
    tokenizer: Path = Tokenizer,
    out: Path = typer.Option(..., "-o", "--out", help="Output motion artifact (.h5)."),
    num_codebooks: Optional[int] = NumCodebooks,
    allow_mismatch: bool = typer.Option(False, "--allow-mismatch", help="Decode tokens made by another tokenizer."),
    as_json: bool = typer.Option(False, "--json"),
):
    """Tokens -> a motion artifact that `motok render` and `motok export bvh` accept."""
    from motok.tokenizer.tokens import decode as _decode
    _report(_run(_decode, tokenizer, tokens, out, num_codebooks, allow_mismatch), as_json, "tokenize decode")


@app.command("eval")
def evaluate(
    tokenizer: Path = Tokenizer,
    data: Path = typer.Option(..., "--data", help="A motion-dataset artifact."),
    split: str = typer.Option("test", "--split"),
    num_codebooks: Optional[int] = NumCodebooks,
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Reconstruction MPJPE (mm), acceleration error, per-codebook usage, perplexity and dead codes."""
    from motok.tokenizer.tokens import evaluate as _evaluate
    _report(_run(_evaluate, tokenizer, data, split, num_codebooks), as_json, f"tokenize eval ({split})")
