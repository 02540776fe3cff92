"""``motok info``: what is in an artifact or a checkpoint bundle, for any kind."""

from __future__ import annotations

import json
import struct
from collections import Counter
from pathlib import Path

import h5py

from motok.artifacts import ArtifactError, open_artifact, provenance_of, read_strings
from motok.errors import MissingFileError, MotokError, UserError


def describe(path: str | Path, n_captions: int = 3) -> dict:
    """Everything ``motok info`` shows about ``path``: an HDF5 artifact, or a checkpoint bundle
    (its folder or its ``bundle.json``)."""
    path = Path(path)
    if not path.exists():
        raise MissingFileError(f"{path}: no such file or directory")
    if path.is_dir() or path.name == "bundle.json":
        return describe_bundle(path if path.is_dir() else path.parent)
    return describe_artifact(path, n_captions)


def describe_artifact(path: Path, n_captions: int = 3) -> dict:
    with open_artifact(path) as f:
        d: dict = {
            "path": str(path),
            "kind": str(f.attrs["kind"]),
            "schema_version": int(f.attrs["schema_version"]),
            "size_mb": round(path.stat().st_size / 1e6, 2),
            "attributes": {k: _plain(v) for k, v in f.attrs.items()
                           if k not in ("kind", "schema_version", "provenance")},
            "datasets": {},
            "warnings": [],
        }
        try:
            d["provenance"] = provenance_of(f).__dict__
        except ArtifactError as e:
            d["provenance"] = {}
            d["warnings"].append(str(e))

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                d["datasets"][name] = {"shape": list(obj.shape), "dtype": str(obj.dtype)}
        f.visititems(visit)
        if "clips/split" in f:
            d["splits"] = dict(Counter(read_strings(f["clips/split"])))
            d["clips"] = len(f["clips/name"])
            d["frames" if d["kind"] in ("motion-dataset", "motion") else "rows"] = int(f["clips/offset"][-1])
        if "captions/text" in f and len(f["captions/text"]) and "clips/name" in f:
            names = read_strings(f["clips/name"])
            texts = f["captions/text"][:n_captions]
            clips = f["captions/clip"][:n_captions]
            d["captions"] = [{"clip": names[int(c)], "text": t.decode() if isinstance(t, bytes) else str(t)}
                             for c, t in zip(clips, texts)]
    return d


