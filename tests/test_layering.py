"""The package's layering: data flows one way, and no stage reaches back into an earlier one.

Every import of radarpc is read from the source (lazy imports and ``TYPE_CHECKING`` blocks
included) and checked file by file: against the rules between the parts of the package, and for
cycles between the files themselves.
"""
from __future__ import annotations

import ast
import functools
from collections import defaultdict
from pathlib import Path

import radarpc

SRC = Path(radarpc.__file__).parent

# What each part of the package may import from radarpc (besides itself). The contract modules
# (points, boxes, config, io, machine) sit below every stage and import nothing but each other.
CONTRACTS = {"points", "boxes", "config", "io", "machine", "__init__"}
ALLOWED = {
    "points": set(),
    "boxes": {"points"},
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
    # metrics score what they are given: no model, simulator or job
    "eval": {"sensors", "dsp", "data"} | CONTRACTS,
    # figures draw the data handed to them (data's view types, eval's report constants)
    "viz": {"sensors", "data", "eval"} | CONTRACTS,
    # the generic loop and its checkpoints: no model, dataset or experiment (those are the Task's)
    "training": {"runs", "distributed"} | CONTRACTS,
}
# never, whatever else changes: the rules
FORBIDDEN = {
    "dsp": {"data", "pipelines", "cli", "sim", "viz", "runs", "distributed", "eval", "rald", "models"},
    "data": {"pipelines", "cli", "viz", "sim"},
    "eval": {"models", "sim", "pipelines", "training", "experiments"},
    "viz": {"pipelines", "models", "training", "experiments", "sim", "dsp"},
    "training": {"models", "data", "experiments", "pipelines", "sim", "eval", "rald"},
    "models": {"training", "experiments", "data", "pipelines", "sim", "eval"},
    # an experiment is a sibling folder of experiments/: the command line sits above it
    "experiments": {"cli"},
}


def _part(module: str) -> str:
    """The first component below ``radarpc`` (a subpackage or module), ``__init__`` for names
    defined in ``radarpc/__init__.py`` itself (``from radarpc import __version__``)."""
    parts = module.split(".")
    if len(parts) < 2:
        return "__init__"
    top = parts[1]
    return top if (SRC / top).is_dir() or (SRC / f"{top}.py").is_file() else "__init__"


def _file_of(module: str, src: Path = SRC) -> Path | None:
    """The source file of a radarpc module (a package's ``__init__.py``) in the package at ``src``,
    None if there is none."""
    p = src.joinpath(*module.split(".")[1:])
    if (p / "__init__.py").is_file():
        return p / "__init__.py"
    return p.with_suffix(".py") if p.with_suffix(".py").is_file() else None


def _module_name(f: Path, src: Path = SRC) -> str:
    return ".".join(f.relative_to(src.parent).with_suffix("").parts).removesuffix(".__init__")


def _imported_files(f: Path, src: Path = SRC) -> set[Path]:
    """The radarpc files ``f`` imports, lazy ones included: ``import a.b`` and ``from a import b``
    name the file of ``a.b`` (a submodule) or else of ``a`` (``b`` a name defined there); a
    package's ``__init__.py`` counts only when it is named itself."""
    mod = _module_name(f, src)
    pkg = mod if f.name == "__init__.py" else mod.rsplit(".", 1)[0]
    names: list[str] = []
    for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base_mod = ".".join(base + ([node.module] if node.module else []))
            else:
                base_mod = node.module or ""
            names += [f"{base_mod}.{a.name}" if _file_of(f"{base_mod}.{a.name}", src) else base_mod
                      for a in node.names]
    out = set()
    for n in names:
        if n != "radarpc" and not n.startswith("radarpc."):
            continue
        target = _file_of(n, src)
        while target is None and "." in n:          # a name inside a module: the module's file
            n = n.rsplit(".", 1)[0]
            target = _file_of(n, src)
        if target is not None and target != f:
            out.add(target)
    return out


@functools.cache
def _file_graph() -> dict[Path, frozenset[Path]]:
    """``{file: the radarpc files it imports}`` for every file of the package (read once)."""
    return {f: frozenset(_imported_files(f)) for f in sorted(SRC.rglob("*.py"))}


def _imports() -> dict[str, set[tuple[str, str]]]:
    """``{file's part: {(imported part, file)}}`` for every radarpc import, lazy ones included."""
    out: dict[str, set[tuple[str, str]]] = defaultdict(set)
    for f, deps in _file_graph().items():
        mod = _module_name(f)
        src_part = _part(mod) if mod != "radarpc" else "__init__"
        for g in deps:
            dst = _module_name(g)
            dst_part = _part(dst) if dst != "radarpc" else "__init__"
            if dst_part != src_part:
                out[src_part].add((dst_part, str(f.relative_to(SRC))))
    return out


