"""``motok eval``: the text-motion evaluator and the T2M metric suite (argument parsing only)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(help="Evaluation: train a text-motion evaluator, the T2M metrics, reconstruction and "
                       "physical plausibility.", no_args_is_help=True)

Recipe = typer.Option(None, "--recipe", help="YAML recipe (recipes/eval/).")
Sets = typer.Option([], "--set", help="Override a config key: --set key=value (repeatable).")
JsonOut = typer.Option(False, "--json", help="Print the result as JSON.")


def _run(fn, *args, **kwargs):
    """User errors become one line and exit code 2 (the root CLI's convention)."""
    from motok.checkpoint import CheckpointError
    from motok.eval.evaluator import EvaluatorError
    from motok.cli.main import run
    return run(fn, *args, catch=(CheckpointError, EvaluatorError, ValueError), **kwargs)


def _flat(summary: dict, as_json: bool, title: str):
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    from rich.table import Table

    from motok.progress import console
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        if isinstance(v, dict):
            v = "  ".join(f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}" for a, b in v.items())
        t.add_row(k, f"{v:.4g}" if isinstance(v, float) else str(v))
    console.print(t)


@app.command("train-evaluator")
def train_evaluator(
    data: Path = typer.Option(..., "--data", help="A motion-dataset with captions (.h5)."),
    out: Path = typer.Option(..., "-o", "--out", help="Run folder (checkpoint bundle + metrics.jsonl)."),
    recipe: Optional[Path] = Recipe, sets: list[str] = Sets, as_json: bool = JsonOut,
):
    """Train the contrastive text-motion co-embedding; reports retrieval on the test split vs chance."""
    from motok.eval.evaluator import resolve_config
    from motok.eval.evaluator import train_evaluator as _train
    cfg = _run(resolve_config, recipe, sets)
    _flat(_run(_train, cfg, data, out), as_json, "eval train-evaluator")


def _t2m(evaluator: Path, data: Path, tokenizer: Optional[Path], gpt: Optional[Path], motions: list[Path],
         gt_length: bool, split: Optional[str], repeats: Optional[int], no_real: bool, save_generated: Optional[Path],
         out_json: Optional[Path], out_md: Optional[Path], recipe: Optional[Path], sets: list[str], as_json: bool):
    from motok.config import load_config
    from motok.eval.report import T2MConfig, markdown, rich_table, t2m
    from motok.progress import console
    flags = {"split": split, "repeats": repeats}
    overrides = list(sets) + [f"{k}={json.dumps(v)}" for k, v in flags.items() if v is not None]
    overrides += ["gt_length=true"] * gt_length
    cfg = _run(load_config, T2MConfig, recipe, overrides)
    report = _run(t2m, evaluator, data, cfg, tokenizer=tokenizer, gpt=gpt, motions=motions,
                  save_generated=save_generated, real=not no_real)
    if out_json is not None:
        out_json.parent.mkdir(parents=True, exist_ok=True)
        out_json.write_text(json.dumps(report, indent=2, default=str))
    if out_md is not None:
        out_md.parent.mkdir(parents=True, exist_ok=True)
        out_md.write_text(markdown(report) + "\n")
    if as_json:
        typer.echo(json.dumps(report, indent=2, default=str))
    else:
        console.print(rich_table(report))
        console.print(f"{report['seconds']} s; evaluator {report['evaluator']}")


def _t2m_command(
    evaluator: Path = typer.Option(..., "--evaluator", "-e", help="An evaluator run (from `eval train-evaluator`)."),
    data: Path = typer.Option(..., "--data", help="The motion-dataset (real motion of --split)."),
    tokenizer: Optional[Path] = typer.Option(None, "--tokenizer", "-t", help="Add the reconstruction row; "
                                             "with --gpt, the tokenizer that decodes its codes."),
    gpt: Optional[Path] = typer.Option(None, "--gpt", help="Add a generation row sampled from this GPT run."),
    motions: list[Path] = typer.Option([], "--motions", "-m", help="Add a row for any motion artifact (repeatable)."),
    gt_length: bool = typer.Option(False, "--gt-length", help="Generate at the ground-truth length, not until End."),
    split: Optional[str] = typer.Option(None, "--split", help="Split of --data (default test)."),
    repeats: Optional[int] = typer.Option(None, "--repeats", help="Repeats (default 20)."),
    no_real: bool = typer.Option(False, "--no-real", help="Skip the real-motion row."),
    save_generated: Optional[Path] = typer.Option(None, "--save-generated", help="Keep the --gpt samples here (.h5)."),
    out_json: Optional[Path] = typer.Option(None, "--out-json", help="Write the full report (JSON)."),
    out_md: Optional[Path] = typer.Option(None, "--out-md", help="Write the Markdown table."),
    recipe: Optional[Path] = Recipe, sets: list[str] = Sets, as_json: bool = JsonOut,
):
    """R-precision, FID, MM-Dist, Diversity, MModality (mean ± 95% CI over 20 repeats) and physical metrics."""
    _t2m(evaluator, data, tokenizer, gpt, motions, gt_length, split, repeats, no_real, save_generated, out_json,
         out_md, recipe, sets, as_json)


app.command("t2m")(_t2m_command)
app.command("fid", help="Alias of `t2m`.")(_t2m_command)


@app.command()
def recon(
    data: Path = typer.Option(..., "--data", help="The motion-dataset the reconstruction is compared with."),
    tokenizer: Optional[Path] = typer.Option(None, "--tokenizer", "-t", help="Reconstruct the split through it."),
    motions: Optional[Path] = typer.Option(None, "--motions", "-m", help="A reconstruction artifact (clips named "
                                           "as in --data, e.g. from `tokenize decode`)."),
    split: str = typer.Option("test", "--split"),
    num_codebooks: Optional[int] = typer.Option(None, "--num-codebooks"),
    as_json: bool = JsonOut,
):
    """MPJPE (mm, root-relative and global) and acceleration error of a reconstruction."""
    from motok.eval.report import recon as _recon
    _flat(_run(_recon, data, split, tokenizer, motions, num_codebooks), as_json, f"eval recon ({split})")


@app.command()
def physical(
    motion: Path = typer.Argument(..., help="Any motion or motion-dataset artifact."),
    split: Optional[str] = typer.Option(None, "--split", help="Only this split (datasets)."),
    contact_tolerance: Optional[float] = typer.Option(None, "--contact-tolerance",
                                                      help="m: a toe this close to its resting height is in contact "
                                                           "(default 0.01)."),
    skate_speed: Optional[float] = typer.Option(None, "--skate-speed",
                                                help="m/s: a faster contact step counts as skating (default 0.5)."),
    as_json: bool = JsonOut,
):
    """Foot skating, ground penetration, floating and jitter of every clip (frame-weighted)."""
    from motok.eval.physical import artifact_physical
    kw = {k: v for k, v in {"contact_tolerance": contact_tolerance, "skate_speed": skate_speed}.items() if v is not None}
    _flat(_run(artifact_physical, motion, split, **kw), as_json, "eval physical")
