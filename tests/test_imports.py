"""No import cycles inside motok, found statically.

Every module under ``motok/`` is parsed with ``ast`` and every import counts, at module level
or inside a function (a lazy import that closes a circle still ties the two modules together,
and moving it to the top is then an ImportError). Relative imports are resolved against the
importing module; ``from motok.x import y`` points at ``motok.x.y`` when that is a module and at
``motok.x`` otherwise; importing ``a.b.c`` also runs ``a`` and ``a.b``, so those count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "motok"


def module_files(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under the package folder ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts) + 1)]


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The modules of ``modules`` that importing ``name`` (source at ``path``) may run."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            targets = [stem]
            targets += [f"{stem}.{a.name}" for a in node.names if f"{stem}.{a.name}" in modules]
        for t in targets:
            found.update(m for m in _with_parents(t) if m in modules)
    found.discard(name)
    return found


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    files = module_files(root)
    return {name: imports_of(name, path, set(files)) for name, path in files.items()}


def tangles(graph: dict[str, set[str]]) -> list[set[str]]:
    """Strongly connected components of more than one module (Tarjan's algorithm, iterative so
    deep import chains cannot hit the recursion limit)."""
    index, low, on_stack, stack, comps = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        return v, iter(sorted(graph[v]))

    for start in sorted(graph):
        if start in index:
            continue
        work = [visit(start)]
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    work.append(visit(w))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = set()
                while not comp or w != v:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.add(w)
                if len(comp) > 1:
                    comps.append(comp)
    return comps


def shortest_cycle(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """``[a, b, ..., a]``: the shortest way from the first module of ``comp`` back to itself."""
    first = min(comp)
    prev, frontier = {first: None}, [first]
    while not any(first in graph[v] for v in frontier):
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & comp):
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    path = [next(v for v in frontier if first in graph[v])]
    while prev[path[-1]] is not None:
        path.append(prev[path[-1]])
    return path[::-1] + [first]


def find_cycles(graph: dict[str, set[str]]) -> list[tuple[list[str], set[str]]]:
    """One shortest cycle per tangle, with every module of the tangle."""
    return sorted((shortest_cycle(graph, comp), comp) for comp in tangles(graph))


def test_no_import_cycles():
    lines = []
    for cycle, comp in find_cycles(import_graph()):
        others = sorted(comp - set(cycle))
        lines.append("  " + " -> ".join(cycle) + (f"  (same tangle: {', '.join(others)})" if others else ""))
    assert not lines, "import cycles in motok:\n" + "\n".join(lines)


def test_cycle_finder_sees_lazy_relative_and_submodule_imports(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "def f():\n    from pkg.sub import b\n",  # function-level, names a submodule
        "sub/__init__.py": "",
        "sub/b.py": "from . import c\n",  # relative, names a submodule
        "sub/c.py": "from ..a import f\n",  # two levels up
        "d.py": "import pkg.sub.c\n",  # outside the cycle: imports into it only
    }
    for rel, text in files.items():
        (pkg / rel).write_text(text)
    graph = import_graph(pkg)
    assert graph["pkg.a"] == {"pkg", "pkg.sub", "pkg.sub.b"} and graph["pkg.sub.c"] == {"pkg", "pkg.a"}
    assert find_cycles(graph) == [(["pkg.a", "pkg.sub.b", "pkg.sub.c", "pkg.a"], {"pkg.a", "pkg.sub.b", "pkg.sub.c"})]


def folder_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The import graph between the package's rooms: every module stands for its stage folder
    (``motok.data.bvh`` -> ``motok.data``) or itself at the top (``motok.atomic``); the package's
    own ``__init__`` is left out (importing anything runs it)."""
    def room(m: str) -> str:
        return ".".join(m.split(".")[:2])
    out: dict[str, set[str]] = {}
    for m, deps in graph.items():
        if m == "motok":
            continue
        out.setdefault(room(m), set()).update(room(d) for d in deps if d != "motok")
    for r, deps in out.items():
        deps.discard(r)
    return out


def test_no_cycles_between_stage_folders():
    """The stages are layers: a folder that imports another is never imported back by it (the
    data <-> features and tokenizer <-> eval loops once were), so each can be read, tested and
    replaced from the bottom up."""
    graph = folder_graph(import_graph())
    assert {"motok.data", "motok.features", "motok.control", "motok.skeleton"} <= set(graph)
    cycles = [" -> ".join(c) for c, _ in find_cycles(graph)]
    assert not cycles, "stage folders importing each other:\n  " + "\n  ".join(cycles)


def test_folder_graph_joins_a_loop_through_two_files_of_one_folder(tmp_path):
    pkg = tmp_path / "motok"
    for rel, text in {"__init__.py": "", "low/__init__.py": "", "low/a.py": "from motok.high import b\n",
                      "low/c.py": "", "high/__init__.py": "", "high/b.py": "from motok.low import c\n"}.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    graph = import_graph(pkg)
    assert find_cycles(graph) == []  # no file loop: a -> b -> c
    assert [c for c, _ in find_cycles(folder_graph(graph))] == [["motok.high", "motok.low", "motok.high"]]


TRAINERS = {"motok.control.rl.runner", "motok.control.priors.distill", "motok.control.priors.dagger"}
INFERENCE = ("motok.gpt.sample", "motok.tokenizer.tokens", "motok.control.track", "motok.control.text_to_physics",
             "motok.control.priors.load", "motok.control.priors.generate", "motok.control.priors.evaluate",
             "motok.control.expert.evaluate", "motok.control.highlevel.evaluate", "motok.api.models", "motok.api.motion")


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for m in graph[todo.pop()] - seen:
            seen.add(m)
            todo.append(m)
    return seen


def test_sampling_tracking_and_evaluation_never_import_a_trainer():
    """Loaders live beside their models, so reading a trained run never runs training code (a
    trainer's imports, its registrations, its failure modes)."""
    graph = import_graph()
    trainers = TRAINERS | {m for m in graph if m.endswith(".train")}
    found = {m: sorted(reachable(graph, m) & trainers) for m in INFERENCE}
    assert not {m: t for m, t in found.items() if t}, found
