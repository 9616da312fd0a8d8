"""The package's layering: data flows one way, and no stage reaches back into an earlier one."""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import radarpc

SRC = Path(radarpc.__file__).parent

# What each part of the package may import from radarpc (besides itself). The contract modules
# (points, config, io, machine) sit below every stage.
CONTRACTS = {"points", "config", "io", "machine", "__init__"}
ALLOWED = {
    "points": set(),
    "config": {"io"},
    "io": set(),
    "machine": set(),
    "sensors": set(),
    "dsp": {"sensors"} | CONTRACTS,
    "data": {"sensors", "dsp"} | CONTRACTS,
    "sim": {"sensors", "dsp", "data", "runs"} | CONTRACTS,
    "runs": {"io"},
    "distributed": {"machine"},
    "models": {"sensors", "dsp"} | CONTRACTS,
}
# never, whatever else changes: the rules
FORBIDDEN = {
    "dsp": {"data", "pipelines", "cli", "sim", "viz", "runs", "distributed", "eval", "rald", "models"},
    "data": {"pipelines", "cli", "viz", "sim"},
}


def _part(module: str) -> str:
    """The first component below ``radarpc`` (a subpackage or module), ``__init__`` for names
    defined in ``radarpc/__init__.py`` itself (``from radarpc import __version__``)."""
    parts = module.split(".")
    if len(parts) < 2:
        return "__init__"
    top = parts[1]
    return top if (SRC / top).is_dir() or (SRC / f"{top}.py").is_file() else "__init__"


def _imports() -> dict[str, set[tuple[str, str]]]:
    """``{file's part: {(imported part, file)}}`` for every radarpc import, lazy ones included."""
    out: dict[str, set[tuple[str, str]]] = defaultdict(set)
    for f in SRC.rglob("*.py"):
        rel = f.relative_to(SRC.parent).with_suffix("")
        mod = ".".join(rel.parts)
        mod = mod.removesuffix(".__init__")
        src_part = _part(mod) if mod != "radarpc" else "__init__"
        pkg = mod if f.name == "__init__.py" else mod.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    names = [".".join(base + ([node.module] if node.module else []))]
                else:
                    names = [node.module or ""]
                if names == ["radarpc"]:
                    names = [f"radarpc.{a.name}" for a in node.names]
            for n in names:
                if n.startswith("radarpc.") and _part(n) != src_part:
                    out[src_part].add((_part(n), str(f.relative_to(SRC))))
    return out


def test_forbidden_imports():
    bad = [f"{f} imports radarpc.{dst}" for src, deps in _imports().items()
           for dst, f in deps if dst in FORBIDDEN.get(src, set())]
    assert not bad, "\n".join(sorted(bad))


def test_lower_layers_import_only_what_is_below_them():
    bad = [f"{f} imports radarpc.{dst}" for src, deps in _imports().items() if src in ALLOWED
           for dst, f in deps if dst not in ALLOWED[src] and dst != "__init__"]
    assert not bad, "\n".join(sorted(bad))


def test_no_cycles_between_parts():
    graph = {src: {dst for dst, _ in deps} for src, deps in _imports().items()}
    graph.pop("__init__", None)
    state: dict[str, int] = {}
    cycles = []

    def visit(n, path):
        state[n] = 1
        for m in sorted(graph.get(n, ())):
            if m == "__init__":
                continue
            if state.get(m) == 1:
                cycles.append(" -> ".join(path[path.index(m):] + [m]) if m in path else f"{n} -> {m}")
            elif m not in state:
                visit(m, path + [m])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])
    assert not cycles, "\n".join(cycles)
