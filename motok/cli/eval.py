"""``motok eval``: the text-motion evaluator and the T2M metric suite (argument parsing only)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (H5, JsonOut, Sets, clips_option, data_option, existing, fail, number_option,
                              output_option, print_json, recipe_option, report, results, run, split_option)
from motok.cli.conventions import examples, renamed
from motok.cli.outputs import Force, train_into

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
GPT = "motok.gpt.model:TrainConfig"
T2M = "motok.eval.protocol:T2MConfig"

app = typer.Typer(help="Evaluation: train a text-motion evaluator, the T2M metrics, reconstruction and "
                       "physical plausibility.", no_args_is_help=True)

Recipe = recipe_option("recipes/eval/")


@app.command("train-evaluator", epilog=examples(
    "motok eval train-evaluator -d runs/bandai2.h5 -o runs/evaluator",
    "motok eval train-evaluator -d runs/bandai2.h5 --recipe recipes/eval/evaluator_bow.yaml -o runs/ev"))
def train_evaluator(
    data: Path = data_option("A motion-dataset with captions (.h5)."),
    out: Path = output_option(help="Run folder (checkpoint bundle + metrics.jsonl).", folder=True),
    recipe: Optional[Path] = Recipe, sets: list[str] = Sets, force: bool = Force, as_json: bool = JsonOut,
):
    """Train the contrastive text-motion co-embedding; reports retrieval on the test split vs chance."""
    from motok.eval.evaluator import resolve_config
    from motok.eval.evaluator import train_evaluator as _train
    cfg = run(resolve_config, recipe, sets)
    summary = train_into(out, lambda where: _train(cfg, data, where), force=force, resumable=False)
    report(summary, as_json, "eval train-evaluator")


# -m meant --motions here and --codebooks in `tokenize`: it keeps its old meaning here, hidden,
# for one release; after that it is --codebooks everywhere.
@renamed(out_json="--out", out_md="--out", m="--motions")
def _t2m_command(
    evaluator: Path = typer.Option(..., "--evaluator", "-e", help="An evaluator run (from `eval train-evaluator`)."),
    data: Path = data_option("The motion-dataset (real motion of --split)."),
    tokenizer: Optional[Path] = typer.Option(None, "--tokenizer", "-t", help="Add the reconstruction row; "
                                             "with --gpt, the tokenizer that decodes its codes."),
    gpt: Optional[Path] = typer.Option(None, "--gpt", "-g", help="Add a generation row sampled from this GPT run."),
    motions: list[Path] = typer.Option([], "--motions", metavar="PATH",
                                       help="Add a row for any motion artifact (repeatable).", callback=existing),
    gt_length: bool = typer.Option(False, "--gt-length", help="Generate at the ground-truth length, not until End."),
    split: Optional[str] = split_option(help="Split of --data (default test); --motions rows keep "
                                             "their clips of it and those without a split (GPT samples)."),
    repeats: Optional[int] = number_option(None, "--repeats", help="Repeats (default 20).", within=f"{T2M}.repeats"),
    captions: Optional[str] = typer.Option(None, "--captions", metavar="all|unseen",
                                           help="unseen: only the captions that do not occur word for word in "
                                                "the train split (clips without one are left out; default all)."),
    no_real: bool = typer.Option(False, "--no-real", help="Skip the real-motion row."),
    common: bool = typer.Option(False, "--common-clips", help="Rows that hold clips of the same names (a tracked "
                                "file and what it tracked) are scored on the names all of them hold."),
    to_end: bool = typer.Option(False, "--tracked-to-end", help="--motions rows written by `control track` keep "
                                "the clips played to their end; with --common-clips, the rows sharing their "
                                "clips follow."),
    save_generated: Optional[Path] = output_option("--save-generated", help="Keep the --gpt samples here (.h5).",
                                                   suffixes=H5, required=False),
    outs: list[Path] = output_option(help="Write the report: the full report to a .json, the table to a .md "
                                     "(repeatable).", suffixes=(".json", ".md"), required=False, default=[]),
    recipe: Optional[Path] = Recipe, sets: list[str] = Sets, as_json: bool = JsonOut,
):
    """R-precision, FID, MM-Dist, Diversity, MModality (mean ± 95% CI over 20 repeats) and physical metrics."""
    from motok.config import load_config
    from motok.eval.report import T2MConfig, rich_table, save_report, t2m
    out_json = [p for p in outs if p.suffix.lower() == ".json"]
    out_md = [p for p in outs if p.suffix.lower() == ".md"]
    if len(out_json) > 1 or len(out_md) > 1:
        fail("-o takes at most one .json and one .md")
    flags = {"split": split, "repeats": repeats, "captions": captions}
    overrides = list(sets) + [f"{k}={json.dumps(v)}" for k, v in flags.items() if v is not None]
    overrides += ["gt_length=true"] * gt_length + ["common_clips=true"] * common + ["tracked_to_end=true"] * to_end
    cfg = run(load_config, T2MConfig, recipe, overrides)
    rep = run(t2m, evaluator, data, cfg, tokenizer=tokenizer, gpt=gpt, motions=motions,
              save_generated=save_generated, real=not no_real)
    save_report(rep, (out_json or [None])[0], (out_md or [None])[0])
    if as_json:
        print_json(rep)
    else:
        results.print(rich_table(rep))
        results.print(f"{rep['seconds']} s; evaluator {rep['evaluator']}")


_T2M_EXAMPLES = examples(
    "motok eval t2m -e runs/evaluator -d runs/bandai2.h5 -t runs/tok -g runs/gpt -o t2m.json -o t2m.md",
    "motok eval t2m -e runs/evaluator -d runs/bandai2.h5 --motions walk_generated.h5 --repeats 5")
app.command("t2m", epilog=_T2M_EXAMPLES)(_t2m_command)
app.command("fid", help="Alias of `t2m`.", epilog=_T2M_EXAMPLES)(_t2m_command)


@app.command("captions", epilog=examples("motok eval captions -d runs/bandai2.h5",
                                         "motok eval captions -d runs/bandai2.h5 --split val --json"))
def captions_command(
    data: Path = data_option("A motion-dataset with captions and splits."),
    split: str = split_option("test", help="The evaluated split."),
    train_split: str = typer.Option("train", "--train-split", help="The split whose captions count as seen."),
    batch: int = number_option(32, "--batch", help="R-precision batch of the label-reader ceiling.",
                               within=f"{T2M}.batch"),
    as_json: bool = JsonOut,
):
    """Share of the split's captions that occur word for word in training, and the R-precision
    ceiling of a perfect label reader (no model involved)."""
    from motok.eval.captions import caption_report
    report(run(caption_report, data, split, train_split, batch), as_json, f"eval captions ({split} vs {train_split})")


@app.command(epilog=examples("motok eval recon -d runs/bandai2.h5 -t runs/tok --split test",
                             "motok eval recon -d runs/bandai2.h5 --motions recon.h5 --json"))
@renamed(m="--motions", num_codebooks="--codebooks")
def recon(
    data: Path = data_option("The motion-dataset the reconstruction is compared with."),
    tokenizer: Optional[Path] = typer.Option(None, "--tokenizer", "-t", help="Reconstruct the split through it."),
    motions: Optional[Path] = typer.Option(None, "--motions", help="A reconstruction artifact (clips named "
                                           "as in --data, e.g. from `tokenize decode`).", callback=existing),
    split: str = split_option("test", help="The split of --data to compare."),
    num_codebooks: Optional[int] = number_option(None, "--codebooks",
                                                 help="With --tokenizer: use only the first M codebooks.",
                                                 within=">= 1"),
    as_json: bool = JsonOut,
):
    """MPJPE (mm, root-relative and global) and acceleration error of a reconstruction."""
    from motok.eval.report import recon as _recon
    report(run(_recon, data, split, tokenizer, motions, num_codebooks), as_json, f"eval recon ({split})")


@app.command(epilog=examples("motok eval physical -d walk_generated.h5", "motok eval physical -d runs/bandai2.h5 "
                             "--split test --json"))
@renamed(positional="--data")
def physical(
    motion: Path = data_option("Any motion or motion-dataset artifact."),
    split: Optional[str] = split_option(help="Only this split (datasets)."),
    contact_tolerance: Optional[float] = number_option(None, "--contact-tolerance",
                                                       help="m: a toe this close to its resting height is in contact "
                                                           "(default 0.01).", within="> 0"),
    skate_speed: Optional[float] = number_option(None, "--skate-speed",
                                                 help="m/s: a faster contact step counts as skating (default 0.5).",
                                                 within="> 0"),
    as_json: bool = JsonOut,
):
    """Foot skating, ground penetration, floating and jitter of every clip (frame-weighted)."""
    from motok.eval.physical import artifact_physical
    kw = {k: v for k, v in {"contact_tolerance": contact_tolerance, "skate_speed": skate_speed}.items()
          if v is not None}
    report(run(artifact_physical, motion, split, **kw), as_json, "eval physical")


@app.command("motion-matching", epilog=examples(
    "motok eval motion-matching -d runs/bandai2.h5 --split train --heldout test --motions gen_hybrid_m1.h5 "
    "--motions gen_cont.h5 -o table1.json -o table1.md",
    "motok eval motion-matching -d runs/bandai2.h5 --motions gen.h5 --threshold 2.5 --json"))
def motion_matching(
    data: Path = data_option("The motion-dataset the generated transitions are matched against."),
    motions: list[Path] = typer.Option(..., "--motions", metavar="PATH", help="A generated motion artifact, one row "
                                       "each (repeatable).", callback=existing),
    clips: Optional[str] = clips_option(help="Only these clips of --data."),
    split: Optional[str] = split_option(help="Only this split of --data."),
    heldout: Optional[str] = typer.Option(None, "--heldout", metavar="SPLIT", help="Also match this split of --data, "
                                          "which the reference must not contain: its filtered rate checks the "
                                          "threshold on unseen clips."),
    threshold: Optional[float] = number_option(None, "--threshold", help="Filter distance, squared (default: derived "
                                               "from --data, leave-one-clip-out).", within="> 0"),
    percentile: float = number_option(99.0, "--percentile", help="Percentile of the dataset's leave-one-clip-out "
                                      "distances that is the threshold.", within="[0, 100]"),
    exact: bool = typer.Option(False, "--exact", help="Exact search (torch blocks) instead of the faiss IVF index: "
                               "the reference, ~10x slower."),
    queries: int = number_option(20000, "--threshold-queries", help="Dataset transitions the threshold is "
                                 "derived from.", within=">= 1"),
    outs: list[Path] = output_option(help="Write the report: all of it to a .json, the table to a .md "
                                     "(repeatable).", suffixes=(".json", ".md"), required=False, default=[]),
    as_json: bool = JsonOut,
):
    """Tables 1 and 4: squared distance to the nearest dataset transition (Eq. 8), filtered rate, falls, coverage,
    jitter, acceleration."""
    from motok.eval.motion_matching import COLUMNS, cells, save
    from motok.eval.motion_matching import motion_matching as _mm

    if sum(p.suffix.lower() == ".json" for p in outs) > 1 or sum(p.suffix.lower() == ".md" for p in outs) > 1:
        fail("-o takes at most one .json and one .md")
    rep = run(_mm, data, motions, clips=clips, split=split, heldout=heldout, threshold=threshold,
              percentile=percentile, queries=queries, exact=exact)
    run(save, rep, outs)
    if as_json:
        print_json(rep)
        return
    from rich.table import Table
    t = Table(title=f"motion matching against {data}" + (f" ({split})" if split else ""))
    t.add_column("motion", overflow="fold")
    for _, header, _ in COLUMNS:
        t.add_column(header, justify="right")
    for r in rep["rows"]:
        t.add_row(str(r["motion"]), *cells(r))
    t.add_row("dataset", *cells(rep["dataset"]))
    results.print(t)
    th = rep["threshold"]
    results.print(f"threshold {th['value']:.3f} ({th['definition']}); {rep['seconds']} s")
    for p in outs:
        results.print(f"wrote {p}", soft_wrap=True, highlight=False)


@app.command("labels", epilog=examples(
    "motok eval labels -d runs/bandai2.h5 --motions gen.h5",
    "motok eval labels -d runs/bandai2.h5 --gpt runs/gpt --retrieval minilm -o labels.json"))
def labels_command(
    data: Path = data_option("The motion-dataset: the classifier is fitted on its train split."),
    motions: list[Path] = typer.Option([], "--motions", metavar="PATH", callback=existing,
                                       help="Score a motion artifact (repeatable): each clip's content/style "
                                            "labels, or its caption, say what it should show."),
    gpt: Optional[Path] = typer.Option(None, "--gpt", "-g", help="Generate from the prompt sets with this GPT "
                                       "run and score it."),
    retrieval: Optional[str] = typer.Option(None, "--retrieval", metavar="ENCODER", help="Add the retrieval "
                                            "baseline: nearest training caption under ENCODER (minilm, mpnet, "
                                            "bow), its real motion."),
    prompts: str = typer.Option("train,heldout_wordings,paraphrases", "--prompts", help="Prompt sets of the "
                                "phrasing-held-out split (comma-separated)."),
    prompt_split: str = typer.Option("test", "--prompt-split", help="Split whose captions make the train and "
                                     "heldout_wordings prompts (val to choose settings; never tune on test)."),
    num_samples: int = number_option(1, "-n", "--num-samples", help="Samples per prompt with --gpt.", within=">= 1"),
    seed: int = number_option(0, "--seed", help="Sampling seed with --gpt.", within=">= 0"),
    guidance: Optional[float] = number_option(None, "--guidance", help="CFG scale with --gpt (default: the run's).",
                                              within=f"{GPT}.guidance"),
    snap: Optional[int] = number_option(None, "--snap", help="With --gpt: condition new sentences on their K nearest "
                                        "training captions (0 = off; default: the run's).", within=f"{GPT}.snap"),
    save_generated: Optional[Path] = output_option("--save-generated", help="Keep the --gpt samples (.h5).",
                                                   suffixes=H5, required=False),
    out: Optional[Path] = output_option(help="Write the report (.json).", suffixes=(".json",), required=False),
    text_cache: Optional[Path] = typer.Option(None, "--text-cache", help="Text-embeddings artifact for --retrieval."),
    classifier_cache: Optional[Path] = typer.Option(None, "--classifier-cache", help="Keep the fitted classifier in "
                                                    "this .npz and reuse it while data and settings are the same."),
    sets: list[str] = Sets, as_json: bool = JsonOut,
):
    """Label accuracy: a content/style classifier fitted on real train motion (its test accuracy is
    reported) applied to generated motion, per prompt set (docs/gpt.md)."""
    from motok.config import load_config
    from motok.eval.labels import LabelsConfig
    from motok.eval.prompted import labels_report, summary_lines
    cfg = run(load_config, LabelsConfig, None, sets)
    names = [p.strip() for p in prompts.split(",") if p.strip()]
    rep = run(labels_report, data, motions=motions, gpt=gpt, retrieval=retrieval, sets=names,
              samples=num_samples, seed=seed, guidance=guidance, save_generated=save_generated, cfg=cfg, out=out,
              prompt_split=prompt_split, text_cache=text_cache, classifier_cache=classifier_cache, snap=snap)
    if as_json:
        print_json(rep)
        return
    for line in summary_lines(rep):
        results.print(line, soft_wrap=True, highlight=False)
    results.print(f"{rep['seconds']} s")


@app.command("text-separation", epilog=examples(
    "motok eval text-separation --encoder minilm --encoder mpnet -d runs/bandai2.h5"))
def text_separation_command(
    encoders: list[str] = typer.Option(["minilm"], "--encoder", metavar="NAME", help="Text encoder (repeatable)."),
    data: Optional[Path] = data_option("A motion-dataset: adds the nearest-training-caption label accuracy per "
                                       "prompt set.", required=False),
    cache: Optional[Path] = typer.Option(None, "--text-cache", help="A text-embeddings artifact to reuse/extend."),
    as_json: bool = JsonOut,
):
    """Cosine similarities between sentences that differ only in left/right, one/both hands, walk/run,
    against other wordings of the same request (docs/gpt.md)."""
    from motok.eval.prompted import text_separation_report
    rep = run(text_separation_report, data, encoders, cache=cache)
    if as_json:
        print_json(rep)
        return
    for enc, row in rep["encoders"].items():
        for name, c in row["contrasts"].items():
            results.print(f"{enc} / {name}: same wording {c['same_wording']:.3f}, same meaning "
                          f"{c['same_meaning']:.3f}, margin {c['margin']:+.3f}, closer {c['closer_rate']:.2f}",
                          highlight=False)
        for s, acc in row.get("nearest_caption", {}).items():
            results.print(f"{enc} / nearest caption / {s}: content {acc['content']:.3f}"
                          + (f", style {acc['style']:.3f}" if acc["style"] is not None else ""), highlight=False)
