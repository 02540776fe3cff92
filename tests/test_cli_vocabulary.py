"""The vocabulary of docs/cli.md holds for every command, including the next one added: inputs and
outputs use the table's names, a shared name is in the table with one kind of value, every old
spelling still parses to its new one with a note, the docs' command lines use none of them, and
a renamed recipe key is still read."""

from __future__ import annotations

import inspect
import re
import shlex
import shutil
import subprocess
import typing
from collections import defaultdict
from pathlib import Path

import pytest
import typer

from motok import progress
from motok.cli.conventions import ALIASES, rewrite_args, walk
from motok.cli.main import app
from conftest import assert_cli_accepts

REPO = Path(__file__).resolve().parents[1]
ROOT = typer.main.get_command(app)
COMMANDS = walk(ROOT)
DOC = (REPO / "docs" / "cli.md").read_text()


def _rows(section: str) -> list[list[str]]:
    """The cells of the table under ``## section`` of docs/cli.md, backticks removed."""
    body = DOC.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in body.splitlines() if ln.startswith("| ") and not ln.startswith("|---")]
    return [[c.strip().replace("`", "") for c in r.strip("|").split("|")] for r in rows[1:]]


TABLE = {r[0]: {"short": r[1], "kind": r[2]} for r in _rows("The names")}
OLD = [(r[0], r[1], r[2]) for r in _rows("Old spellings")]


def _options(cmd):
    """``(long name, param, value type)`` of each visible option; the type without Optional/list."""
    hints = typing.get_type_hints(inspect.unwrap(cmd.callback))
    for p in cmd.params:
        if p.param_type_name != "option" or getattr(p, "hidden", False) or p.name == "quiet":
            continue
        t = hints.get(p.name)
        while typing.get_origin(t) in (typing.Union, list) or str(typing.get_origin(t)) == "<class 'types.UnionType'>":
            t = next(a for a in typing.get_args(t) if a is not type(None))
        yield next(o for o in p.opts if o.startswith("--")), p, t


def _aliases(cmd) -> tuple[dict, str | None]:
    return getattr(cmd.callback, ALIASES, ({}, None))


def _distinct():
    """Each command once (``eval fid`` is ``eval t2m`` under another name)."""
    seen, out = set(), []
    for path, cmd in COMMANDS:
        if inspect.unwrap(cmd.callback) not in seen:
            seen.add(inspect.unwrap(cmd.callback))
            out.append((path, cmd))
    return out


def test_the_table_is_read():
    assert {"--data", "--out", "--render", "--policy", "--prior", "--expert", "--clips", "--codebooks"} <= set(TABLE)
    assert TABLE["--data"] == {"short": "-d", "kind": "input"} and TABLE["--out"]["kind"] == "output"
    assert len(OLD) >= 10


def test_inputs_and_outputs_use_the_tables_names():
    wrong = []
    for path, cmd in COMMANDS:
        for name, p, t in _options(cmd):
            writes = "_writable" in getattr(p.callback, "__qualname__", "")
            kind = TABLE.get(name, {}).get("kind")
            if writes and kind != "output":
                wrong.append(f"motok {' '.join(path)} {name}: an output not named as in docs/cli.md")
            elif t is Path and not writes and kind not in ("input", "config"):
                wrong.append(f"motok {' '.join(path)} {name}: an input not named as in docs/cli.md")
    assert not wrong, "\n".join(wrong)


def test_a_shared_name_is_in_the_table_with_one_kind_of_value_and_its_short_flag():
    uses = defaultdict(list)
    for path, cmd in _distinct():
        table, _ = _aliases(cmd)
        for name, p, t in _options(cmd):
            uses[name].append((" ".join(path), t))
            want = TABLE.get(name, {}).get("short")
            shorts = [o for o in p.opts if not o.startswith("--")]
            if want and want not in table:  # a short flag that is still an old spelling here is left out
                assert shorts == [want], f"motok {' '.join(path)} {name}: short flag {shorts}, the table says {want}"
            if shorts:
                assert TABLE.get(name, {}).get("short") == shorts[0], f"{name} {shorts}: not in docs/cli.md"
    missing = sorted(n for n, u in uses.items() if len(u) > 1 and n not in TABLE)
    assert not missing, f"names used by several commands but not in docs/cli.md: {missing}"
    for name, u in uses.items():
        types = {("path" if t is Path or name == "--data" else getattr(t, "__name__", str(t))) for _, t in u}
        assert len(types) == 1, f"{name} takes different kinds of value: {sorted(u, key=str)}"