def safetensors_header(path: Path) -> dict:
    """Tensor names, dtypes and shapes from the header of a safetensors file, without reading
    the weights (the format: 8-byte little-endian header length, then a JSON header)."""
    try:
        with open(path, "rb") as fh:
            n = struct.unpack("<Q", fh.read(8))[0]
            if n > 100_000_000:
                raise ValueError(f"header length {n} is implausible")
            header = json.loads(fh.read(n))
    except (OSError, struct.error, ValueError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: not a readable safetensors file ({e})") from None
    header.pop("__metadata__", None)
    return header


def describe_bundle(run: Path) -> dict:
    # Here, not at the top: describing an HDF5 file should not wait for torch to import.
    from motok.checkpoint import read_meta, read_weights, resolve_ref

    meta = read_meta(run)
    files = {p.name: p.stat().st_size for p in sorted(run.iterdir()) if p.is_file() and not p.name.startswith(".")}
    d: dict = {
        "path": str(run), "kind": meta.get("kind"), "schema_version": meta.get("schema_version"),
        "size_mb": round(sum(files.values()) / 1e6, 2), "files": files,
        "provenance": meta.get("provenance") or {}, "config": meta.get("config") or {},
        "extra": {k: _short(v) for k, v in (meta.get("extra") or {}).items()},
        "references": {}, "tensors": {}, "parameters": 0, "model_sha256": meta.get("model_sha256"), "warnings": [],
    }
    extra = meta.get("extra") or {}
    for key in meta.get("refs") or [k for k in ("tokenizer", "tokens", "text_cache", "dataset", "data") if k in extra]:
        if extra.get(key):
            found = next((p for p in resolve_ref(extra[key], run) if p.exists()), None)
            d["references"][key] = {"stored": extra[key], "found": str(found) if found else None}
            if found is None:
                d["warnings"].append(f"its {key} {extra[key]!r} does not exist")
    weights = run / "model.safetensors"
    if not weights.is_file():
        d["warnings"].append("no model.safetensors")
        d["weights"] = "missing"
        return d
    try:
        for name, t in safetensors_header(weights).items():
            n = 1
            for s in t["shape"]:
                n *= int(s)
            d["tensors"][name] = {"shape": list(t["shape"]), "dtype": t["dtype"]}
            d["parameters"] += n
        read_weights(run, meta)
        d["weights"] = "verified against model_sha256"
    except MotokError as e:
        d["weights"] = "REFUSED"
        d["warnings"].append(str(e))
    return d


def _short(v):
    """Bundle metadata fit for a summary: long lists and nested tables are counted, not shown."""
    if isinstance(v, list) and len(v) > 8:
        return f"<list of {len(v)}>"
    if isinstance(v, dict) and len(json.dumps(v, default=str)) > 160:
        return f"<{len(v)} fields>"
    return v


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


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _machine_line(m: dict) -> str:
    pk = m.get("packages", {})
    parts = [f"{m.get('cpu')}, {m.get('cores')} cores"]
    if "torch" in pk:
        parts.append(f"torch {pk['torch']}" + (f" ({m['torch_cpu_capability']})" if m.get("torch_cpu_capability") else ""))
    if "numpy" in pk:
        parts.append(f"numpy {pk['numpy']} ({'+'.join(m.get('numpy_simd') or ['baseline'])})")
    parts += [f"{p} {pk[p]}" for p in pk if p not in ("torch", "numpy")]
    parts += [f"{k}={v}" for k, v in (m.get("env") or {}).items()]
    return ", ".join(parts)


def _provenance(d: dict, console) -> None:
    prov = d["provenance"]
    if prov:
        console.print(f"made by motok {prov.get('motok_version')} on {prov.get('created')}: {prov.get('command')}",
                      highlight=False)
    if prov.get("machine"):
        console.print(f"  on {_machine_line(prov['machine'])}", highlight=False)
    for k, v in prov.get("inputs", {}).items():
        console.print(f"  input {k}  sha256 {str(v)[:16]}…", highlight=False)
    if prov.get("skipped"):
        console.print(f"  [yellow]skipped {len(prov['skipped'])} bad input(s)[/], e.g. {prov['skipped'][0]}")
    for w in d.get("warnings", []):
        console.print(f"[yellow]warning:[/] {w}", highlight=False)


def print_description(d: dict, console) -> None:
    from rich.table import Table

    console.print(f"[bold]{d['path']}[/]  kind [cyan]{d['kind']}[/] v{d['schema_version']}  {d['size_mb']} MB")
    _provenance(d, console)
    if "tensors" in d:
        _print_bundle(d, console)
        return
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


def _print_bundle(d: dict, console) -> None:
    from rich.markup import escape
    from rich.table import Table

    console.print(f"files: {', '.join(f'{k} ({v / 1e6:.2f} MB)' for k, v in d['files'].items())}", highlight=False)
    for key, r in d["references"].items():
        where = r["found"] or "[red]missing[/]"
        console.print(f"  {key} -> {escape(r['stored'])} ({escape(where) if r['found'] else where})", highlight=False)
    cfg = _flat(d["config"])
    if cfg:
        console.print("config: " + escape(", ".join(f"{k}={v}" for k, v in cfg.items())), highlight=False)
    scalars = {k: v for k, v in d["extra"].items() if not isinstance(v, (dict, list)) and k not in d["references"]}
    if scalars:
        console.print("metadata: " + escape(", ".join(f"{k}={v}" for k, v in scalars.items())), highlight=False)
    t = Table("tensor", "shape", "dtype", title=f"{len(d['tensors'])} tensors, {d['parameters']:,} parameters; "
                                                f"weights {d.get('weights')}")
    for name, v in d["tensors"].items():
        t.add_row(name, str(tuple(v["shape"])), v["dtype"])
    console.print(t)
