"""Training curves from metrics JSONL files (one JSON object per line), one subplot per quantity:
its training, validation (``val_``), evaluation (``eval_``) and train-clip (``train_``) values
overlaid, each panel titled and its axes labelled with units (``motok.render.metric_names``),
the figure titled with the run's name and kind. Several runs (the five priors, three navigation
policies) are overlaid on the same subplots, one colour each."""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Mapping, Sequence

from motok.atomic import atomic_path, check_writable
from motok.errors import MissingFileError, UserError
from motok.render.metric_names import axis_label, describe, split_key

# A quantity's curves in one panel: for several runs the colour is the run's and the line style
# the data's (training solid, validation dashed, ...); for one run the colour tells them apart.
LINESTYLES = ("-", "--", ":", "-.")


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def read_metrics(path: str | os.PathLike) -> list[dict]:
    """The JSON objects of a JSONL file; malformed or non-object lines are skipped with a warning
    (a run killed mid-write leaves half a line), but a file with no object at all is refused."""
    if not Path(path).is_file():
        raise MissingFileError(f"{path}: no such file")
    with open(path, "rb") as fh:
        if fh.read(8) == b"\x89HDF\r\n\x1a\n":
            raise UserError(f"{path}: an HDF5 artifact, not a metrics log; give a run folder or its metrics.jsonl "
                            f"(`motok info` describes artifacts)")
    records, bad = [], []
    try:
        with open(path, encoding="utf-8") as fh:
            for lineno, line in enumerate(fh, 1):
                if not line.strip():
                    continue
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError as e:
                    bad.append(f"line {lineno}: malformed JSON ({e.msg})")
                    continue
                if not isinstance(rec, dict):
                    bad.append(f"line {lineno}: a {type(rec).__name__}, expected an object")
                    continue
                records.append(rec)
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a metrics log (JSON lines expected, found binary data)") from None
    if bad and not records:
        raise UserError(f"{path}: not a metrics log (one JSON object a line expected; {bad[0]})")
    for b in bad:
        warnings.warn(f"{path}: {b}: skipped", stacklevel=2)
    return records


def _ema(values: Sequence[float], weight: float, rows: Sequence[int] | None = None) -> list[float]:
    """Debiased exponential moving average (TensorBoard's smoothing: the curve does not start
    pinned at the first value). ``weight`` is per record of the log: a metric logged every
    K-th record (``rows`` = the record numbers) decays by ``weight ** K`` between its points, so
    a sparse evaluation curve is smoothed over the same stretch of training as a dense one."""
    rows = list(range(len(values)) if rows is None else rows)
    gaps = [max(b - a, 1) for a, b in zip(rows, rows[1:])]
    out, acc, norm = [], 0.0, 0.0
    for v, gap in zip(values, gaps[:1] + gaps or [1]):  # the first point stands for one gap too
        w = weight**gap
        acc, norm = w * acc + (1.0 - w) * v, w * norm + (1.0 - w)
        out.append(acc / norm)
    return out


def _interp(v, xp: Sequence[float], fp: Sequence[float]):
    """Piecewise-linear map through the points, extended beyond them with the overall slope:
    clamping (``np.interp``) would pile the top axis' ticks up at the ends of the data."""
    import numpy as np

    v, xp, fp = np.asarray(v, dtype=float), np.asarray(xp, dtype=float), np.asarray(fp, dtype=float)
    slope = (fp[-1] - fp[0]) / (xp[-1] - xp[0]) if xp[-1] > xp[0] else 1.0
    out = np.interp(v, xp, fp)
    out = np.where(v < xp[0], fp[0] + (v - xp[0]) * slope, out)
    return np.where(v > xp[-1], fp[-1] + (v - xp[-1]) * slope, out)


def _records(src) -> tuple[list[dict], str]:
    if isinstance(src, (str, os.PathLike)):
        return read_metrics(src), str(src)
    return [dict(r) for r in src], "records"


def plot_curves(jsonl_path_or_records, out_png: str | os.PathLike, keys: Sequence[str] | None = None,
                x: str = "iteration", *, smooth: float = 0.0, logy: bool | Sequence[str] = False,
                title: str | None = None, x2: str | None = None, missing_ok: bool = False,
                kind: str | None = None) -> Path:
    """Plot metrics against ``x`` (the record index where a record lacks it) into ``out_png``.

    The source is a JSONL path or records, or a mapping ``{label: path or records}`` of several
    runs drawn on the same subplots (one colour and legend entry each). ``keys`` defaults to every
    numeric field but ``x``, in first-seen order; with several runs a key needs to be in one of
    them (a continuous prior has no code usage). ``smooth`` in [0, 1) is an exponential-moving-
    average weight per record (see ``_ema``): the raw curve is drawn faintly behind the smoothed
    one. ``logy`` is True for every subplot or a list of keys to draw on a log scale. ``x2``
    labels a second, top axis with another field that grows with ``x`` (e.g. ``samples`` below,
    ``wall_s`` on top), read off by interpolation; one run only, since runs differ in speed.
    Keys of one quantity (``loss``, ``val_loss``) share a panel; ``kind`` (the run's, e.g.
    ``gpt``) chooses the labels of keys that stages use differently, such as ``loss``.
    """
    fig = _figure(jsonl_path_or_records, keys, x, smooth=smooth, logy=logy, title=title, x2=x2,
                  missing_ok=missing_ok, kind=kind)
    out = Path(out_png)
    with atomic_path(out) as tmp:
        from motok.marks import MARK  # how motok knows its own picture again
        fig.savefig(tmp, dpi=100, format="png", metadata={"Comment": MARK})
    return out


