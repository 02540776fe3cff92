"""``motok eval t2m`` and ``motok eval recon``: which rows a report has, and the report itself
(JSON, Markdown for docs/results.md, rich tables for the terminal).

Rows: real motion, tokenizer reconstruction, generation (a GPT with predicted or ground-truth
length, :mod:`motok.eval.generate`), or any ``motion`` artifact; each is a motion set
(:mod:`motok.eval.sets`) measured by the protocol of :mod:`motok.eval.protocol`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from motok.atomic import atomic_path, write_json
from motok.data.dataset import MotionFile
from motok.eval import metrics as M
from motok.eval.captions import label_ceiling, training_captions, unseen_only
from motok.eval.evaluator import EvaluatorError, load_evaluator
from motok.eval.generate import generated_set
from motok.eval.protocol import T2MConfig, evaluate_rows, physical_of
from motok.eval.sets import common_clips, motion_set, real_set, recon_set

__all__ = ["COLUMNS", "PHYSICAL", "T2MConfig", "headers", "markdown", "recon", "rich_table", "save_report", "t2m"]


# --------------------------------------------------------------------------- the report

def t2m(evaluator: Path, data: Path, cfg: T2MConfig, tokenizer: Path | None = None, gpt: Path | None = None,
        motions: list[Path] = (), save_generated: Path | None = None, real: bool = True) -> dict:
    """Evaluate every requested row; returns the JSON-ready report."""
    import torch
    t0 = time.perf_counter()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    ev = load_evaluator(evaluator)
    ref, info = real_set(Path(data), cfg.split)
    ex = ev.meta["extra"]
    if int(ex["feature_dim"]) != ref.clips[0].shape[1]:
        raise EvaluatorError(f"{data} has {ref.clips[0].shape[1]}-d features; {evaluator} was trained on "
                             f"{ex['feature_dim']}-d ones")
    # Before any row is made: the evaluator reads per-frame velocities, so every row must be at its rate.
    _same_rate(data, info["fps"], ex, evaluator)
    for p in motions:
        with MotionFile(p) as mf:
            _same_rate(p, mf.fps, ex, evaluator)
            if int(mf.h5["frames/features"].shape[1]) != int(ex["feature_dim"]):
                raise EvaluatorError(f"{p} has {mf.h5['frames/features'].shape[1]}-d features; {evaluator} was "
                                     f"trained on {ex['feature_dim']}-d ones")
    if cfg.captions not in ("all", "unseen"):
        raise EvaluatorError(f"captions must be all or unseen, not {cfg.captions!r}")
    try:
        seen = training_captions(data, cfg.train_split)
    except EvaluatorError:
        if cfg.captions == "unseen":
            raise
        seen = None  # no training split to compare with: the overlap is not defined
    all_caps = [t for c in ref.captions for t in c]
    overlap = None if seen is None else {"train_split": cfg.train_split, "captions": len(all_caps),
                                         "share_in_train": sum(t in seen for t in all_caps) / len(all_caps)}
    if cfg.captions == "unseen":
        ref = unseen_only(ref, seen)
        if len(ref.clips) < 2:
            raise EvaluatorError(f"only {len(ref.clips)} {cfg.split} clip(s) have a caption that is not in "
                                 f"{cfg.train_split}; --captions unseen needs 2+")
    rows = [ref] if real else []
    if tokenizer is not None:
        rows.append(recon_set(ref, Path(tokenizer), info))
    if gpt is not None:
        rows.append(generated_set(Path(gpt), tokenizer, ref, cfg, save_generated, fps=info["fps"]))
    rows += [motion_set(Path(p), split=cfg.split, tracked_to_end=cfg.tracked_to_end) for p in motions]
    if cfg.tracked_to_end and not any(r.extra.get("tracked_clips") for r in rows):
        raise EvaluatorError("--tracked-to-end: no --motions file holds clips written by `motok control track` "
                             "(none has the label 'tracked_to_end')")
    if cfg.captions == "unseen":  # generated rows already use only ref's captions; --motions rows do not
        rows = [r if r is ref else unseen_only(r, seen) for r in rows]
    if not rows:
        raise EvaluatorError("nothing to evaluate: give --tokenizer, --gpt or --motions (or keep the real row)")
    if cfg.common_clips:
        rows = common_clips(rows)
    results = evaluate_rows(ev, ref, rows, cfg)
    ev_text = ev.meta["config"]["text_encoder"]
    for res in results:
        if res.get("gpt_text_encoder"):
            # Guo et al.'s evaluator reads text with its own encoder; a frozen encoder shared with
            # the generator can favour it in R-precision and MM-Dist.
            res["text_side"] = "shared" if res["gpt_text_encoder"] == ev_text else "independent"
    if cfg.physical:
        for res, row in zip(results, rows):
            res["physical"] = physical_of(row, info["fps"], info["feet"])
    return {"kind": "t2m-report", "schema_version": 1, "protocol": "Guo et al. 2022 / T2M-GPT Table 1", "config": dict(cfg.__dict__),
            "evaluator": str(evaluator), "evaluator_sha256": ev.meta.get("model_sha256"),
            "text_encoder": ev_text, "data": str(data), "split": cfg.split, "captions": cfg.captions,
            "caption_overlap": overlap, "label_ceiling": label_ceiling(ref.labels or [], cfg.batch, cfg.top_k),
            "clips": len(ref.clips), "rows": results, "seconds": round(time.perf_counter() - t0, 1)}


def _same_rate(path, fps: float, ex: dict, evaluator) -> None:
    if "fps" in ex and abs(float(fps) - float(ex["fps"])) > 1e-6:
        raise EvaluatorError(f"{path} is at {float(fps):g} fps; {evaluator} was trained at {float(ex['fps']):g} fps "
                             f"and reads motion at that rate only")


COLUMNS = [("R@1", "R@1 ↑"), ("R@2", "R@2 ↑"), ("R@3", "R@3 ↑"), ("FID", "FID ↓"), ("MM-Dist", "MM-Dist ↓"),
           ("Diversity", "Diversity →"), ("MModality", "MModality ↑")]
PHYSICAL = [("skate_cm_s", "Skate cm/s"), ("penetration_cm", "Penetr. cm"), ("floating_cm", "Float cm"),
            ("floating_placed_cm", "Float placed cm"), ("jitter_m_s3", "Jitter m/s³")]


def _t2m_cells(res: dict) -> list[str]:
    cells = []
    for key, _ in COLUMNS:
        m = res["metrics"].get(key)
        # FID of unit-norm embeddings is small: one more digit keeps the real row readable.
        fmt = ".1e" if key == "FID" and m is not None and m["mean"] < 1e-3 else (".4f" if key == "FID" else ".3f")
        cells.append("-" if m is None else f"{m['mean']:{fmt}}±{m['ci']:{fmt}}")
    return cells


def _other_cells(res: dict) -> list[str]:
    phys = res.get("physical", {})
    cells = ["-" if k not in phys else f"{phys[k]:.2f}" for k, _ in PHYSICAL]
    recon = res.get("recon")
    return cells + ["-" if recon is None else f"{recon['mpjpe_mm']:.1f}"]


def _cells(res: dict) -> list[str]:
    return _t2m_cells(res) + _other_cells(res)


def headers() -> list[str]:
    return ["Motion"] + [h for _, h in COLUMNS] + [h for _, h in PHYSICAL] + ["MPJPE mm"]


def markdown(report: dict) -> str:
    """A table ready for docs/results.md (mean ± 95% CI over the repeats)."""
    h = headers()
    lines = ["| " + " | ".join(h) + " |", "|" + "---|" * len(h)]
    lines += ["| " + " | ".join([r["name"]] + _cells(r)) + " |" for r in report["rows"]]
    c = report["config"]
    lines.append("")
    which = " (only captions that do not occur in training)" if report.get("captions") == "unseen" else ""
    lines.append(f"{report['split']} split of `{report['data']}`, {report['clips']} clips{which}, {c['repeats']} "
                 f"repeats (mean ± 1.96 std/sqrt({c['repeats']})); evaluator `{report['evaluator']}` "
                 f"({report['text_encoder']} text encoder).")
    ov, ceil = report.get("caption_overlap"), report.get("label_ceiling")
    if ov:
        lines.append(f"{ov['share_in_train']:.1%} of the split's {ov['captions']} captions occur word for word in "
                     f"{ov['train_split']}.")
    if ceil:
        lines.append(f"Label-reader ceiling (batches of {ceil['batch']}): R@1 {ceil['R@1']:.3f}, "
                     f"R@3 {ceil.get('R@3', float('nan')):.3f}.")
    for r in report["rows"]:
        if r.get("other_split_left_out"):
            lines.append(f"{r['name']}: {r['other_split_left_out']} clip(s) of other splits than {report['split']} "
                         f"left out.")
        if r.get("not_tracked_to_end_left_out"):
            lines.append(f"{r['name']}: {r['not_tracked_to_end_left_out']} clip(s) left out that the tracking played "
                         f"only to its failure (--tracked-to-end).")
        if r.get("common_clips_left_out"):
            lines.append(f"{r['name']}: {r['common_clips_left_out']} clip(s) left out that a row sharing its clip "
                         f"names does not hold (--common-clips).")
        if r.get("text_side"):
            lines.append(f"{r['name']}: the GPT reads text with `{r['gpt_text_encoder']}`, the evaluator with "
                         f"`{report['text_encoder']}` ({r['text_side']} text side).")
    return "\n".join(lines)


def save_report(report: dict, json_path: Path | None = None, md_path: Path | None = None) -> None:
    """Write the full report as JSON and/or its table as Markdown (``--out-json``, ``--out-md``)."""
    if json_path is not None:
        write_json(json_path, report)
    if md_path is not None:
        with atomic_path(md_path) as tmp:
            from motok.marks import MD_MARK  # how motok knows its own report again
            tmp.write_text(MD_MARK + "\n" + markdown(report) + "\n")


def rich_table(report: dict):
    """Two rich tables (the T2M metrics, then physical and reconstruction) so each fits a terminal."""
    from rich.console import Group
    from rich.table import Table
    first = Table(title=f"t2m protocol: {report['split']} split, {report['config']['repeats']} repeats (mean ± 95% CI)")
    second = Table(title="physical plausibility and reconstruction")
    for table, names in ((first, [h for _, h in COLUMNS]), (second, [h for _, h in PHYSICAL] + ["MPJPE mm"])):
        table.add_column("Motion")
        for name in names:
            table.add_column(name, justify="right")
    for r in report["rows"]:
        first.add_row(r["name"], *_t2m_cells(r))
        second.add_row(r["name"], *_other_cells(r))
    return Group(first, second)


def recon(data: Path, split: str = "test", tokenizer: Path | None = None, motions: Path | None = None,
          num_codebooks: int | None = None) -> dict:
    """MPJPE (mm, root-relative and global) and acceleration error of a reconstruction: the split
    through ``tokenizer``, or the clips of a ``motion`` artifact matched to the data set by name
    (each pair cut to the shorter length: a tokenizer drops the frames past its last token)."""
    ref, info = real_set(Path(data), split)
    if tokenizer is not None:
        ms = recon_set(ref, Path(tokenizer), info, num_codebooks)
        return {"data": str(data), "split": split, "tokenizer": str(tokenizer), "clips": len(ms.clips),
                **ms.extra["recon"]}
    if motions is None:
        raise EvaluatorError("recon needs --tokenizer or --motions")
    by_name = dict(zip(info["names"], ref.joints))
    errs = {"mpjpe": [], "mpjpe_global": [], "accel": []}
    with MotionFile(motions) as mf:
        if abs(mf.fps - info["fps"]) > 1e-6 or list(mf.skeleton.joints) != info["joints"]:
            raise EvaluatorError(f"{motions}: {mf.skeleton.num_joints} joints at {mf.fps:g} fps; {data} has "
                                 f"{info['num_joints']} at {info['fps']:g}: frames are compared one to one")
        pairs = [(i, by_name[n]) for i, n in enumerate(mf.names) if n in by_name]
        if not pairs:
            raise EvaluatorError(f"{motions}: no clip named like a {split} clip of {data} (first: {mf.names[:3]})")
        for i, gt in pairs:
            pred = mf.frames("joints", i)
            T = min(len(pred), len(gt))
            errs["mpjpe"].append(M.mpjpe(pred[:T], gt[:T]))
            errs["mpjpe_global"].append(M.mpjpe(pred[:T], gt[:T], root_relative=False))
            if T >= 3:
                errs["accel"].append(M.acceleration_error(pred[:T], gt[:T]))
    return {"data": str(data), "split": split, "motions": str(motions), "clips": len(pairs),
            "mpjpe_mm": float(np.concatenate(errs["mpjpe"]).mean()),
            "mpjpe_global_mm": float(np.concatenate(errs["mpjpe_global"]).mean()),
            "accel_error_mm": float(np.concatenate(errs["accel"]).mean()) if errs["accel"] else float("nan")}
