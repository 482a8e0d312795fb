"""Imports run one way. Every ``import`` / ``from`` statement is read with :mod:`ast`, at
module level and inside functions alike (a lazy import that dodges a circle is still a
circle), and:

* the modules of ``service/`` import each other without a cycle, in layers: settings and
  the services container at the bottom, domain modules above them, process wiring above
  those, the CLI at the top;
* ``worker/`` never imports ``service/``; ``model/`` never imports ``service/``, and of
  ``worker/`` only the leaves (``WORKER_LEAVES``: the one image reader, the working-resolution
  photo, the sRGB curves, the colour table, the domain errors, the names and bounds the parts
  agree on), which import nothing of the project but each other and no onnxruntime,
  scikit-image or torch, so that training reads photos exactly as an upload is read;
* torch is imported only under ``model/`` (the service and the worker run on ONNX).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: lowest first; a module may import its own layer or those below, never one above
LAYERS = (
    ("settings and container", {"service.vocabulary", "service.settings", "service.container"}),
    ("domain", {"service.auth", "service.jobs", "service.limits", "service.purge", "service.job_kinds"}),
    ("process wiring", {"service.context", "service.runner", "service.processes"}),
    ("CLI", {"service.cli"}),
)


#: modules of worker/ that model/ may import: numpy / OpenImageIO / Pillow / stdlib, and each other
WORKER_LEAVES = {"worker.decode", "worker.photo", "worker.colour", "worker.colour_match", "worker.errors",
                 "worker.contract"}
LEAF_THIRD_PARTY = {"numpy", "OpenImageIO", "PIL"}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(package: str) -> dict[str, Path]:
    """Dotted name -> file, for every module of ``package`` (a top-level folder)."""
    return {module_name(p): p for p in sorted((ROOT / package).rglob("*.py")) if "__pycache__" not in p.parts}


def imported(name: str, path: Path) -> list[tuple[str, int]]:
    """(dotted name, line) of everything ``path`` imports, anywhere in the file. ``from X
    import y`` yields ``X.y`` (a submodule, or an attribute of ``X``) after ``X``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            found.append((source, node.lineno))
            found += [(f"{source}.{alias.name}", node.lineno) for alias in node.names]
    return found


def package_graph(package: str) -> dict[str, dict[str, int]]:
    """module of ``package`` -> {module of the same package it imports: line}."""
    known = modules(package)
    graph: dict[str, dict[str, int]] = {name: {} for name in known}
    for name, path in known.items():
        for target, line in imported(name, path):
            if target in known and target != name and target != package:  # the package: version only
                graph[name].setdefault(target, line)
    return graph


def service_graph() -> dict[str, dict[str, int]]:
    """service module -> {service module it imports: line}."""
    return package_graph("service")


def find_cycle(graph: dict[str, dict[str, int]]) -> list[str] | None:
    """One import cycle as [a, b, ..., a], or None."""
    state: dict[str, str] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = "open"
        stack.append(node)
        for target in graph[node]:
            if state.get(target) == "open":
                return stack[stack.index(target):] + [target]
            if target not in state and (cycle := visit(target)):
                return cycle
        stack.pop()
        state[node] = "done"
        return None

    for node in graph:
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_cycle_finder_sees_a_cycle() -> None:
    assert find_cycle({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": 1}, "b": {}, "c": {"a": 1, "b": 1}}) is None


def test_service_imports_have_no_cycle() -> None:
    graph = service_graph()
    assert {"service.cli", "service.context", "service.container", "service.runner"} <= set(graph)
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle in service/: " + " -> ".join(
        f"{a} (line {graph[a][b]})" for a, b in zip(cycle, cycle[1:])) + f" -> {cycle[-1]}"


def test_worker_imports_have_no_cycle() -> None:
    # (colour_match once reached back into images, which imports runtime, which imports colour_match)
    graph = package_graph("worker")
    assert {"worker.runtime", "worker.images", "worker.colour_match"} <= set(graph)
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle in worker/: " + " -> ".join(cycle)


def test_service_layers_import_downwards() -> None:
    graph = service_graph()
    level = {name: i for i, (_, members) in enumerate(LAYERS) for name in members}
    assert set(level) <= set(graph), "a layer names a module that does not exist"
    upward = [f"{name} ({LAYERS[level[name]][0]}) imports {target} ({LAYERS[level[target]][0]}) "
              f"on line {line}"
              for name, targets in graph.items() if name in level
              for target, line in targets.items() if level.get(target, -1) > level[name]]
    assert not upward, "\n".join(upward)


@pytest.mark.parametrize(("package", "forbidden"), [("worker", ("service",)), ("model", ("service", "worker"))])
def test_lower_packages_do_not_import_upper_ones(package: str, forbidden: tuple[str, ...]) -> None:
    bad = [f"{path.relative_to(ROOT)}:{line} imports {target}"
           for name, path in modules(package).items() for target, line in imported(name, path)
           if target.split(".")[0] in forbidden and not is_leaf_import(target)]
    assert not bad, "\n".join(bad)


def is_leaf_import(target: str) -> bool:
    """``target`` is a worker leaf, or a name taken from one (``worker.decode.read_image``);
    the bare ``worker`` package of ``from worker import x`` counts by its ``x``."""
    return any(target == leaf or target.startswith(leaf + ".") for leaf in WORKER_LEAVES) or target == "worker"


def test_worker_leaves_import_only_each_other_numpy_openimageio_and_pillow() -> None:
    """The leaves model/ may import pull in nothing else of the project (no runtime, no
    onnxruntime, no scikit-image, no torch): standard library, numpy, OpenImageIO, Pillow."""
    import sys

    known = modules("worker")
    assert WORKER_LEAVES <= set(known), "a leaf named here does not exist"
    bad = []
    for leaf in sorted(WORKER_LEAVES):
        for target, line in imported(leaf, known[leaf]):
            top = target.split(".")[0]
            if top == "__future__" or top in sys.stdlib_module_names or top in LEAF_THIRD_PARTY:
                continue
            if top == "worker" and is_leaf_import(target):
                continue
            bad.append(f"{known[leaf].relative_to(ROOT)}:{line} imports {target}")
    assert not bad, "\n".join(bad)


def test_model_reads_photos_with_the_upload_reader() -> None:
    """model/ decodes exemplars through worker.decode (one reader for upload, fit,
    training and evaluation); Pillow opens files only where ``fetch`` converts the packaged
    source images into the PNG data set (model/data.py: _read_source)."""
    readers = [str(path.relative_to(ROOT)) for name, path in modules("model").items()
               if any(target == "worker.decode.read_image" for target, _ in imported(name, path))]
    assert readers == ["model/data.py"], readers
    opened = []
    for path in modules("model").values():
        for func in ast.walk(ast.parse(path.read_text())):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)) or func.name == "_read_source":
                continue
            opened += [f"{path.relative_to(ROOT)}:{node.lineno} ({func.name})" for node in ast.walk(func)
                       if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                       and node.func.attr == "open" and getattr(node.func.value, "id", None) == "Image"]
    assert not opened, "Pillow reads a photo outside fetch: " + ", ".join(opened)


def test_the_product_never_imports_the_eval_tools() -> None:
    """eval/ (the tools ``make`` runs) is not in the wheel: service/, worker/ and model/ never import it."""
    bad = [f"{path.relative_to(ROOT)}:{line} imports {target}"
           for package in ("service", "worker", "model") for name, path in modules(package).items()
           for target, line in imported(name, path) if target.split(".")[0] == "eval"]
    assert not bad, "\n".join(bad)
