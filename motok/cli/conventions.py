"""What makes every ``motok`` command speak the same language, applied in one place to the whole
command tree when the root app is built (:class:`MotokGroup`), so a stage CLI (including ones
registered later) gets it without doing anything:

- ``--quiet``/``-q`` is accepted after the subcommand as well as before it;
- flags are shown as flags in ``--help`` (typer's rich help labels them ``<bool>``);
- old option spellings keep working for one release as hidden aliases (:func:`renamed`): they
  are rewritten to the new ones before parsing, with a note on stderr that names the release
  they go in (:data:`ALIASES_GO_IN`), and never appear in ``--help``, so a short flag has one
  meaning everywhere.

The vocabulary itself is docs/cli.md (its table is what tests/test_cli_vocabulary.py checks every
command against): the main input of a command is ``--data``/``-d``; models are named by kind
(``--tokenizer``/``-t``, ``--gpt``/``-g``, ``--evaluator``/``-e``, ``--expert``, ``--prior``,
``--policy``); what a command exists to make is ``-o``/``--out``, a video beside it ``--render``;
one clip is ``--clip``, a clip-name glob is ``--clips``; ``info`` and ``plot`` take the file they
describe as their argument.
"""

from __future__ import annotations

from typing import Callable

import typer
from typer.core import TyperGroup

from motok import progress

ALIASES = "__motok_aliases__"
# The release that drops the hidden aliases: the spellings of 0.1.0 still work through 0.2.x
# (README, "The stages"; CHANGELOG 0.2.0).
ALIASES_GO_IN = "0.3.0"


def renamed(positional: str | None = None, **old_to_new: str) -> Callable:
    """Mark a command's old spellings: ``@renamed(tokens="--data")`` maps ``--tokens`` to
    ``--data`` (a one-letter key is a short flag: ``i="--data"`` maps ``-i``); ``positional``
    names the option an old positional argument now goes to."""
    table = {(f"-{k}" if len(k) == 1 else "--" + k.replace("_", "-")): v for k, v in old_to_new.items()}

    def mark(fn):
        setattr(fn, ALIASES, (table, positional))
        return fn
    return mark


def _quiet(ctx: typer.Context, param, value: bool):
    if value and not ctx.resilient_parsing:
        progress.configure(quiet=True)


def _quiet_command(quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or chatter (results "
                                              "and errors are still printed).", callback=_quiet, is_eager=True,
                                              expose_value=False)):
    """Carries the --quiet option every command gets."""


def _quiet_option():
    """A fresh ``--quiet`` parameter, built by typer itself from :func:`_quiet_command` (one per
    command: a parameter object belongs to one command)."""
    app = typer.Typer()
    app.command()(_quiet_command)
    return next(p for p in typer.main.get_command(app).params if p.name == "quiet")


def _takes_value(cmd, opt: str) -> bool:
    for p in cmd.params:
        if opt in getattr(p, "opts", ()) or opt in getattr(p, "secondary_opts", ()):
            return p.param_type_name == "option" and not getattr(p, "is_flag", False) \
                and not getattr(p, "count", False)
    return False


def rewrite_args(cmd, args: list[str], table: dict[str, str],
                 positional: str | None) -> tuple[list[str], list]:
    """``args`` with old spellings replaced (see :func:`renamed`); returns ``(args, [(old, new)])``."""
    has_arguments = any(p.param_type_name == "argument" for p in cmd.params)
    out, used, i = [], [], 0
    while i < len(args):
        a = args[i]
        if a == "--":
            rest = args[i + 1:]
            if positional and not has_arguments and rest:
                used.append(("a positional input", positional))
                out += [x for r in rest for x in (positional, r)]
            else:
                out += [a, *rest]
            break
        if a.startswith("-") and a != "-":
            name, eq, val = a.partition("=") if a.startswith("--") else (a, "", "")
            if name in table:
                used.append((name, table[name]))
                name = table[name]
            out.append(name + eq + val)
            if not eq and _takes_value(cmd, name) and i + 1 < len(args):
                out.append(args[i + 1])
                i += 1
        elif positional and not has_arguments:
            used.append(("a positional input", positional))
            out += [positional, a]
        else:
            out.append(a)
        i += 1
    return out, used


def _with_aliases(cmd, table, positional):
    parse = cmd.parse_args

    def parse_args(ctx, args):
        args, used = rewrite_args(cmd, list(args), table, positional)
        # Before parsing, so an error about the option (a missing file) follows the note that
        # names it; a --quiet after the subcommand is not parsed yet: it is looked for here.
        options = args[:args.index("--")] if "--" in args else args
        if not {"-q", "--quiet"} & set(options):
            for old, new in dict(used).items():
                progress.info(f"[yellow]note:[/] {old} is now {new} (the old spelling works until motok {ALIASES_GO_IN})")
        return parse(ctx, args)
    return parse_args


def _show_flags_as_flags(cmd) -> None:
    """Typer's rich help labels a flag ``<bool>`` and a repeatable option ``<list[str]>``: a flag
    gets no label, a repeatable option the label of one value (the help says "repeatable")."""
    ctx = typer.Context(cmd)
    params = list(cmd.params)
    helper = cmd.get_help_option(ctx)  # built once and cached by the command
    params += [helper] if helper is not None else []
    for p in params:
        if p.metavar is not None or p.param_type_name != "option":
            continue
        if getattr(p, "is_flag", False):
            p.metavar = ""
        elif p.multiple:
            label = str(p.display_type(ctx))
            p.metavar = label.replace("<list[", "<").replace("]>", ">").replace("<Path>", "<path>")


def polish(cmd) -> None:
    """Apply the conventions above to one leaf command (idempotent)."""
    if getattr(cmd, "_motok_polished", False):
        return
    cmd._motok_polished = True
    if not any("--quiet" in getattr(p, "opts", ()) for p in cmd.params):
        cmd.params.append(_quiet_option())
    table, positional = getattr(cmd.callback, ALIASES, ({}, None))
    if table or positional:
        cmd.parse_args = _with_aliases(cmd, table, positional)
    _show_flags_as_flags(cmd)


def walk(group) -> list:
    """Every leaf command under ``group``, as ``(path, command)`` with the path a tuple of names."""
    out = []
    for name, cmd in getattr(group, "commands", {}).items():
        if hasattr(cmd, "commands"):
            out += [((name, *path), c) for path, c in walk(cmd)]
        else:
            out.append(((name,), cmd))
    return out


class MotokGroup(TyperGroup):
    """The root ``motok`` group: polishes every command below it when it is built."""

    def __init__(self, **kw):
        super().__init__(**kw)
        _show_flags_as_flags(self)
        for _, cmd in walk(self):
            polish(cmd)
        for g in _groups(self):
            _show_flags_as_flags(g)

    def invoke(self, ctx):
        """A value of the wrong type (``--seconds abc``) is one ``error:`` line and exit 2, like
        every other bad value, instead of typer's usage panel; a missing option keeps the panel,
        which shows the usage it lacks."""
        try:
            return super().invoke(ctx)
        except typer.BadParameter as e:
            if type(e).__name__ == "MissingParameter":  # a subclass typer does not export
                raise
            from motok.cli.common import fail
            fail(e.format_message())


def _groups(group) -> list:
    out = []
    for cmd in getattr(group, "commands", {}).values():
        if hasattr(cmd, "commands"):
            out += [cmd, *_groups(cmd)]
    return out


def examples(*lines: str) -> str:
    """An epilog of examples for ``--help`` (one paragraph each, so rich keeps them apart)."""
    return "\n\n".join(["Examples:", *lines])