def _cycles(graph: dict) -> list[list]:
    """The strongly connected components of more than one node (Tarjan), each a cycle's members."""
    index: dict = {}
    low: dict = {}
    stack: list = []
    on_stack: set = set()
    found: list[list] = []

    def visit(v) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _a_cycle(graph: dict, members: list) -> list:
    """One closed path through a cycle's members, to name in the message."""
    inside = set(members)
    path, seen = [members[0]], {members[0]: 0}
    while True:
        nxt = min(w for w in graph[path[-1]] if w in inside)
        if nxt in seen:
            return path[seen[nxt]:] + [nxt]
        seen[nxt] = len(path)
        path.append(nxt)


def test_forbidden_imports():
    bad = [f"{f} imports radarpc.{dst}" for src, deps in _imports().items()
           for dst, f in deps if dst in FORBIDDEN.get(src, set())]
    assert not bad, "\n".join(sorted(bad))


def test_lower_layers_import_only_what_is_below_them():
    bad = [f"{f} imports radarpc.{dst}" for src, deps in _imports().items() if src in ALLOWED
           for dst, f in deps if dst not in ALLOWED[src] and dst != "__init__"]
    assert not bad, "\n".join(sorted(bad))


def test_contracts_import_only_contracts():
    contracts = CONTRACTS - {"__init__"}
    assert all(ALLOWED[c] <= contracts for c in contracts)   # the table above says so ...
    bad = [f"{f} imports radarpc.{dst}" for src, deps in _imports().items() if src in contracts
           for dst, f in deps if dst not in contracts]
    assert not bad, "\n".join(sorted(bad))                  # ... and so does the code


def test_no_cycles_between_parts():
    graph = {src: {dst for dst, _ in deps} - {"__init__"} for src, deps in _imports().items()}
    graph.pop("__init__", None)
    found = _cycles(graph)
    assert not found, "\n".join(" -> ".join(_a_cycle(graph, c)) for c in found)


def test_no_cycles_between_files():
    graph = {str(f.relative_to(SRC)): {str(g.relative_to(SRC)) for g in deps} for f, deps in _file_graph().items()}
    found = _cycles(graph)
    assert not found, "import cycles between files:\n" + "\n".join(
        " -> ".join(_a_cycle(graph, c)) + f"  (files in the cycle: {', '.join(c)})" for c in found)


def test_the_import_reader_sees_what_it_must(tmp_path):
    # the checks above are only as good as the reader: on a package made here, lazy, TYPE_CHECKING
    # and relative imports count, `from package import name` names the submodule's file when the
    # name is a submodule and the package's __init__.py when it is defined there, and a cycle is
    # found and named file by file
    src = tmp_path / "radarpc"
    files = {
        "__init__.py": "__version__ = '0'\n",
        "a.py": "import numpy\nfrom radarpc import __version__\nfrom radarpc.sub import mod2, thing\n",
        "b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from radarpc.sub.mod2 import f\n",
        "c.py": "import radarpc.sub.mod2 as m\n",
        "sub/__init__.py": "thing = 1\n",
        "sub/mod2.py": "def f():\n    from radarpc import a\n",
        "sub/rel.py": "from . import mod2\nfrom .mod2 import f\nfrom .. import b\nfrom ..c import m\n",
    }
    for name, text in files.items():
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_text(text)
    got = {str(f.relative_to(src)): sorted(str(g.relative_to(src)) for g in _imported_files(f, src))
           for f in sorted(src.rglob("*.py"))}
    assert got == {"__init__.py": [], "a.py": ["__init__.py", "sub/__init__.py", "sub/mod2.py"],
                   "b.py": ["sub/mod2.py"], "c.py": ["sub/mod2.py"], "sub/__init__.py": [],
                   "sub/mod2.py": ["a.py"], "sub/rel.py": ["b.py", "c.py", "sub/mod2.py"]}
    graph = {k: set(v) for k, v in got.items()}
    (cycle,) = _cycles(graph)
    assert cycle == ["a.py", "sub/mod2.py"] and _a_cycle(graph, cycle) == ["a.py", "sub/mod2.py", "a.py"]
    three = {"x": {"y"}, "y": {"z"}, "z": {"x", "w"}, "w": set(), "v": {"v"}}      # a self-import is no cycle
    (cycle,) = _cycles(three)
    assert _a_cycle(three, cycle) == ["x", "y", "z", "x"]