def _figure(source, keys, x, *, smooth=0.0, logy=False, title=None, x2=None, missing_ok=False, kind=None):
    if not 0.0 <= smooth < 1.0:
        raise UserError(f"smooth must be in [0, 1), got {smooth}")
    many = isinstance(source, Mapping)
    runs = {label: _records(src) for label, src in (source.items() if many else [("", source)])}
    if many and not runs:
        raise UserError("no runs to plot")
    if many and len(runs) > 1 and x2:
        raise UserError("--x2 labels one run's second axis: give a single run with it")
    names = ", ".join(src for _, src in runs.values())
    available = list(dict.fromkeys(k for recs, _ in runs.values() for r in recs for k, v in r.items() if is_number(v)))
    if keys is None:
        keys = [k for k in available if k != x]
    keys = list(keys)
    unknown = [k for k in keys if k not in available]
    if unknown and missing_ok and len(unknown) < len(keys):
        # e.g. a short run that has logged no evaluation yet: draw what there is, say what is not
        warnings.warn(f"{names}: no metric {', '.join(map(repr, unknown))} in the log yet; drawing the others",
                      stacklevel=3)
        keys, unknown = [k for k in keys if k in available], []
    if unknown:
        raise UserError(f"{names}: no metric {', '.join(map(repr, unknown))} in the log; it has: "
                        f"{', '.join(available) or '(nothing numeric)'}")
    if logy is not True and set(logy or ()) - set(keys):
        # a typo here would silently draw a linear axis
        raise UserError(f"{names}: --log {', '.join(sorted(set(logy) - set(keys)))}: not among the plotted keys "
                        f"({', '.join(keys)})")
    for name, key in (("--x", x), ("--x2", x2)):
        # Without an iteration field the record number is the x axis (documented); any other
        # field must be there, or the plot would silently show something else.
        if key and key not in available and not (name == "--x" and key == "iteration"):
            raise UserError(f"{names}: {name} {key!r} is not a numeric field of the log; it has: "
                            f"{', '.join(available) or '(nothing numeric)'}")
    series = {label: {k: [(r[x] if is_number(r.get(x)) else i, r[k], i) for i, r in enumerate(recs)
                          if is_number(r.get(k))] for k in keys} for label, (recs, _) in runs.items()}
    top = None
    if x2:
        (recs, source_name), = runs.values()
        pairs = sorted({(r[x], r[x2]) for r in recs if is_number(r.get(x)) and is_number(r.get(x2))})
        if len(pairs) < 2 or any(b[1] < a[1] for a, b in zip(pairs, pairs[1:])):
            raise UserError(f"{source_name}: {x2!r} must grow with {x!r} to label a second axis")
        top = tuple(map(list, zip(*pairs)))
    if not keys or not any(pts for s in series.values() for pts in s.values()):
        raise UserError(f"{names}: no numeric values to plot for keys {keys or '(none found)'}")

    # A bare Figure renders through Agg without touching pyplot's global backend or state,
    # so this works headless and does not disturb an interactive session that calls it.
    from matplotlib.figure import Figure

    panels: dict[str, list[str]] = {}
    for k in keys:
        panels.setdefault(split_key(k)[0], []).append(k)
    ncols = 1 if len(panels) <= 3 else 2
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(6.4 * ncols, 2.6 * nrows + 0.4 + 0.3 * bool(title)))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    log_keys = set(keys) if logy is True else set(logy or ())
    for ax, (quantity, members) in zip(axes.flat, panels.items()):
        metric = describe(quantity, kind)
        ax.set_title(metric.label, fontsize=10, loc="left")
        ax.set_ylabel(metric.unit, fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.set_xlabel(axis_label(x, kind), fontsize=8)
        drawn = []
        for c, (label, s) in enumerate(series.items()):
            for r, k in enumerate(members):
                pts = sorted(s[k], key=lambda p: p[0])
                if not pts:
                    continue
                xs, ys, rows = zip(*pts)
                drawn += ys
                role = split_key(k)[1] if len(members) > 1 else ""
                name = " · ".join(p for p in (label, role) if p) or None
                color, style = (f"C{c}", LINESTYLES[r % len(LINESTYLES)]) if len(series) > 1 else (f"C{r}", "-")
                sparse = dict(marker="o", markersize=3) if len(xs) < 60 else {}  # an evaluation every K iterations
                if smooth > 0:
                    ax.plot(xs, ys, color=color, linestyle=style, alpha=0.25, linewidth=1)
                    ax.plot(xs, _ema(ys, smooth, rows), color=color, linestyle=style, linewidth=1.6, label=name,
                            **sparse)
                else:
                    ax.plot(xs, ys, color=color, linestyle=style, linewidth=1.4, label=name, **sparse)
        if not drawn:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="grey")
            continue
        if log_keys & set(members) and min(drawn) > 0:
            ax.set_yscale("log")
        if len(series) > 1 or len(members) > 1:
            ax.legend(fontsize=7, loc="best")
        if top is not None:
            fwd = lambda v, a=top: _interp(v, a[0], a[1])  # noqa: E731
            inv = lambda v, a=top: _interp(v, a[1], a[0])  # noqa: E731
            ax.secondary_xaxis("top", functions=(fwd, inv)).set_xlabel(axis_label(x2, kind), fontsize=8)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def _metrics_file(run_or_jsonl) -> Path:
    src = Path(run_or_jsonl)
    if src.is_dir():
        if not (src / "metrics.jsonl").is_file():
            raise UserError(f"{src}: not a run folder (it has no metrics.jsonl)")
        src = src / "metrics.jsonl"
    return src


