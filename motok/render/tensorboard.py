"""``motok plot RUN --tensorboard DIR``: a run's ``metrics.jsonl`` as TensorBoard event files, for
those who look at curves there. An optional extra (``pip install 'motok[tensorboard]'``): the
training loops keep writing JSONL only, and the conversion can be run at any time, on a run
that is still training too (run it again: it replaces what it wrote before).

Each run goes to ``DIR/<run name>/<data>/`` with one subfolder per kind of data (``training``,
``validation``, ``evaluation``, ``train clips``), each tag the quantity's key without its prefix:
TensorBoard overlays runs, so a loss and its validation value come out on one chart, as in
``motok plot``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Mapping

from motok.atomic import OutputError, atomic_folder
from motok.errors import UserError
from motok.render.metric_names import split_key
from motok.render.plot import is_number, read_metrics

EVENTS = "events.out.tfevents."  # TensorBoard's file name prefix


def summary_writer():
    """torch's TensorBoard writer, which needs the ``tensorboard`` package."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise UserError("--tensorboard writes event files with the tensorboard package, which is not installed: "
                        "pip install 'motok[tensorboard]'") from None
    return SummaryWriter


def write_events(runs: Mapping[str, Path], out: str | Path, x: str = "iteration") -> list[Path]:
    """Write each ``{name: metrics.jsonl}`` as event files under ``out/name``; returns those folders.
    The step is ``x`` (the record number where a record lacks it), the wall time ``wall_s``."""
    SummaryWriter = summary_writer()
    written = []
    for name, src in runs.items():
        dst = Path(out) / name
        if dst.exists() and any(not p.name.startswith(EVENTS) for p in dst.rglob("*") if p.is_file()):
            raise OutputError(f"--tensorboard {dst} holds other files than event files; give another folder")
        records = read_metrics(src)
        if dst.exists():
            shutil.rmtree(dst)  # ours from an earlier conversion: two copies would draw every curve twice
        with atomic_folder(dst) as tmp:
            writers = {}
            for i, rec in enumerate(records):
                step = int(rec[x]) if is_number(rec.get(x)) else i
                wall = float(rec["wall_s"]) if is_number(rec.get("wall_s")) else None
                for key, value in rec.items():
                    if key == x or not is_number(value):
                        continue
                    quantity, role = split_key(key)
                    if role not in writers:
                        writers[role] = SummaryWriter(log_dir=str(tmp / role))
                    writers[role].add_scalar(quantity, float(value), global_step=step, walltime=wall)
            for w in writers.values():
                w.close()
        written.append(dst)
    return written
