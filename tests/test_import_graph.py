"""The package's import graph: no circles, and the light layers stay light.

The graph is built statically (``ast`` over every ``covers_dist/**/*.py``), so it sees imports
that a run may never reach. What counts as an edge ``A -> B``:

* every ``import`` / ``from ... import`` of a ``covers_dist`` module anywhere in ``A``: at module
  level, inside functions and methods, and under ``if TYPE_CHECKING:`` (a deferred or type-only
  import is still an arrow; moving an import into a function does not cut a circle);
* ``from pkg import name`` points at the submodule ``pkg.name`` when there is one, else at ``pkg``
  (its ``__init__``);
* importing ``covers_dist.a.b`` also runs ``covers_dist/a/__init__.py``, so ``A`` gets an edge to
  each ancestor package of ``B`` too, except the ancestor packages of ``A`` itself: those are
  already being imported when ``A`` runs. So a package ``__init__`` that imports its own submodules
  (re-exports), whose submodules import each other, makes no circle; a submodule that imports
  names from its own package (``from covers_dist.clustering import PolicyBank`` inside
  ``clustering/``) does, as it would read a half-initialised package.

Not counted: imports by string (``importlib.import_module``: the CLI's command discovery and the
lazily loaded env suites), which name their targets at run time.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = "covers_dist"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE


def _modules() -> dict[str, tuple[Path, bool]]:
    """Module name -> (file, is a package ``__init__``)."""
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


MODULES = _modules()


def _imports(name: str) -> tuple[set[str], set[str]]:
    """(``covers_dist`` modules that ``name`` imports, before resolution; top-level names of every
    other package it imports)."""
    path, is_pkg = MODULES[name]
    here = name if is_pkg else name.rpartition(".")[0]
    internal: set[str] = set()
    external: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == PACKAGE:
                    internal.add(alias.name)
                else:
                    external.add(alias.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = here.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base.split(".")[0] != PACKAGE:
                external.add(base.split(".")[0])
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                internal.add(sub if sub in MODULES else base)
    return internal, external


def _resolve(target: str) -> str:
    while target not in MODULES and "." in target:
        target = target.rpartition(".")[0]
    return target


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules importing it runs (see the module docstring for what counts)."""
    graph: dict[str, set[str]] = {}
    for name in MODULES:
        own = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 2)}
        edges: set[str] = set()
        for raw in _imports(name)[0]:
            target = _resolve(raw)
            if target != name:
                edges.add(target)
            parts = target.split(".")
            edges.update(a for a in (".".join(parts[:i]) for i in range(1, len(parts))) if a in MODULES and a not in own)
        graph[name] = edges
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One concrete circle (``[a, b, ..., a]``) per strongly connected component with more than
    one module (or a module importing itself)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan; the package is a few hundred modules at most
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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
            if len(comp) > 1 or v in graph[v]:
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)

    cycles = []
    for comp in components:  # a shortest path back to the start, inside the component
        members, start = set(comp), comp[0]
        prev: dict[str, str] = {}
        frontier, seen = [start], {start}
        while frontier and start not in prev:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & members):
                    if w == start and start not in prev:
                        prev[start] = v
                    elif w not in seen:
                        seen.add(w)
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        path, v = [start], prev[start]
        while v != start:
            path.append(v)
            v = prev[v]
        cycles.append([start, *reversed(path[1:]), start])
    return cycles


def test_the_graph_sees_the_package():
    graph = import_graph()
    assert len(graph) > 50
    assert "covers_dist.clustering.bank" in graph["covers_dist.clustering.persistence"]
    assert "covers_dist.config" in graph["covers_dist.models"]
    # a function-level import is an edge: runtime.backends makes the Ray actors lazily
    assert "covers_dist.runtime.actors" in graph["covers_dist.runtime.backends"]
    # the cycle finder itself
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    cycles = find_cycles(import_graph())
    assert not cycles, "import circles in the package:\n" + "\n".join(" -> ".join(c) for c in cycles)


LIGHT_FORBIDDEN_INTERNAL = ("covers_dist.envs", "covers_dist.models", "covers_dist.config")
LIGHT_FORBIDDEN_EXTERNAL = ("ray", "fastapi", "torch")


def test_clustering_imports_no_envs_models_config_ray_fastapi_or_torch():
    bad = []
    for name in sorted(MODULES):
        if name != "covers_dist.clustering" and not name.startswith("covers_dist.clustering."):
            continue
        internal, external = _imports(name)
        for raw in sorted(internal):
            target = _resolve(raw)
            if any(target == f or target.startswith(f + ".") for f in LIGHT_FORBIDDEN_INTERNAL):
                bad.append(f"{name} -> {target}")
        bad += [f"{name} -> {e}" for e in sorted(external) if e in LIGHT_FORBIDDEN_EXTERNAL]
    assert not bad, "clustering/ must stay plain (numpy, POT, scikit-learn):\n" + "\n".join(bad)


def _run(code: str) -> None:
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT.parent, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


def test_config_imports_no_torch():
    # validation included: block_sizes' arithmetic lives in the torch-free covers_dist.sizes
    _run(
        "import covers_dist.config, sys; assert 'torch' not in sys.modules\n"
        "covers_dist.config.config_from_dict({})\n"
        "bad = [m for m in ('torch', 'covers_dist.models') if m in sys.modules]; assert not bad, bad"
    )


def test_importing_clustering_stays_light():
    _run(
        "import covers_dist.clustering, sys\n"
        "bad = [m for m in ('torch', 'ray', 'fastapi', 'covers_dist.envs', 'covers_dist.models', 'covers_dist.config')"
        " if m in sys.modules]\n"
        "assert not bad, bad"
    )
