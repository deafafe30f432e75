"""The import structure: no cycles, the core never imports the app, no library imports a command line.

Every ``import`` in ``companion/`` and ``perception/`` counts, function-level and TYPE_CHECKING ones included
(a cycle hidden in a function is still a cycle: it decides what must be loaded before what).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# The pure core: the paper's math, the decisions, the scorer, the config schema. It is what the app, the simulators,
# replay and the studies share, so it may depend on none of them.
CORE = {
    "companion.guidance", "companion.frames", "companion.controller", "companion.closing", "companion.ownmotion",
    "companion.engagement", "companion.targetlock", "companion.hover", "companion.limits", "companion.reasons",
    "companion.scoring", "companion.core", "companion.metrics", "companion.baseline", "companion.vehicle",
    "companion.configbase", "companion.config_app", "companion.config_perception",
}
# What the core may not import: the app, the simulators, the studies, the command lines. (The config schema's
# own sections, companion.sim.config and companion.px4sitl.config, are schema, not simulator.)
UPWARD = ("companion.app", "companion.sim", "companion.px4sitl", "companion.evaluation", "companion.replay",
          "companion.cli", "companion.calibrate", "companion.logtools", "companion.bench", "companion.check")
SCHEMA = ("companion.sim.config", "companion.px4sitl.config")
# Command-line modules: they import libraries; no library imports them.
CLI = {"companion.cli", "companion.app.main", "companion.sim.cli", "companion.evaluation.cli",
       "companion.sim.px4.cli", "companion.sim.px4.__main__"}


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in ("companion", "perception"):
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = p
    return mods


def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports (the deepest module an import names)."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for m, path in mods.items():
        deps: set[str] = set()
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                deps.update(r for a in node.names if (r := resolve(a.name)))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = m.split(".") if is_pkg else m.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    name = ".".join([*base, node.module] if node.module else base)
                else:
                    name = node.module or ""
                for a in node.names:  # `from pkg import module` names the module, `from mod import f` the module
                    r = resolve(f"{name}.{a.name}") if f"{name}.{a.name}" in mods else resolve(name)
                    if r:
                        deps.add(r)
        deps.discard(m)
        graph[m] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


GRAPH = import_graph()


def test_the_walk_sees_function_level_imports():
    # companion.core imports companion.controller inside FlightCore.from_config only: the walk must see it.
    assert "companion.controller" in GRAPH["companion.core"]
    assert set(CORE) <= set(GRAPH), set(CORE) - set(GRAPH)


def test_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    assert cycles(GRAPH) == []


@pytest.mark.parametrize("module", sorted(CORE))
def test_the_core_imports_nothing_above_it(module):
    bad = sorted(d for d in GRAPH[module] if d.startswith(UPWARD) and not d.startswith(SCHEMA))
    assert bad == [], f"{module} imports {bad}"


def test_perception_imports_no_app():
    for m, deps in GRAPH.items():
        if m.startswith("perception"):
            bad = sorted(d for d in deps if d.startswith(UPWARD) and not d.startswith(SCHEMA))
            assert bad == [], f"{m} imports {bad}"


def test_no_library_imports_a_command_line():
    assert set(GRAPH) | {"companion.sim.px4.__main__"} >= CLI
    for m, deps in GRAPH.items():
        if m in CLI:
            continue
        assert not (deps & CLI), f"{m} imports the command line {sorted(deps & CLI)}"
