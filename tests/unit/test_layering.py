"""The layering of the package, read from every module's imports (ast, also the ones inside
functions), and no import cycle among the project's modules.

    protocol                      imports nothing of the project but protocol
    runtime                       protocol and runtime
    world / agents / server       protocol, runtime and themselves, never each other
    the tools (everything else)   anything
"""

from __future__ import annotations

import ast
import os
from collections.abc import Mapping
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "tagswarm"
ALLOWED = {
    "protocol": {"protocol"},
    "runtime": {"protocol", "runtime"},
    "world": {"protocol", "runtime", "world"},
    "agents": {"protocol", "runtime", "agents"},
    "server": {"protocol", "runtime", "server"},
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    return ".".join(rel.parts).removesuffix(".__init__")


def project_modules() -> dict[str, Path]:
    """Every module of the package by dotted name (the symlinked process packages included)."""
    out = {}
    for folder, _, files in os.walk(PACKAGE, followlinks=True):
        for f in files:
            if f.endswith(".py"):
                out[_module_name(Path(folder, f))] = Path(folder, f)
    return out


def imports_of(name: str, source: str, modules: Mapping[str, object]) -> set[str]:
    """The project modules ``name`` imports anywhere in ``source`` (``from a import b`` counts
    as ``a.b`` when that is a module, else as ``a``)."""
    package = name if name == "tagswarm" or name in _packages(modules) else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parent = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{parent}.{base}" if base else parent
            for a in node.names:
                if f"{base}.{a.name}" in modules:
                    found.add(f"{base}.{a.name}")
                elif base in modules:
                    found.add(base)
    return found - {name}


def _packages(modules: Mapping[str, object]) -> set[str]:
    return {m.rpartition(".")[0] for m in modules if "." in m}


def import_graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: imports_of(name, path.read_text(), modules) for name, path in modules.items()}


def layer(module: str) -> str:
    """``protocol``, ``runtime``, ``world``, ``agents``, ``server`` or ``tools``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else "tools"


def layer_violations(graph: Mapping[str, set[str]]) -> list[str]:
    bad = []
    for module, deps in sorted(graph.items()):
        allowed = ALLOWED.get(layer(module))
        if allowed is None:
            continue
        bad += [f"{module} imports {dep}" for dep in sorted(deps) if layer(dep) not in allowed]
    return bad


def cycles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
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
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def test_the_graph_covers_every_module() -> None:
    graph = import_graph()
    assert len(graph) >= 90
    for layer_name in ("protocol", "runtime", "world", "agents", "server"):
        assert any(layer(m) == layer_name for m in graph), layer_name
    assert "tagswarm.protocol.codec" in graph["tagswarm.server.node"]
    assert "tagswarm.runtime.lockstep" in graph["tagswarm.agents.nodestate"]


def test_each_layer_imports_only_what_it_may() -> None:
    assert layer_violations(import_graph()) == []


def test_no_import_cycle() -> None:
    assert cycles(import_graph()) == []


# the checks themselves can fail


def test_a_violation_is_found() -> None:
    graph = {"tagswarm.protocol.a": {"tagswarm.runtime.b"}, "tagswarm.runtime.b": {"tagswarm.protocol.a"},
             "tagswarm.world.c": {"tagswarm.agents.d", "tagswarm.protocol.a"}, "tagswarm.agents.d": set(),
             "tagswarm.view.e": {"tagswarm.world.c"}, "tagswarm.runtime.f": {"tagswarm.server.g"},
             "tagswarm.server.g": {"tagswarm.view.e"}}
    assert layer_violations(graph) == ["tagswarm.protocol.a imports tagswarm.runtime.b",
                                       "tagswarm.runtime.f imports tagswarm.server.g",
                                       "tagswarm.server.g imports tagswarm.view.e",
                                       "tagswarm.world.c imports tagswarm.agents.d"]


def test_a_cycle_is_found_also_through_an_import_inside_a_function() -> None:
    modules = {"tagswarm.protocol.layout": None, "tagswarm.protocol.scenario": None, "tagswarm.protocol": None,
               "tagswarm.protocol.tags": None}
    scenario = "from tagswarm.protocol import tags\n\ndef f():\n    from tagswarm.protocol.layout import x\n"
    layout = "from tagswarm.protocol.scenario import Scenario\n"
    graph = {"tagswarm.protocol.scenario": imports_of("tagswarm.protocol.scenario", scenario, modules),
             "tagswarm.protocol.layout": imports_of("tagswarm.protocol.layout", layout, modules),
             "tagswarm.protocol.tags": set()}
    assert graph["tagswarm.protocol.scenario"] == {"tagswarm.protocol.tags", "tagswarm.protocol.layout"}
    assert cycles(graph) == [["tagswarm.protocol.layout", "tagswarm.protocol.scenario"]]


@pytest.mark.parametrize(("source", "expected"), [
    ("from . import codec\n", {"tagswarm.protocol.codec"}),
    ("from .messages import Tick\n", {"tagswarm.protocol.messages"}),
    ("from ..runtime import streams\n", {"tagswarm.runtime.streams"}),
    ("import tagswarm.protocol.codec as c\n", {"tagswarm.protocol.codec"}),
    ("import numpy\nfrom msgspec import Struct\n", set()),
])
def test_relative_and_aliased_imports_resolve(source: str, expected: set[str]) -> None:
    modules = {m: None for m in ("tagswarm.protocol", "tagswarm.protocol.codec", "tagswarm.protocol.messages",
                                 "tagswarm.protocol.bus", "tagswarm.runtime", "tagswarm.runtime.streams")}
    assert imports_of("tagswarm.protocol.bus", source, modules) == expected


#: a module past this wants splitting (issue: "no product module over ~500 lines")
MAX_MODULE_LINES = 425


def test_no_product_module_is_too_long() -> None:
    long = {name: n for name, path in project_modules().items()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"