def default_output(run_or_jsonl) -> Path:
    """Where ``motok plot RUN`` draws without ``-o``: ``curves.png`` beside the run's metrics."""
    return _metrics_file(run_or_jsonl).with_name("curves.png")


def run_kind(metrics: Path) -> str | None:
    """The kind of the run whose ``metrics.jsonl`` this is (``tokenizer``, ``gpt``, ``control-task``
    ...), from the checkpoint bundle beside it; None for a bare log or a run not saved yet."""
    bundle = metrics.with_name("bundle.json")
    try:
        kind = json.loads(bundle.read_text(encoding="utf-8")).get("kind") if bundle.is_file() else None
    except (OSError, ValueError, AttributeError):
        return None  # the figure is still worth drawing without it
    return str(kind) if kind else None


def _run_name(src: Path) -> str:
    return src.parent.name if src.name == "metrics.jsonl" else src.stem


def run_title(srcs: Sequence[Path], names: Sequence[str]) -> str:
    """``gpt (gpt)``, ``prior_hybrid, prior_continuous (control-prior)``: the runs and their kinds."""
    kinds = list(dict.fromkeys(k for k in map(run_kind, srcs) if k))
    return ", ".join(names) + (f" ({', '.join(kinds)})" if kinds else "")


def run_sources(runs: Sequence, labels: Sequence[str] | None = None) -> dict[str, Path]:
    """``{name: metrics.jsonl}`` of run folders or JSONL files, named by ``labels`` or their folders."""
    srcs = [_metrics_file(r) for r in runs]
    if labels is not None and len(labels) != len(srcs):
        raise UserError(f"{len(labels)} labels for {len(srcs)} runs: give one --label per run")
    names = list(labels) if labels is not None else [_run_name(s) for s in srcs]
    if len(set(names)) != len(names):
        raise UserError(f"runs share a name ({', '.join(names)}): tell them apart with --label")
    return dict(zip(names, srcs))


def plot_run(run_or_jsonl, out_png: str | os.PathLike | None = None, keys: Sequence[str] | None = None,
             x: str = "iteration", labels: Sequence[str] | None = None, **kw) -> Path:
    """``motok plot``: a run folder (its ``metrics.jsonl``) or a JSONL file, drawn by
    :func:`plot_curves` to ``out_png`` (default: ``curves.png`` beside the metrics); or a list of
    them on the same subplots (``out_png`` required), labelled by ``labels`` or their folder names.
    The figure is titled with the runs' names and kinds unless ``title`` is given."""
    runs = list(run_or_jsonl) if isinstance(run_or_jsonl, (list, tuple)) else [run_or_jsonl]
    if len(runs) > 1 and out_png is None:
        raise UserError("several runs: name the comparison's file with -o/--out (a .png)")
    sources = run_sources(runs, labels)
    srcs = list(sources.values())
    out = Path(out_png) if out_png is not None else default_output(srcs[0])
    check_writable(out, suffixes=(".png",))
    kinds = {run_kind(s) for s in srcs}
    kw.setdefault("title", run_title(srcs, list(sources)))
    kw.setdefault("kind", kinds.pop() if len(kinds) == 1 else None)
    return plot_curves(srcs[0] if len(srcs) == 1 else sources, out, keys, x, **kw)
