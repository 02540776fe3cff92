"""Training curves from metrics JSONL files (one JSON object per line), one subplot per key; several
runs (the five priors, three navigation policies) overlaid on the same subplots, one colour each."""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Mapping, Sequence

from motok.atomic import atomic_path, check_writable
from motok.errors import MissingFileError, UserError


def _is_number(v) -> bool:
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
                title: str | None = None, x2: str | None = None, missing_ok: bool = False) -> Path:
    """Plot metrics against ``x`` (the record index where a record lacks it) into ``out_png``.

    The source is a JSONL path or records, or a mapping ``{label: path or records}`` of several
    runs drawn on the same subplots (one colour and legend entry each). ``keys`` defaults to every
    numeric field but ``x``, in first-seen order; with several runs a key needs to be in one of
    them (a continuous prior has no code usage). ``smooth`` in [0, 1) is an exponential-moving-
    average weight per record (see ``_ema``): the raw curve is drawn faintly behind the smoothed
    one. ``logy`` is True for every subplot or a list of keys to draw on a log scale. ``x2``
    labels a second, top axis with another field that grows with ``x`` (e.g. ``samples`` below,
    ``wall_s`` on top), read off by interpolation; one run only, since runs differ in speed.
    """
    fig = _figure(jsonl_path_or_records, keys, x, smooth=smooth, logy=logy, title=title, x2=x2,
                  missing_ok=missing_ok)
    out = Path(out_png)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return out


def _figure(source, keys, x, *, smooth=0.0, logy=False, title=None, x2=None, missing_ok=False):
    if not 0.0 <= smooth < 1.0:
        raise UserError(f"smooth must be in [0, 1), got {smooth}")
    many = isinstance(source, Mapping)
    runs = {label: _records(src) for label, src in (source.items() if many else [("", source)])}
    if many and not runs:
        raise UserError("no runs to plot")
    if many and len(runs) > 1 and x2:
        raise UserError("--x2 labels one run's second axis: give a single run with it")
    names = ", ".join(src for _, src in runs.values())
    available = list(dict.fromkeys(k for recs, _ in runs.values() for r in recs for k, v in r.items() if _is_number(v)))
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
    series = {label: {k: [(r[x] if _is_number(r.get(x)) else i, r[k], i) for i, r in enumerate(recs)
                          if _is_number(r.get(k))] for k in keys} for label, (recs, _) in runs.items()}
    top = None
    if x2:
        (recs, source_name), = runs.values()
        pairs = sorted({(r[x], r[x2]) for r in recs if _is_number(r.get(x)) and _is_number(r.get(x2))})
        if len(pairs) < 2 or any(b[1] < a[1] for a, b in zip(pairs, pairs[1:])):
            raise UserError(f"{source_name}: {x2!r} must grow with {x!r} to label a second axis")
        top = tuple(map(list, zip(*pairs)))
    if not keys or not any(pts for s in series.values() for pts in s.values()):
        raise UserError(f"{names}: no numeric values to plot for keys {keys or '(none found)'}")

    # A bare Figure renders through Agg without touching pyplot's global backend or state,
    # so this works headless and does not disturb an interactive session that calls it.
    from matplotlib.figure import Figure

    ncols = 1 if len(keys) <= 3 else 2
    nrows = math.ceil(len(keys) / ncols)
    fig = Figure(figsize=(6.4 * ncols, 2.6 * nrows + 0.4))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    log_keys = set(keys) if logy is True else set(logy or ())
    for ax, k in zip(axes.flat, keys):
        ax.set_title(k, fontsize=10, loc="left")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel(x, fontsize=8)
        drawn = []
        for c, (label, s) in enumerate(series.items()):
            pts = sorted(s[k], key=lambda p: p[0])
            if not pts:
                continue
            xs, ys, rows = zip(*pts)
            drawn += ys
            color, name = f"C{c}", label or None
            sparse = dict(marker="o", markersize=3) if len(xs) < 60 else {}  # an evaluation every K iterations
            if smooth > 0:
                ax.plot(xs, ys, color=color, alpha=0.25, linewidth=1)
                ax.plot(xs, _ema(ys, smooth, rows), color=color, linewidth=1.6, label=name, **sparse)
            else:
                ax.plot(xs, ys, color=color, linewidth=1.4, label=name, **sparse)
        if not drawn:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="grey")
            continue
        if k in log_keys and min(drawn) > 0:
            ax.set_yscale("log")
        if len(series) > 1:
            ax.legend(fontsize=7, loc="best")
        if top is not None:
            fwd = lambda v, a=top: _interp(v, a[0], a[1])  # noqa: E731
            inv = lambda v, a=top: _interp(v, a[1], a[0])  # noqa: E731
            ax.secondary_xaxis("top", functions=(fwd, inv)).set_xlabel(x2, fontsize=8)
    for ax in axes.flat[len(keys):]:
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


def plot_run(run_or_jsonl, out_png: str | os.PathLike | None = None, keys: Sequence[str] | None = None,
             x: str = "iteration", labels: Sequence[str] | None = None, **kw) -> Path:
    """``motok plot``: a run folder (its ``metrics.jsonl``) or a JSONL file, drawn by
    :func:`plot_curves` to ``out_png`` (default: ``curves.png`` beside the metrics); or a list of
    them on the same subplots (``out_png`` required), labelled by ``labels`` or their folder names."""
    many = isinstance(run_or_jsonl, (list, tuple))
    srcs = [_metrics_file(r) for r in (run_or_jsonl if many else [run_or_jsonl])]
    if many and len(srcs) > 1 and out_png is None:
        raise UserError("several runs: name the comparison's file with -o/--out (a .png)")
    if labels is not None and len(labels) != len(srcs):
        raise UserError(f"{len(labels)} labels for {len(srcs)} runs: give one --label per run")
    out = Path(out_png) if out_png is not None else srcs[0].with_name("curves.png")
    check_writable(out, suffixes=(".png",))
    if len(srcs) == 1:
        return plot_curves(srcs[0], out, keys, x, **kw)
    names = list(labels) if labels is not None else [s.parent.name if s.name == "metrics.jsonl" else s.stem for s in srcs]
    if len(set(names)) != len(names):
        raise UserError(f"runs share a name ({', '.join(names)}): tell them apart with --label")
    return plot_curves(dict(zip(names, srcs)), out, keys, x, **kw)
