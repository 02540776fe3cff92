"""``motok info``: what is in an artifact, for any kind."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import h5py

from motok.artifacts import open_artifact, provenance_of, read_strings


def describe(path: str | Path, n_captions: int = 3) -> dict:
    path = Path(path)
    with open_artifact(path) as f:
        d: dict = {
            "path": str(path),
            "kind": str(f.attrs["kind"]),
            "schema_version": int(f.attrs["schema_version"]),
            "size_mb": round(path.stat().st_size / 1e6, 2),
            "attributes": {k: _plain(v) for k, v in f.attrs.items() if k not in ("kind", "schema_version", "provenance")},
            "provenance": provenance_of(f).__dict__,
            "datasets": {},
        }

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                d["datasets"][name] = {"shape": list(obj.shape), "dtype": str(obj.dtype)}
        f.visititems(visit)
        if "clips/split" in f:
            d["splits"] = dict(Counter(read_strings(f["clips/split"])))
            d["clips"] = len(f["clips/name"])
            d["frames" if d["kind"] in ("motion-dataset", "motion") else "rows"] = int(f["clips/offset"][-1])
        if "captions/text" in f and len(f["captions/text"]):
            names = read_strings(f["clips/name"])
            texts = f["captions/text"][:n_captions]
            clips = f["captions/clip"][:n_captions]
            d["captions"] = [{"clip": names[int(c)], "text": t.decode() if isinstance(t, bytes) else str(t)}
                             for c, t in zip(clips, texts)]
    return d


def _plain(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, str) and v.startswith("{"):
        try:
            return json.loads(v)
        except ValueError:
            return v
    return v


def print_description(d: dict, console) -> None:
    from rich.table import Table

    prov = d["provenance"]
    console.print(f"[bold]{d['path']}[/]  kind [cyan]{d['kind']}[/] v{d['schema_version']}  {d['size_mb']} MB")
    console.print(f"made by motok {prov.get('motok_version')} on {prov.get('created')}: {prov.get('command')}")
    for k, v in prov.get("inputs", {}).items():
        console.print(f"  input {k}  sha256 {v[:16]}…")
    if prov.get("skipped"):
        console.print(f"  [yellow]skipped {len(prov['skipped'])} bad input(s)[/], e.g. {prov['skipped'][0]}")
    if "clips" in d:
        rows = d.get("frames", d.get("rows"))
        unit = "frames" if "frames" in d else "rows"
        console.print(f"{d['clips']} clips, {rows} {unit}; splits {d['splits']}")
    attrs = {k: v for k, v in d["attributes"].items() if not isinstance(v, dict)}
    if attrs:
        console.print("attributes: " + ", ".join(f"{k}={v}" for k, v in attrs.items()))
    t = Table("dataset", "shape", "dtype")
    for name, v in d["datasets"].items():
        t.add_row(name, str(tuple(v["shape"])), v["dtype"])
    console.print(t)
    for c in d.get("captions", []):
        console.print(f"  [green]{c['clip']}[/]: {c['text']}")
