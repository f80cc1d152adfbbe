"""The allowed import directions, enforced by parsing every module (top-level and function-level imports).

- the pure core (model, calibration: dataset, plans, ISO 9283, discovery; errors, atomic) imports
  the standard library, numpy, scipy and itself only;
- ``drivers.base`` / ``drivers.registry`` never import ``daemon``;
- a plugin imports ``drivers.base``, the registry, the pure core and its own libraries, never the
  service, the procedures, the bus, the config or the CLI;
- the service layer (service, bus, procedure, config, logs, sdnotify, reports) never names a concrete
  plugin, nor the CLI or the assembly;
- only ``daemon.assembly`` and the CLI (``daemon.cli``, ``daemon.commands``) name concrete plugins;
- no cycle between units (a unit: a top-level module of ``daemon``/``drivers``, or a subpackage).
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("daemon", "drivers")
CORE_UNITS = {"daemon.model", "daemon.calibration", "daemon.errors", "daemon.atomic"}
CORE_THIRD_PARTY = {"numpy", "scipy"}
DRIVER_CORE_UNITS = {"drivers.base", "drivers.registry"}
PLUGIN_UNITS = {"drivers.simulated", "drivers.modbus", "drivers.serial_line"}
ASSEMBLY_UNITS = {"daemon.assembly", "daemon.cli", "daemon.commands"}
#: optional heavy dependencies a function may import lazily, with the reason
LAZY_ALLOWED = {
    "matplotlib": "figures are drawn only when a report is asked for",
    "daemon.reports": "they import matplotlib (half a second) only when a report is asked for",
}


def modules() -> Iterator[tuple[str, Path]]:
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join(parts), path


def unit_of(module: str) -> str:
    """``daemon.config`` -> itself; ``daemon.model.terms`` -> ``daemon.model``;
    ``drivers.modbus.hub`` -> ``drivers.modbus``."""
    parts = module.split(".")
    if parts[0] not in PACKAGES:
        return parts[0]
    return ".".join(parts[:2]) if len(parts) >= 2 else parts[0]


def imports(module: str, path: Path) -> Iterator[tuple[str, int, bool]]:
    """(imported module, line, inside a function) for every import statement of ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"

    def visit(node: ast.AST, in_function: bool) -> Iterator[tuple[str, int, bool]]:
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            if isinstance(child, ast.Import):
                for alias in child.names:
                    yield alias.name, child.lineno, in_function
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = module.split(".")
                    base = base[: len(base) - child.level + (1 if is_package else 0)]
                    target = ".".join([*base, child.module] if child.module else base)
                else:
                    target = child.module or ""
                yield target, child.lineno, in_function
                for alias in child.names:  # "from daemon import config" imports daemon.config
                    candidate = f"{target}.{alias.name}"
                    if any(name == candidate for name, _ in MODULES):
                        yield candidate, child.lineno, in_function
            yield from visit(child, nested)

    yield from visit(tree, False)


MODULES = list(modules())


def forbidden(importer: str, imported: str) -> str | None:
    """Why ``importer`` (a unit) may not import ``imported`` (a module), or None when it may."""
    target = unit_of(imported)
    top = imported.split(".")[0]
    if importer in CORE_UNITS:
        if top in PACKAGES:
            return None if target in CORE_UNITS else "the pure core imports only itself"
        if top in sys.stdlib_module_names or top == "__future__" or top in CORE_THIRD_PARTY:
            return None
        return f"the pure core imports only the standard library, numpy and scipy, not {top}"
    if importer in DRIVER_CORE_UNITS:
        return "drivers.base and the registry never import daemon" if top == "daemon" else None
    if importer in PLUGIN_UNITS:
        if top == "daemon" and target not in CORE_UNITS:
            return "a plugin imports drivers.base and the pure core only, never the service, bus, config or CLI"
        if target in PLUGIN_UNITS and target != importer:
            return "a plugin never imports another plugin"
        return None
    if importer in ASSEMBLY_UNITS:
        return None
    # the service layer: everything else in daemon
    if target in PLUGIN_UNITS:
        return "only daemon.assembly and the CLI name concrete plugins"
    if target in ASSEMBLY_UNITS:
        return "the service layer never imports the assembly or the CLI"
    return None


def test_every_import_goes_in_an_allowed_direction() -> None:
    violations = []
    for module, path in MODULES:
        importer = unit_of(module)
        for imported, line, _ in imports(module, path):
            why = forbidden(importer, imported)
            if why:
                violations.append(f"{path.relative_to(REPO)}:{line}: {module} imports {imported}: {why}")
    assert not violations, "\n".join(violations)


def test_no_cycle_between_units() -> None:
    graph: dict[str, set[str]] = {}
    for module, path in MODULES:
        source = unit_of(module)
        for imported, _, _ in imports(module, path):
            target = unit_of(imported)
            if imported.split(".")[0] in PACKAGES and target != source:
                graph.setdefault(source, set()).add(target)
    cycles = []
    state: dict[str, int] = {}  # 1: on the stack, 2: done

    def walk(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join([*stack[stack.index(nxt):], nxt]))
            elif nxt not in state:
                walk(nxt, [*stack, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            walk(node, [node])
    assert not cycles, "import cycles between units:\n" + "\n".join(cycles)


def test_function_level_imports_are_only_optional_dependencies() -> None:
    lazy = []
    for module, path in MODULES:
        for imported, line, in_function in imports(module, path):
            if in_function and not any(imported == p or imported.startswith(p + ".") for p in LAZY_ALLOWED):
                lazy.append(f"{path.relative_to(REPO)}:{line}: {imported}")
    assert not lazy, "imports inside functions (hoist them; a cycle must be broken, not hidden):\n" + "\n".join(lazy)


@pytest.mark.parametrize(
    ("importer", "imported", "allowed"),
    [
        ("daemon.model", "numpy", True),
        ("daemon.model", "zenoh", False),
        ("daemon.calibration", "drivers.simulated.cell", False),
        ("daemon.calibration", "matplotlib.pyplot", False),
        ("drivers.base", "daemon.config", False),
        ("drivers.simulated", "daemon.calibration.plans", True),
        ("drivers.simulated", "daemon.service.runner", False),
        ("drivers.modbus", "drivers.simulated.cell", False),
        ("daemon.service", "drivers.base", True),
        ("daemon.service", "drivers.simulated.plugin", False),
        ("daemon.procedure", "daemon.assembly", False),
        ("daemon.assembly", "drivers.registry", True),
        ("daemon.commands", "drivers.simulated.datasets", True),
    ],
)
def test_the_rules_themselves(importer: str, imported: str, allowed: bool) -> None:
    """The checker would catch each kind of violation (so an empty list above means something)."""
    assert (forbidden(importer, imported) is None) == allowed
