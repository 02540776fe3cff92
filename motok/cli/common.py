"""What every ``motok`` subcommand shares: calling into a stage, failing, printing results, and
the option declarations that mean the same thing everywhere.

Stage CLIs (``motok/cli/<stage>.py``) import from here and ``motok/cli/main.py`` imports the
stage CLIs, so nothing here may import ``motok.cli.main``. Importing this module stays cheap
(typer only): ``motok --help`` must not pay for torch or MuJoCo.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Mapping

import typer
from rich.console import Console

from motok import progress
from motok.atomic import strict_json
from motok.errors import MotokError

__all__ = ["DataRoot", "Device", "JsonOut", "Resume", "Sets", "cell", "choose_mujoco_gl", "clips_option",
           "data_option", "device_sets", "existing", "fail", "input_option", "number_option", "output_option",
           "print_json", "recipe_option", "report", "results", "run", "split_option", "valid_device", "wrote"]

# Results (tables, JSON, what was written) go to stdout; progress, notes and errors to stderr
# (motok.progress.console), so `motok ... --json | jq` and `> log` both work.
results = Console()


# --------------------------------------------------------------------------- errors

def fail(msg: str, code: int = 2):
    """Print ``error: msg`` on stderr and exit with ``code`` (2: the user has something to fix)."""
    from rich.markup import escape

    from motok.cli.output_files import release_claims
    progress.console.print(f"[bold red]error:[/] {escape(msg)}", highlight=False, soft_wrap=True)
    release_claims()  # nothing is written after a refusal, not even a lock file
    raise typer.Exit(code)


def run(fn: Callable, *args, **kwargs):
    """Call into a stage. An error motok raised on purpose (:class:`motok.errors.MotokError`)
    becomes one line and exit code 2; any other exception is a bug and keeps its traceback."""
    try:
        return fn(*args, **kwargs)
    except MotokError as e:
        fail(str(e))
    except KeyboardInterrupt:  # Ctrl-C: a line, not a traceback (training commands say more: cli/outputs.py)
        fail("interrupted; every file motok writes appears only when complete, so none is half-written", 130)
    except Exception as e:  # a full disk is the user's to fix: one line, not a traceback
        from motok.cli.output_files import disk_full_message
        if (msg := disk_full_message(e)) is not None:
            fail(msg)
        raise


def existing(ctx: typer.Context, param, value):
    """Typer callback for input paths: a path that does not exist fails at parse time, in the
    same one-line form as every other user error (typer's own ``exists=True`` draws a panel)."""
    if ctx.resilient_parsing or value is None:
        return value
    opts = [o for o in getattr(param, "opts", []) if o.startswith("--")]
    label = opts[0] if opts else (param.name or "").upper()
    for v in value if isinstance(value, (list, tuple)) else [value]:
        if not Path(v).exists():
            fail(f"{v}: no such file or directory ({label})")
    return value


# --------------------------------------------------------------------------- output

def print_json(obj) -> None:
    typer.echo(strict_json(obj))  # null, not NaN: jq and other parsers reject NaN


def wrote(summary: dict, as_json: bool, *paths) -> None:
    """The result of a command that writes files: ``summary`` as JSON, or one ``wrote PATH`` line
    per file, unwrapped so it can be copied whatever the terminal width."""
    if as_json:
        print_json(summary)
        return
    from rich.markup import escape
    for p in paths or [summary["output"]]:
        results.print(f"wrote {escape(str(p))}", soft_wrap=True, highlight=False)


def cell(v) -> str:
    """One table cell: floats to 4 significant digits, mappings as ``k=v``, sequences comma-joined."""
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, Mapping):
        return "  ".join(f"{k}={cell(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return ", ".join(cell(x) for x in v)
    return str(v)


def report(summary: dict, as_json: bool, title: str, *, hide=(),
           cells: Mapping[str, Callable[[Any], str]] | None = None) -> None:
    """A stage's summary: the whole dict as JSON with ``--json``, else a two-column table on
    stdout without the keys in ``hide``; ``cells`` formats chosen keys its own way."""
    if as_json:
        print_json(summary)
        return
    from rich.markup import escape
    from rich.table import Table
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        if k not in hide:
            t.add_row(escape(str(k)), escape((cells or {}).get(k, cell)(v)))
    results.print(t)


# --------------------------------------------------------------------------- environment

def choose_mujoco_gl() -> None:
    """MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported. Without a display its
    default (GLFW) has no context to open, so a headless ``motok`` renders through EGL unless the
    user chose a backend; ``motok.sim.render`` falls back to the stick figure if none works."""
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("MUJOCO_GL", "egl")


# --------------------------------------------------------------------------- options

def recipe_option(folder: str = "recipes/"):
    return typer.Option(None, "--recipe", help=f"YAML recipe ({folder}).")


def input_option(*names: str, help: str, required: bool = True):
    """An input file option checked by :func:`existing` (required unless ``required=False``)."""
    return typer.Option(... if required else None, *names, help=help, callback=existing)


def data_option(help: str, required: bool = True):
    """The main input of a command, ``--data``/``-d`` everywhere (motok.cli.conventions)."""
    return input_option("--data", "-d", help=help, required=required)


def clips_option(help: str):
    """``--clips GLOB``: the clip-name filter every command that reads clips takes (``pattern:`` in
    a recipe); ``help`` says what it filters and its default, which differ per command."""
    return typer.Option(None, "--clips", metavar="GLOB", help=help)


def split_option(default: str | None = None, *, help: str):
    """``--split``: one split of a dataset's split files (checked against the file's splits when
    it is read, since a dataset may carry its own)."""
    return typer.Option(default, "--split", metavar="train|val|test", help=help)


def check_output(ctx: typer.Context, path, label: str, *, folder: bool = False,
                 suffixes: tuple[str, ...] = ()) -> None:
    """The checks of an output option (:func:`output_option`) on ``path``, for an output a command
    names itself when the option is left out (``motok plot RUN`` writes ``RUN/curves.png``)."""
    from motok.atomic import OutputError, check_writable
    try:
        check_writable(path, folder=folder, suffixes=suffixes, what=label)
    except OutputError as e:
        fail(str(e))
    if not folder:  # a foreign file is never replaced; one writer per file
        from motok.cli.output_files import claim_output_file
        run(claim_output_file, ctx, path, label)


def _writable(folder: bool, suffixes: tuple[str, ...]):
    def check(ctx: typer.Context, param, value):
        if ctx.resilient_parsing or value is None:
            return value
        opts = [o for o in getattr(param, "opts", []) if o.startswith("-")]
        label = "/".join(sorted(opts, key=len)) or param.name
        for v in value if isinstance(value, (list, tuple)) else [value]:
            check_output(ctx, v, label, folder=folder, suffixes=suffixes)
        return value
    return check


def output_option(*names: str, help: str, folder: bool = False, suffixes: tuple[str, ...] = (),
                  required: bool = True, default=None):
    """An output path (``-o``/``--out`` unless ``names`` says otherwise), checked at parse time,
    before any work: not a folder where a file goes (or a file where a run folder goes), a
    suffix the writer knows, a place that can be written."""
    names = names or ("--out", "-o")
    return typer.Option(... if required else default, *names, help=help, callback=_writable(folder, suffixes))


def _in_range(within: str):
    def check(ctx: typer.Context, param, value):
        if ctx.resilient_parsing or value is None:
            return value
        from motok.ranges import range_of
        rng = range_of(within)
        label = max((o for o in getattr(param, "opts", []) if o.startswith("-")), key=len, default=param.name)
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if (why := rng.problem(v)) is not None:
                fail(f"{label} {v} {why}")
        return value
    check.within = within  # what tests read to drive every numeric option with bad values
    return check


def number_option(default, *names: str, within: str, help: str, **kw):
    """A numeric option and its valid range, checked at parse time, before any work, the way a
    config field's is (:mod:`motok.ranges`): ``within`` is a range (``"> 0"``, ``"[0, 1)"``) or,
    for an option that sets a config field, that field (``"motok.data.preprocess:PreprocessConfig.fps"``),
    so the two cannot disagree."""
    return typer.Option(default, *names, help=help, callback=_in_range(within), **kw)


DataRoot = typer.Option(None, "--data-root", help="Data folder (else $MOTOK_DATA, else ../shared/datasets).")
Sets = typer.Option([], "--set", metavar="KEY=VALUE", help="Override a config key: --set key=value (repeatable).")
# The backslash keeps rich from reading "[gpu]" as markup in --help.
Device = typer.Option(None, "--device", metavar="cpu|cuda", help="Physics device (default: the recipe's env.device, "
                      "cpu). cuda runs MuJoCo Warp (env.backend=warp; pip install 'motok\\[gpu]').")


def valid_device(device: str | None) -> str | None:
    if device is not None and device != "cpu" and not device.startswith("cuda"):
        fail(f"--device {device!r}: use cpu or cuda (cuda:N for another GPU)")
    return device


def device_sets(device: str | None) -> list[str]:
    """``--device`` as recipe overrides, before the user's ``--set`` (which win): a GPU needs the
    MuJoCo Warp backend, so ``cuda`` also sets ``env.backend=warp``."""
    if valid_device(device) is None:
        return []
    return [f"env.device={device}"] + (["env.backend=warp"] if device != "cpu" else [])
Resume = typer.Option(False, "--resume", help="Continue the run in -o exactly where it stopped.")
H5 = (".h5", ".hdf5")  # HDF5 artifacts: a .gif here would be an HDF5 file named like a video
JsonOut = typer.Option(False, "--json", help="Print the result as JSON (on stdout; progress and notes go to stderr).")
