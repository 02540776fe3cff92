"""What ``--resume`` may change: nothing that would make the continued run differ from one that
was never interrupted.

A resumed run continues with the config it was saved with. A recipe or ``--set`` given with
``--resume`` is compared with it, and any setting that would change what the steps compute is
refused with what differs (:func:`resolve_config`); each trainer names the few settings that may
change because they do not (how often to log, the run's length where no schedule spans it).
Every input a run records (its data set, the runs it was made from, its humanoid, its clips) is
compared with the one a resume would use, by content hash, and a difference is an error that
names it (:func:`check_inputs`).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Iterable

from motok.config import ConfigError, checked, from_dict, load_config, to_dict
from motok.errors import UserError


def differences(saved: dict, wanted: dict, derived: Iterable[str] = (), prefix: str = "") -> list[tuple[str, Any, Any]]:
    """``(dotted key, saved value, wanted value)`` of every setting that differs. For the keys in
    ``derived`` a wanted ``None`` or ``""`` means "derive it" (from the run this one is made from,
    a command-line option), which the saved config holds resolved: no difference."""
    out = []
    for k in sorted(set(saved) | set(wanted)):
        a, b, key = saved.get(k), wanted.get(k), f"{prefix}{k}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, derived, f"{key}.")
        elif a != b and not (key in derived and b in (None, "")):
            out.append((key, a, b))
    return out


def _rules(cfg) -> tuple[set[str], tuple[str, ...]]:
    """What a config class says about resuming: the settings a resume may change (its
    ``resume_may_change()``) and those derived at the start of a run (``RESUME_DERIVED``)."""
    free = set(cfg.resume_may_change()) if hasattr(cfg, "resume_may_change") else set()
    return free, tuple(getattr(cfg, "RESUME_DERIVED", ()))


def _refuse(run, refused: list, free: set) -> None:
    if refused:
        what = ", ".join(f"{k} {a!r} -> {b!r}" for k, a, b in refused)
        may = f" (a resume may change {', '.join(sorted(free))})" if free else ""
        raise ConfigError(f"--resume continues {run} with the settings it was trained with; this would change "
                          f"{what}{may}: leave them out, or train a new run")


def resolve_config(cls, recipe, overrides: Iterable[str], run, kind: str, resume: bool):
    """The config of a run: from ``recipe`` and ``overrides`` for a new run; for a resume, the
    saved one, which ``overrides`` apply to when no recipe is given (so a resume needs no recipe).
    Any setting the recipe or ``overrides`` would change is refused, except those the config
    class lets a resume change. A resume of a folder without a bundle is left to the trainer,
    which says there is nothing to resume."""
    from motok.checkpoint import read_meta

    if not resume or not (Path(run) / "bundle.json").is_file():
        return load_config(cls, recipe, overrides)
    run = Path(run)
    # Through the dataclasses, so keys newer than the bundle get their defaults.
    saved_cfg = from_dict(cls, copy.deepcopy(read_meta(run, kind)["config"]))
    saved = to_dict(saved_cfg)
    wanted = to_dict(load_config(cls, recipe, overrides, base=None if recipe is not None else copy.deepcopy(saved)))
    free, derived = _rules(saved_cfg)
    diffs = differences(saved, wanted, derived)
    _refuse(run, [d for d in diffs if d[0] not in free], free)
    out = copy.deepcopy(saved)
    for k, _, b in diffs:
        *parents, leaf = k.split(".")
        node = out
        for p in parents:
            node = node[p]
        node[leaf] = b
    return checked(from_dict(cls, out))


def check_settings(run, saved: dict, cfg) -> None:
    """Refuse to resume ``run`` (saved config ``saved``) with a config ``cfg`` that differs in
    anything but what the config class lets a resume change: what a trainer called from code gets,
    beside :func:`resolve_config` for the command line."""
    free, _ = _rules(cfg)
    saved = to_dict(from_dict(type(cfg), copy.deepcopy(saved)))
    _refuse(run, [d for d in differences(saved, to_dict(cfg)) if d[0] not in free], free)


def check_inputs(run, meta: dict, *, data_hash: str | None = None, links: dict | None = None,
                 clips: list[str] | None = None, flags: dict[str, str] | None = None) -> None:
    """Refuse a resume whose inputs are not the ones ``run`` (its bundle metadata ``meta``) was
    trained on: the data set (``data_hash``, its SHA-256, against the provenance's), the runs it
    was made from (``links``: :func:`motok.control.runs.link_record` entries, compared by weights
    hash) and the clips. ``flags`` names the option that chose each link (``{"expert": "--expert"}``)."""
    ex, flags = meta.get("extra", {}), flags or {}
    recorded = list((meta.get("provenance") or {}).get("inputs", {}).items())
    if data_hash is not None and recorded and data_hash not in {h for _, h in recorded}:
        path, h = recorded[0]
        raise UserError(f"--resume: {run} was trained on another data set ({path}, sha256 {h[:12]}; this one "
                        f"is {data_hash[:12]}): resume with the same file, or train a new run")
    for key, info in (links or {}).items():
        if not key.endswith("_info"):
            continue
        name = key[:-len("_info")]
        before = ex.get(key)
        if before is None:
            raise UserError(f"{flags.get(name, name)} {info['absolute']}: {run} was not made from one, and a resume "
                            f"continues it as it was: {flags.get(name, name)} applies to a new run only")
        if before.get("model_sha256") != info.get("model_sha256"):
            was = f"{before['absolute']} (weights sha256 {str(before.get('model_sha256'))[:12]})"
            raise UserError(f"{flags.get(name, name)} {info['absolute']}: {run} was made from another {name}, "
                            f"{was}; this one's weights are sha256 {str(info.get('model_sha256'))[:12]}. A resume "
                            f"continues with the run's own {name}: name that one, or train a new run")
    if clips is not None and ex.get("clips") is not None and list(ex["clips"]) != list(clips):
        gone = [c for c in ex["clips"] if c not in set(clips)][:3]
        new = [c for c in clips if c not in set(ex["clips"])][:3]
        raise UserError(f"--resume: {run} was trained on {len(ex['clips'])} clips, this command selects "
                        f"{len(clips)} (missing e.g. {gone}, new e.g. {new}): resume with the same --data, --clips "
                        f"and --split, or train a new run")


def carried_links(run, meta: dict, extra: dict) -> dict:
    """The link records of the saved ``meta`` (the runs ``run`` was made from: ``KEY`` and
    ``KEY_info``) that ``extra`` does not name again, so a resume never drops them from the bundle
    (a warm-started expert resumed without ``--init`` still says where it started)."""
    ex, refs = meta.get("extra", {}), set(meta.get("refs", ()))
    out = {}
    for key, info in ex.items():
        name = key[:-len("_info")] if key.endswith("_info") else None
        if name and key not in extra and isinstance(info, dict):
            out[key] = info
            if name in ex:
                out[name] = Path(run) / ex[name] if name in refs else ex[name]
    return out
