"""The import graph keeps the layout's promises: no circles, and every arrow pointing down.

Read with :mod:`ast` from the source, so an import inside a function or under ``TYPE_CHECKING``
counts as much as one at the top: each is a dependency a reader has to follow.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("training", "flightsim", "companion")  # each may import those after it, never before

#: the layer of each subpackage (a module directly in the package: the top layer); an import may
#: go to a lower layer or within its own subpackage, never up nor sideways
LAYERS: dict[str, dict[str, int]] = {
    "companion": {
        "common": 0,
        "perception": 1,
        "autopilot": 2,
        "lidar": 2,
        "recording": 2,
        "params": 3,
        "guidance": 4,
        "safety": 4,
        "": 5,
    },
    "flightsim": {"vehicle": 0, "worlds": 0, "envs": 1, "sitl": 2, "": 3},
}
#: training is flat: the controller registry and model loading/export sit below the rest, with
#: the leaf modules they build on
TRAINING_BASE = {
    "config",
    "baselines",
    "path_expert",
    "predictive_expert",
    "space_time_expert",
    "mirror",
    "attackers",
    "scan_features",
    "batched_vec_env",
    "sharded_vec_env",
    "vec_env",
    "controllers",
    "export",
}


def module_files() -> dict[str, Path]:
    """Every module of the three packages by dotted name."""
    modules = {}
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the project modules it imports (``from a import b`` counts ``a.b`` when a module)."""

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets: set[str] = set()
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                found = [base] + [f"{base}.{alias.name}" for alias in node.names]
            else:
                continue
            for target in found:
                if target.split(".")[0] in PACKAGES and (resolved := resolve(target)) and resolved != name:
                    targets.add(resolved)
        graph[name] = targets
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import that runs against the package order or a package's layers."""
    bad = []
    for source, targets in sorted(graph.items()):
        top, *rest = source.split(".")
        for target in sorted(targets):
            target_top, *target_rest = target.split(".")
            if PACKAGES.index(target_top) < PACKAGES.index(top):
                bad.append(f"{source} -> {target}: {top} may not import {target_top}")
            elif target_top != top:
                continue
            elif top in LAYERS:
                layers = LAYERS[top]
                here = rest[0] if rest and rest[0] in layers else ""
                there = target_rest[0] if target_rest and target_rest[0] in layers else ""
                if here != there and layers[here] <= layers[there]:
                    bad.append(f"{source} -> {target}: layer {here or top} may not import {there or top}")
            elif rest and rest[0] in TRAINING_BASE and target_rest and target_rest[0] not in TRAINING_BASE:
                bad.append(f"{source} -> {target}: the registry and model modules may not import the rest")
    return bad


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(module_files())


def test_no_module_imports_itself_round_a_circle(graph: dict[str, set[str]]) -> None:
    assert circles(graph) == []


def test_every_import_points_down_the_layers(graph: dict[str, set[str]]) -> None:
    assert layer_violations(graph) == []


def test_every_subpackage_has_a_layer() -> None:
    for package, layers in LAYERS.items():
        subpackages = {p.parent.name for p in (REPO / package).glob("*/__init__.py")}
        assert subpackages <= set(layers), f"{package}: give {sorted(subpackages - set(layers))} a layer"


def test_the_checks_find_a_circle_and_an_upward_import() -> None:
    """The checks themselves, on a graph made to break both rules."""
    made = {
        "companion.perception.scan": {"companion.safety.shield"},
        "companion.safety.shield": {"companion.perception.scan"},
        "flightsim.vehicle.control": {"training.train"},
        "training.train": set(),
    }
    assert circles(made) == [["companion.perception.scan", "companion.safety.shield"]]
    assert layer_violations(made) == [
        "companion.perception.scan -> companion.safety.shield: layer perception may not import safety",
        "flightsim.vehicle.control -> training.train: flightsim may not import training",
    ]