def test_every_old_spelling_is_documented_and_retired_names_are_not_reused():
    documented = {(o.strip(), n) for old, new, _ in OLD for o in old.split(",") for n in [new.split("/")[-1]]}
    current = {o for _, cmd in COMMANDS for _, p, _ in _options(cmd) for o in p.opts}
    shorts = {row["short"] for row in TABLE.values()}
    for path, cmd in COMMANDS:
        table, positional = _aliases(cmd)
        for old, new in table.items():
            assert (old, new) in documented, f"motok {' '.join(path)}: {old} -> {new} missing from docs/cli.md"
            # an old name is retired everywhere, or it is a name of the table with the table's meaning
            # (pd-track's -o is the product elsewhere; info's --captions is what eval t2m scores)
            assert old not in current or old in TABLE or old in shorts, f"motok {' '.join(path)} {old}: reused"
        if positional:
            assert ("a positional input", positional) in documented


@pytest.mark.parametrize("path,cmd", [(p, c) for p, c in COMMANDS if any(_aliases(c))],
                         ids=[" ".join(p) for p, c in COMMANDS if any(_aliases(c))])
def test_every_old_spelling_still_parses_with_a_note(path, cmd, capsys):
    progress.configure(quiet=False)
    table, positional = _aliases(cmd)
    cases = [([old, "1"], old, new) for old, new in table.items()]
    cases += [(["1"], "a positional input", positional)] if positional else []
    for args, old, new in cases:
        param = next(p for p in cmd.params if new in p.opts)
        # resilient: callbacks that check files and required options stay out of the way
        ctx = cmd.make_context(path[-1], list(args), resilient_parsing=True)
        value = ctx.params[param.name]
        assert "1" in str(value), (path, old, new, value)
        err = capsys.readouterr().err
        assert f"{old} is now {new}" in " ".join(err.split()), (path, old, err)


# ----------------------------------------------------------------------------- command lines in the docs

DOCS = [REPO / "README.md", REPO / "Makefile", *sorted((REPO / "docs").glob("*.md")),
        *sorted((REPO / "scripts").glob("*.sh")), *sorted((REPO / "recipes").rglob("*.yaml"))]
BY_PATH = {path: cmd for path, cmd in COMMANDS}


def _command_lines(text: str):
    """``(command path, its words)`` for each ``motok ...`` command line (continuations joined)."""
    text = re.sub(r"\\\n[#\s]*", " ", text)
    for line in text.splitlines():
        if line.lstrip().startswith("|"):  # a table row of docs/cli.md's old spellings
            continue
        for m in re.finditer(r"(?:\bmotok|\"\$\{M\[@\]\}\") ([^`\n]*)", line):
            try:
                words = shlex.split(m.group(1), comments=True)
            except ValueError:
                words = m.group(1).split()
            words = [w.strip("[]()") for w in words]  # [--option VALUE] in a synopsis
            path = next((p for n in (3, 2, 1) for p in [tuple(words[:n])] if p in BY_PATH), None)
            if path:
                yield path, words[len(path):]


def test_command_lines_in_the_docs_use_no_old_spelling():
    old = []
    for f in DOCS:
        for path, words in _command_lines(f.read_text()):
            cmd = BY_PATH[path]
            table, _ = _aliases(cmd)
            for w in words:
                if w.split("=", 1)[0] in table:
                    old.append(f"{f.relative_to(REPO)}: motok {' '.join(path)} ... {w}")
    for path, cmd in COMMANDS:  # and the examples of --help
        table, _ = _aliases(cmd)
        for _, words in _command_lines(cmd.epilog or ""):
            old += [f"--help of motok {' '.join(path)}: {w}" for w in words if w.split("=", 1)[0] in table]
    assert not old, "old spellings in command lines:\n" + "\n".join(old)


