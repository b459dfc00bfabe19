"""The modules of ``metricslam.wire`` import each other one way only: no cycle.

Read from the source with ``ast`` (every ``import`` statement, also those inside functions), so
a cycle fails here even where Python's import order happens to let it load. ``from pkg import
name`` counts as an import of ``pkg.name`` when that is a module, else of ``pkg`` itself; the
implicit import of a parent package that every submodule import makes is left out (it would make
every package ``__init__`` that imports its submodules a cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

import metricslam.wire
import metricslam.wire.codec as codec

WIRE = "metricslam.wire"
WIRE_DIR = Path(metricslam.wire.__file__).parent


def module_names(package: str, package_dir: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (its ``__init__`` as ``package``)."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = path.relative_to(package_dir).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join((package, *parts))] = path
    return names


def import_graph(package: str, package_dir: Path) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports (anywhere in its source)."""
    modules = module_names(package, package_dir)
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: resolve against this module's package
                    base_parts = name.split(".") if is_package else name.split(".")[:-1]
                    base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                    source = ".".join([*base_parts, *([node.module] if node.module else [])])
                else:
                    source = node.module or ""
                targets = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source
                           for alias in node.names]
            for target in targets:
                # `import a.b.c` names a.b.c; keep the longest prefix that is one of the package's modules
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as ``[a, b, ..., a]``, or None (depth-first search, white/grey/black)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_wire_has_no_import_cycle() -> None:
    graph = import_graph(WIRE, WIRE_DIR)
    # the graph is really read: the codec sits on the message modules, which sit on the base
    assert {f"{WIRE}.base", f"{WIRE}.camera_messages", f"{WIRE}.map_messages"} <= graph[f"{WIRE}.codec"]
    assert f"{WIRE}.base" in graph[f"{WIRE}.map_messages"]
    assert find_cycle(graph) is None, f"import cycle in {WIRE}: {' -> '.join(find_cycle(graph) or [])}"


def test_core_has_no_import_cycle() -> None:
    """The same over the whole core (none there either when the wire cycle was broken)."""
    core_dir = WIRE_DIR.parent
    graph = import_graph("metricslam", core_dir)
    assert len(graph) > 50 and f"{WIRE}.codec" in graph
    assert find_cycle(graph) is None, f"import cycle in metricslam: {' -> '.join(find_cycle(graph) or [])}"


def test_cycle_finder_finds_the_old_codec_map_messages_cycle(tmp_path: Path) -> None:
    pkg = tmp_path / "wire"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from wire.codec import Message\n")
    (pkg / "keys.py").write_text("import re\n")
    (pkg / "codec.py").write_text("from wire.keys import x\nclass Message: ...\n"
                                  "def late():\n    from wire.map_messages import Landmarks\n")
    (pkg / "map_messages.py").write_text("from wire.codec import Message\n")
    graph = import_graph("wire", pkg)
    assert graph["wire"] == {"wire.codec"} and graph["wire.keys"] == set()
    assert find_cycle(graph) == ["wire.codec", "wire.map_messages", "wire.codec"]
    (pkg / "map_messages.py").write_text("from . import keys\nfrom .keys import y\n")
    assert import_graph("wire", pkg)["wire.map_messages"] == {"wire.keys"}
    assert find_cycle(import_graph("wire", pkg)) is None


def test_every_message_still_imports_from_the_codec_and_the_package() -> None:
    for kind, cls in codec.MESSAGE_TYPES.items():
        assert cls.KIND == kind
        assert getattr(codec, cls.__name__) is cls, f"metricslam.wire.codec.{cls.__name__} is gone"
        assert getattr(metricslam.wire, cls.__name__) is cls, f"metricslam.wire.{cls.__name__} is gone"
    for name in codec.__all__:
        assert hasattr(codec, name), name
    assert len(codec.MESSAGE_TYPES) == 9
