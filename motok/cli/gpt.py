"""``motok gpt``: train the text-to-motion transformer and sample motions from text (argument parsing only)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import JsonOut, Resume, Sets, existing, input_option, recipe_option, report, run

app = typer.Typer(help="Text to motion (T2M-GPT transformer over tokenizer codes): train, sample.",
                  no_args_is_help=True)


def _report(summary: dict, as_json: bool, title: str):
    files = [summary["output"]] if "names" in summary else []
    files += summary.get("render", []) + summary.get("bvh", [])
    report(summary, as_json, title, hide=("render", "bvh", "names") + (("output",) if files else ()))
    if as_json:
        return
    from rich.markup import escape

    from motok.progress import console
    # Paths unwrapped, one per line, so they can be copied whatever the terminal width.
    for f in files:
        console.print(f"wrote {escape(str(f))}", soft_wrap=True, highlight=False)


@app.command()
def train(
    tokens: Path = input_option("--tokens", help="A tokens artifact (from `tokenize encode`) with captions."),
    out: Path = typer.Option(..., "-o", "--out", help="Run folder (checkpoint bundle + metrics.jsonl)."),
    recipe: Optional[Path] = recipe_option("recipes/gpt/"), sets: list[str] = Sets,
    resume: bool = Resume, as_json: bool = JsonOut,
):
    """Train the GPT; runs unchanged under `torchrun --nproc_per_node N --no-python motok ...`."""
    from motok.gpt.train import resolve_config
    from motok.gpt.train import train as _train
    cfg = run(resolve_config, recipe, sets, out, resume)
    summary = run(_train, cfg, tokens, out, resume=resume)
    if int(os.environ.get("RANK", "0")) == 0:  # every torchrun rank returns the summary; one prints it
        _report(summary, as_json, "gpt train")


@app.command()
def sample(
    gpt: Path = typer.Option(..., "--gpt", help="A GPT run folder (from `gpt train`)."),
    text: list[str] = typer.Option([], "--text", help="A sentence (repeatable)."),
    texts_file: Optional[Path] = typer.Option(None, "--texts-file", help="One sentence per line.", callback=existing),
    num_samples: int = typer.Option(1, "-n", "--num-samples", help="Samples per text."),
    seed: int = typer.Option(0, "--seed", help="Sample j uses seed + j."),
    temperature: float = typer.Option(1.0, "--temperature"),
    top_k: Optional[int] = typer.Option(None, "--top-k", help="Keep the k most likely codes."),
    top_p: Optional[float] = typer.Option(None, "--top-p", help="Nucleus: keep the codes holding p of the mass."),
    argmax: bool = typer.Option(False, "--argmax", help="Greedy: the most likely code at each step."),
    seconds: Optional[float] = typer.Option(None, "--seconds", help="Target length: End masked before, forced at."),
    out: Path = typer.Option(..., "-o", "--out", help="Output motion artifact (.h5)."),
    render: Optional[Path] = typer.Option(None, "--render", help="Also render OUT.gif/.mp4/.png (one per clip)."),
    bvh: Optional[Path] = typer.Option(None, "--bvh", help="Also export OUT.bvh (one per clip)."),
    tokenizer: Optional[Path] = typer.Option(None, "--tokenizer", help="Tokenizer run (default: the GPT's own)."),
    allow_mismatch: bool = typer.Option(False, "--allow-mismatch", help="Decode with another tokenizer."),
    as_json: bool = JsonOut,
):
    """Text -> codes -> motion artifact (and optional GIF/BVH); prints where everything went."""
    from motok.gpt.sample import sample as _sample
    texts = list(text)
    if texts_file is not None:
        texts += [ln.strip() for ln in texts_file.read_text().splitlines() if ln.strip()]
    summary = run(_sample, gpt, texts, out, num_samples=num_samples, seed=seed, temperature=temperature,
                  top_k=top_k, top_p=top_p, argmax=argmax, seconds=seconds, render=render, bvh=bvh,
                  tokenizer=tokenizer, allow_mismatch=allow_mismatch)
    _report(summary, as_json, "gpt sample")