def test_the_scan_sees_command_lines():
    lines = list(_command_lines("run `motok control eval --task hmd --run R -n 2` and\n"
                                '  once x y "${M[@]}" control perturb --run "$dir" \\\n    --period 0.6\n'))
    assert lines == [(("control", "eval"), ["--task", "hmd", "--run", "R", "-n", "2"]),
                     (("control", "perturb"), ["--run", "$dir", "--period", "0.6"])]


# ----------------------------------------------------------------------------- recipe keys

def test_a_renamed_recipe_key_is_read_with_a_note(tmp_path, capsys):
    from motok.config import ConfigError, load_config
    from motok.data.preprocess import PreprocessConfig

    progress.configure(quiet=False)
    recipe = tmp_path / "old.yaml"
    recipe.write_text("inputs: [a.bvh]\npattern: 'walk_*'\n")
    cfg = load_config(PreprocessConfig, recipe)
    assert cfg.data == ["a.bvh"] and cfg.clips == "walk_*"
    err = " ".join(capsys.readouterr().err.split())
    assert "key pattern is now clips" in err and "key inputs is now data" in err
    # the option (an override after the recipe) wins over the old key, as over the new one
    assert load_config(PreprocessConfig, recipe, ["clips=run_*"]).clips == "run_*"
    assert load_config(PreprocessConfig, None, ["pattern=run_*"]).clips == "run_*"
    recipe.write_text("clips: a\npattern: b\n")
    with pytest.raises(ConfigError, match="give 'clips' or its old spelling 'pattern', not both"):
        load_config(PreprocessConfig, recipe)
    # every preprocess option that sets a config key has the key's name
    keys = {f.replace("_", "-") for f in PreprocessConfig.__dataclass_fields__}
    preprocess = BY_PATH[("preprocess",)]
    config_opts = {n[2:] for n, _, _ in _options(preprocess)} - {"out", "recipe", "set", "data-root", "json"}
    assert config_opts <= keys, config_opts - keys


def test_the_note_comes_before_an_error_about_the_option(tmp_path):
    from typer.testing import CliRunner

    r = CliRunner().invoke(app, ["control", "perturb", "--run", str(tmp_path / "nope"), "-n", "1"])
    lines = [" ".join(ln.split()) for ln in r.stderr.strip().splitlines()]
    assert r.exit_code == 2 and lines[0].startswith("note: --run is now --policy"), r.stderr
    assert lines[-1] == f"error: {tmp_path / 'nope'}: no such file or directory (--policy)"
    r = CliRunner().invoke(app, ["control", "perturb", "--run", str(tmp_path / "nope"), "-q"])
    assert r.exit_code == 2 and "note:" not in r.stderr


def test_clips_and_split_read_the_same_in_every_command():
    """Declared once (cli.common.clips_option / split_option): a command that spelled its own would
    show another metavar in --help, or none."""
    want = {"--clips": "GLOB", "--split": "train|val|test"}
    seen = defaultdict(list)
    for path, cmd in _distinct():
        for name, p, _ in _options(cmd):
            if name in want:
                seen[name].append(" ".join(path))
                assert p.metavar == want[name], f"motok {' '.join(path)} {name}: metavar {p.metavar!r}"
    assert len(seen["--clips"]) >= 10 and len(seen["--split"]) >= 10, dict(seen)


def test_every_command_of_the_demos_is_accepted_by_the_cli():
    """`make demo` and `make demo-physics` run 20-30 minutes: an option renamed under them fails here,
    not half an hour in. Their commands as make expands them (``make -n``: printed, not run), each
    parsed with every option and ``--help`` last (click parses all options first, then stops)."""
    assert shutil.which("make"), "make is needed to expand the Makefile's demo targets"
    p = subprocess.run(["make", "-n", "-o", "install", "demo", "demo-physics"], cwd=REPO, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    lines = re.sub(r"\\\n\s*", " ", p.stdout).splitlines()
    cmds = [shlex.split(ln.split("bin/motok ", 1)[1]) for ln in lines if "bin/motok " in ln]
    assert len(cmds) >= 18 and {c[0] for c in cmds} >= {"preprocess", "control", "tokenize", "gpt", "render"}
    assert_cli_accepts(cmds)
