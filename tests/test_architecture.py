"""The package's layers, checked from the source (``ast``): no cycles, cores import no edges.

Layers, innermost first (a module may import its own layer and the ones before it):

- ``pipeline.errors``: the exception types every layer raises;
- ``pipeline.core``: the paper's optics, PSFs, motions, weights, deconvolution,
  simulation, alignment: arrays in, arrays out; no files, dask, USB, CLI or TOML;
- ``pipeline.io``, ``pipeline.parallel``: files and formats; dask graphs;
- ``pipeline.jobs``, ``pipeline.workflow``, ``pipeline.tether``, ``pipeline.paper``:
  the jobs users run, built from the layers below;
- ``pipeline.commands``, ``pipeline.cli``: argparse only.

Every import counts, including those inside functions (a lazy import is still a
dependency, and a lazy cycle is still a cycle).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"

LAYERS = {
    "pipeline.errors": 0,
    "pipeline.core": 1,
    "pipeline.io": 2,
    "pipeline.parallel": 2,
    "pipeline.jobs": 3,
    "pipeline.workflow": 4,
    "pipeline.tether": 4,
    "pipeline.paper": 4,
    "pipeline.commands": 5,
    "pipeline.cli": 5,
}
# Libraries only the edges may use (cores stay pure computation).
EDGE_LIBRARIES = ("dask", "distributed", "usb", "libusb_package", "tomllib", "tifffile", "rawpy",
                  "rich", "argparse", "sqlite3", "PIL", "matplotlib")


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports_of(path: Path) -> set[str]:
    """Every module ``path`` imports (absolute names; relative imports resolved)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def graph() -> dict[str, set[str]]:
    """pipeline module -> the pipeline modules it imports."""
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    edges = {}
    for name, path in modules.items():
        edges[name] = {m for m in imports_of(path) if m in modules and m != name}
    return edges


def layer_of(module: str) -> int:
    for prefix, layer in sorted(LAYERS.items(), key=lambda kv: -len(kv[0])):
        if module == prefix or module.startswith(prefix + "."):
            return layer
    if module == "pipeline":
        return 0
    raise AssertionError(f"{module} is in no layer: add it to LAYERS in {__file__}")


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (as a path that returns to its start), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for start in sorted(edges):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def test_no_import_cycles():
    # A package __init__ re-exporting its submodules is not a cycle of concepts.
    edges = {
        m: {d for d in deps if not (m + ".").startswith(d + ".") and not d.startswith(m + ".")}
        for m, deps in graph().items()
    }
    assert find_cycle(edges) is None, f"import cycle: {' -> '.join(find_cycle(edges))}"


def test_layers_import_only_inward():
    wrong = [
        f"{m} (layer {layer_of(m)}) imports {d} (layer {layer_of(d)})"
        for m, deps in graph().items()
        for d in deps
        if layer_of(d) > layer_of(m)
    ]
    assert not wrong, "\n".join(wrong)


def test_cores_use_no_edge_libraries():
    wrong = []
    for path in (PACKAGE / "core").rglob("*.py"):
        for m in imports_of(path):
            if m.split(".")[0] in EDGE_LIBRARIES:
                wrong.append(f"{module_name(path)} imports {m}")
    assert not wrong, "\n".join(wrong)


def test_same_layer_siblings_stay_apart():
    """Jobs, workflows, tethering and the paper's figures do not reach into one another,
    except the workflow running jobs and the paper's figures using the jobs."""
    allowed = {("pipeline.workflow", "pipeline.jobs"), ("pipeline.paper", "pipeline.jobs"),
               ("pipeline.tether", "pipeline.jobs")}
    tops = ("pipeline.jobs", "pipeline.workflow", "pipeline.tether", "pipeline.paper")

    def top(m: str) -> str | None:
        return next((t for t in tops if m == t or m.startswith(t + ".")), None)

    wrong = [
        f"{m} imports {d}"
        for m, deps in graph().items()
        for d in deps
        if top(m) and top(d) and top(m) != top(d) and (top(m), top(d)) not in allowed
    ]
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize(
    ("edges", "expected"),
    [
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c", "a"]),
        ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
        ({"a": {"a2"}, "a2": {"b"}, "b": {"a2"}}, ["a2", "b", "a2"]),
    ],
)
def test_cycle_finder_finds_cycles(edges, expected):
    assert find_cycle(edges) == expected


def test_layer_check_sees_a_core_importing_an_edge(tmp_path):
    module = tmp_path / "pipeline" / "core" / "bad.py"
    module.parent.mkdir(parents=True)
    module.write_text("import dask\nfrom pipeline.jobs import stack\n")
    assert {"dask", "pipeline.jobs", "pipeline.jobs.stack"} <= imports_of_at(module, tmp_path)


def imports_of_at(path: Path, root: Path) -> set[str]:
    """:func:`imports_of` for a module under another package root (for the self-test)."""
    global PACKAGE
    saved, PACKAGE = PACKAGE, root / "pipeline"
    try:
        return imports_of(path)
    finally:
        PACKAGE = saved
