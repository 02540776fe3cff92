"""``motok gpt``: train the text-to-motion transformer and sample motions from text (argument parsing only)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (H5, JsonOut, Resume, Sets, clips_option, data_option, existing, fail, input_option,
                              number_option, output_option, recipe_option, report, results, run)
from motok.cli.conventions import examples, renamed
from motok.cli.outputs import Force, train_into

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
GPT = "motok.gpt.model:TrainConfig"

app = typer.Typer(help="Text to motion (T2M-GPT transformer over tokenizer codes): train, sample.",
                  no_args_is_help=True)

RENDER_SUFFIXES = (".gif", ".mp4", ".png")


def _report(summary: dict, as_json: bool, title: str):
    files = [summary["output"]] if "names" in summary else []
    files += summary.get("render", []) + summary.get("bvh", [])
    report(summary, as_json, title, hide=("render", "bvh", "names", "truncated") + (("output",) if files else ()))
    if as_json:
        return
    from rich.markup import escape

    # Paths unwrapped, one per line, so they can be copied whatever the terminal width.
    for f in files:
        results.print(f"wrote {escape(str(f))}", soft_wrap=True, highlight=False)


@app.command(epilog=examples(
    "motok gpt train -d runs/tokens.h5 --recipe recipes/gpt/default.yaml -o runs/gpt",
    "torchrun --nproc_per_node 2 --no-python motok gpt train -d runs/tokens.h5 -o runs/gpt"))
@renamed(tokens="--data")
def train(
    tokens: Path = data_option("A tokens artifact (from `tokenize encode`) with captions."),
    out: Path = output_option(help="Run folder (checkpoint bundle + metrics.jsonl).", folder=True),
    recipe: Optional[Path] = recipe_option("recipes/gpt/"), sets: list[str] = Sets,
    resume: bool = Resume, force: bool = Force, as_json: bool = JsonOut,
):
    """Train the GPT; runs unchanged under `torchrun --nproc_per_node N --no-python motok ...`."""
    from motok.gpt.train import resolve_config
    from motok.gpt.train import train as _train
    cfg = run(resolve_config, recipe, sets, out, resume)
    summary = train_into(out, lambda where: _train(cfg, tokens, where, resume=resume), resume=resume,
                         force=force)
    if int(os.environ.get("RANK", "0")) == 0:  # every torchrun rank returns the summary; one prints it
        _report(summary, as_json, "gpt train")


@app.command(epilog=examples(
    'motok gpt sample -g runs/gpt --text "a person walks forward" -n 4 -o walk.h5 --render walk.gif --bvh walk.bvh',
    'motok gpt sample -g runs/gpt --texts-file prompts.txt --seconds 4 --top-k 20 -o prompts.h5 --json',
    'motok gpt sample -g runs/gpt --text "a person walks forward" --prior runs/prior_hybrid -o walk_sim.h5 '
    '--render walk_sim.mp4',
    'motok gpt sample -g runs/gpt --text "a person walks forward" --prior runs/prior_hybrid --closed-loop '
    '--replan-every 1 -o walk_loop.h5',
    'motok gpt sample -g runs/gpt --text "a person walks forward" --then "4s a person waves with both hands" '
    '--then "8s a person turns left" --seconds 10 --prior runs/prior_hybrid --closed-loop -o story.h5 '
    '--render story.mp4'))
@renamed(physics="--prior")
def sample(
    gpt: Path = typer.Option(..., "--gpt", "-g", help="A GPT run folder (from `gpt train`)."),
    text: list[str] = typer.Option([], "--text", metavar="TEXT",
                                   help="A sentence (repeatable); empty ones are refused."),
    texts_file: Optional[Path] = typer.Option(None, "--texts-file", help="One sentence per line (blank lines are "
                                              "skipped).", callback=existing),
    num_samples: int = number_option(1, "-n", "--num-samples", help="Samples per text, >= 1.", within=">= 1"),
    seed: int = number_option(0, "--seed", help="Sample j uses seed + j.", within=">= 0"),
    temperature: float = number_option(1.0, "--temperature", help="Softmax temperature, > 0.", within="> 0"),
    top_k: Optional[int] = number_option(None, "--top-k", help="Keep the k most likely codes (1 to the codebook "
                                         "size).", within=">= 1"),
    top_p: Optional[float] = number_option(None, "--top-p", help="Nucleus: keep the codes holding p of the mass, "
                                           "p in (0, 1].", within="(0, 1]"),
    argmax: bool = typer.Option(False, "--argmax", help="Greedy: the most likely code at each step."),
    guidance: Optional[float] = number_option(None, "--guidance", help="Classifier-free guidance scale, >= 0 "
                                              "(1 = off; default: the run's own, from its recipe). Needs a GPT "
                                              "trained with caption_dropout.", within=f"{GPT}.guidance"),
    snap: Optional[int] = number_option(None, "--snap", help="Condition a sentence that is not a training caption "
                                        "on its K nearest training captions (0 = off; default: the run's).",
                                        within=f"{GPT}.snap"),
    seconds: Optional[float] = number_option(None, "--seconds", help="Target length in seconds, > 0: End is masked "
                                             "before it and forced at it.", within="> 0"),
    out: Path = output_option(help="Output motion artifact (.h5).", suffixes=H5),
    render: Optional[Path] = output_option("--render", help="Also render each clip to this .gif, .mp4 or .png "
                                           "(numbered when there are several).", suffixes=RENDER_SUFFIXES,
                                           required=False),
    bvh: Optional[Path] = output_option("--bvh", help="Also export each clip to this .bvh (numbered when there are "
                                        "several).", suffixes=(".bvh",), required=False),
    tokenizer: Optional[Path] = typer.Option(None, "--tokenizer", "-t", help="Tokenizer run (default: the GPT's own).",
                                             callback=existing),
    allow_mismatch: bool = typer.Option(False, "--allow-mismatch", help="Decode with another tokenizer."),
    prior: Optional[Path] = input_option("--prior", help="Also simulate: track the motion with this distilled "
                                         "prior (a control-prior: its posterior and decoder); -o is then the "
                                         "simulated motion, the kinematic one goes to OUT.kinematic.h5, "
                                         "--render is a video (.mp4/.gif) of the first clip over its kinematic "
                                         "ghost and --bvh exports the simulated clips.", required=False),
    expert: Optional[Path] = input_option("--expert", help="Simulate as --prior does, tracked by this "
                                          "control-expert run instead of a prior.", required=False),
    codebooks: Optional[int] = number_option(None, "--codebooks", "-m", help="With --prior: decode with the first M "
                                             "codebooks only (default: all).", within=">= 1"),
    closed_loop: bool = typer.Option(False, "--closed-loop", help="With --prior: re-plan from the simulated "
                                     "character (the GPT continues the tokens of its last window) every "
                                     "--replan-every seconds; writes OUT.plans.h5 and OUT.closed-loop.json too."),
    replan_every: Optional[float] = number_option(None, "--replan-every", metavar="SECONDS", within="> 0",
                                                 help="With --closed-loop: seconds between re-plans, a multiple of "
                                                 "the token duration (default 1)."),
    then: list[str] = typer.Option([], "--then", metavar='"TIME TEXT"',
                                   help='With --prior: from TIME on, the motion follows TEXT, re-planned from the '
                                   'simulated character (repeatable; times increasing, on token boundaries, before '
                                   'the end): --then "4s a person waves".'),
    data: Optional[Path] = data_option("With --closed-loop: a generated motion artifact (e.g. from `eval t2m "
                                       "--save-generated`) made again in the closed loop: each clip's text, length "
                                       "and seed.", required=False),
    clips: Optional[str] = clips_option(help="With --data: only its clips whose name matches (each keeps its "
                                             "seed), e.g. 'gen-*0' for every tenth."),
    as_json: bool = JsonOut,
):
    """Text -> codes -> motion artifact (and optional GIF/BVH); prints where everything went. With
    --prior (or --expert) the motion is also tracked in MuJoCo, as `motok control track` does."""
    from motok.gpt.sample import sample as _sample
    texts = list(text)
    if texts_file is not None:
        try:
            texts += [ln.strip() for ln in texts_file.read_text(encoding="utf-8").splitlines() if ln.strip()]
        except (OSError, UnicodeDecodeError) as e:
            fail(f"--texts-file {texts_file}: not a readable text file ({e})")
    opts = dict(num_samples=num_samples, seed=seed, temperature=temperature, top_k=top_k, top_p=top_p,
                argmax=argmax, seconds=seconds, render=render, bvh=bvh, tokenizer=tokenizer,
                allow_mismatch=allow_mismatch, guidance=guidance, snap=snap)
    if closed_loop or then or replan_every is not None or data is not None or clips is not None:
        from motok.control.closed_loop.loop import REPLAN_EVERY, check_options
        from motok.control.closed_loop.loop import closed_loop as _closed_loop
        run(check_options, texts=texts, then=then, data=data, replan_every=replan_every, closed_loop=closed_loop,
            simulated=prior is not None or expert is not None, clips=clips)
        from motok.cli.output_files import refuse_foreign
        from motok.control.closed_loop.files import plans_path, report_path
        for beside in (plans_path(out), report_path(out)):  # the files written beside the motion
            run(refuse_foreign, beside, "-o")
        every = (REPLAN_EVERY if replan_every is None else replan_every) if closed_loop else None
        _report_loop(run(_closed_loop, gpt, out, texts=texts, then=then, data=data, replan_every=every, prior=prior,
                         expert=expert, codebooks=codebooks, clips=clips, **opts), as_json)
        return
    if prior is None and expert is None and codebooks is None:
        _report(run(_sample, gpt, texts, out, **opts), as_json, "gpt sample")
        return
    from motok.control.text_to_physics import text_to_physics
    _report_physics(run(text_to_physics, gpt, texts, out, prior=prior, expert=expert, codebooks=codebooks,
                        **opts), as_json)


def _report_physics(summary: dict, as_json: bool):
    """The summary table, one line per clip (how far it was tracked, its errors), then the files."""
    if as_json:
        report(summary, True, "")
        return
    from rich.markup import escape
    per = summary.pop("per_clip")
    report(summary, False, "gpt sample, simulated", hide=("output", "kinematic", "video", "bvh"))
    for name, r in per.items():
        if "mpjpe_mm" not in r:
            line = r.get("error", "not tracked")
        else:
            how = "tracked to the end" if r["tracked_to_end"] else f"failed at {r['failed_at_s']:.2f} s"
            line = (f"{how} of {r['clip_seconds']:.2f} s; MPJPE {r['mpjpe_mm']:.1f} mm, G-MPJPE "
                    f"{r['g_mpjpe_mm']:.1f} mm" + (f"; {r['error']}" if "error" in r else ""))
        results.print(escape(f"{name}: {line}"), soft_wrap=True, highlight=False)
    files = [summary["output"], f"{summary['kinematic']} (the kinematic motion)"]
    files += ([summary["video"]] if "video" in summary else []) + summary["bvh"]
    for f in files:
        results.print(f"wrote {escape(str(f))}", soft_wrap=True, highlight=False)


def _report_loop(summary: dict, as_json: bool):
    """The closed loop's summary, one line per motion (how far it was tracked, its re-plans), then the files."""
    if as_json:
        report(summary, True, "")
        return
    from rich.markup import escape
    per = summary.pop("per_clip")
    summary.pop("provenance", None)
    report(summary, False, "gpt sample, closed loop", hide=("output", "kinematic", "plans", "video", "bvh"))
    for name, r in per.items():
        how = "tracked to the end" if r["tracked_to_end"] else f"failed at {r['failed_at_s']:.2f} s"
        at = ", ".join(f"{x['at_s']:g}" for x in r["replans"]) or "none"
        results.print(escape(f"{name}: {how} of {r['clip_seconds']:.2f} s; MPJPE {r['mpjpe_mm']:.1f} mm; "
                             f"re-planned at {at} s"), soft_wrap=True, highlight=False)
    files = [summary["output"], f"{summary['kinematic']} (the reference tracked)", f"{summary['plans']} (every plan)",
             str(Path(summary["output"]).with_name(Path(summary["output"]).stem + ".closed-loop.json"))]
    files += ([summary["video"]] if "video" in summary else []) + summary["bvh"]
    for f in files:
        results.print(f"wrote {escape(str(f))}", soft_wrap=True, highlight=False)
