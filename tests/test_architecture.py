"""The allowed import directions, enforced by parsing every module (top-level and function-level imports).

- the pure core (model, calibration and its subpackages: dataset, plans, ISO 9283, residuals,
  discovery; the compensation of one target; motion, errors, atomic) imports the standard library, numpy,
  scipy and itself only, and of the standard library nothing that does I/O concurrency (asyncio, socket,
  subprocess, threading, selectors, multiprocessing, concurrent); in particular it imports neither the
  bus nor the service (a target is the core's, the wire format only parses and encodes it);
- ``nanodrift.drivers.base`` / ``nanodrift.drivers.registry`` never import ``daemon``;
- a plugin imports ``nanodrift.drivers.base``, the registry, the pure core and its own libraries, never the
  service, the procedures, the bus, the config or the CLI;
- the simulator's physics, scenarios, effects, runs, datasets and clock import the pure core, each
  other, numpy, scipy and the standard library only (no ``nanodrift.drivers.base``, no pydantic): the cell's
  physics works without the plugin around it;
- the service layer (service, bus, procedure, config, logs, sdnotify, reports) never names a concrete
  plugin, nor the CLI or the assembly;
- the procedures (``nanodrift.procedure``) never import the service (``nanodrift.service``): what they
  share with the daemon's actuation is ``nanodrift.outputs`` and ``nanodrift.motion``;
- only ``nanodrift.assembly`` and the CLI (``nanodrift.cli``, ``nanodrift.commands``) name concrete plugins;
- ``nanodrift.bus`` loads without plugin discovery: nothing it imports, directly or through other modules
  (a module's parent packages included), imports ``nanodrift.drivers.registry``;
- ``nanodrift.drivers.testing`` (the device emulators, for tests) imports ``nanodrift.drivers.base``, the registry, the
  plugins, pymodbus and pyserial, never the daemon beyond the pure core; nothing else of nanodrift
  imports it (the daemon never runs an emulator); only its contract kit (``nanodrift.drivers.testing.contract``)
  imports pytest, and no other module of it imports the kit (the emulators work without pytest);
- the CLI's ``HANDLERS`` table (command -> module, imported by name) names ``nanodrift.commands``
  modules only, and counts as imports; no other module imports by a string;
- a command module (``nanodrift.commands.<name>``) is imported by the CLI only: no command imports
  another, nor does a helper (``nanodrift.commands._<name>``, what several commands share) import a command;
- no cycle between units (a unit: a top-level module of ``daemon``/``drivers``, or a package's own
  modules; a subpackage is a unit of its own, so a subpackage and its parent may not import each
  other both ways), and no cycle between modules.

Every rule has a self-test below that feeds it a violation: an empty list of violations means something.
"""

from __future__ import annotations

import ast
import functools
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: the import package and the design card's folders it is installed from (pyproject's package-dir)
TOP = "nanodrift"
DRIVERS = "nanodrift.drivers"
FOLDERS = {TOP: "daemon", DRIVERS: "drivers"}
CORE_ROOTS = ("nanodrift.model", "nanodrift.calibration", "nanodrift.compensation", "nanodrift.motion",
              "nanodrift.errors", "nanodrift.atomic")
#: the Zenoh wire format and session: the edge where payloads are parsed into the core's types and encoded
BUS_ROOT = "nanodrift.bus"
CORE_THIRD_PARTY = {"numpy", "scipy"}
#: standard library the pure core may not use: it computes, it does not wait on devices or threads
CORE_FORBIDDEN_STDLIB = {"asyncio", "socket", "subprocess", "threading", "selectors", "multiprocessing",
                         "concurrent"}
DRIVER_CORE_UNITS = {"nanodrift.drivers.base", "nanodrift.drivers.registry", "nanodrift.drivers.local_port"}
PLUGIN_ROOTS = ("nanodrift.drivers.simulated", "nanodrift.drivers.modbus", "nanodrift.drivers.serial_line",
                "nanodrift.drivers.attocube_ids", "nanodrift.drivers.dcon", "nanodrift.drivers.pi_gcs")
#: the simulated cell's computation: pure core + numpy/scipy/stdlib + each other
SIMULATOR_PURE = {f"{DRIVERS}.simulated.{name}" for name in ("physics", "scenarios", "effects", "runs", "datasets",
                                                           "clock")}
ASSEMBLY_ROOTS = ("nanodrift.assembly", "nanodrift.cli", "nanodrift.commands")
#: modules that load without plugin discovery: every Zenoh client of the daemon (``nanodrift target``, a
#: lab's script) imports the bus, and must neither wait for nor fail on the installed plugins
NO_PLUGIN_DISCOVERY = ("nanodrift.bus",)
PLUGIN_DISCOVERY = "nanodrift.drivers.registry"
#: the device emulators shipped for tests (a lab's plugin tests use them too)
TESTING_ROOT = "nanodrift.drivers.testing"
#: the plugin contract kit: pytest test classes a lab's test suite imports
CONTRACT_KIT = "nanodrift.drivers.testing.contract"
#: what the kit may import beyond the emulators' libraries, with the reason (no other emulator module may)
CONTRACT_KIT_THIRD_PARTY = {
    "pytest": "the kit is pytest test classes (approx, raises, skip); a lab's test suite runs under pytest",
}
COMMANDS_PACKAGE = "nanodrift.commands"
#: the calibration and validation procedures, and the daemon's service: what both share lives beside them
#: (``nanodrift.outputs``, ``nanodrift.motion``), never in the service
PROCEDURE_ROOT = "nanodrift.procedure"
SERVICE_ROOT = "nanodrift.service"
#: optional heavy dependencies a function may import lazily, with the reason
LAZY_ALLOWED = {
    "matplotlib": "figures are drawn only when a report is asked for",
    "nanodrift.reports": "they import matplotlib (half a second) only when a report is asked for",
    "scipy.signal": "a second at every command's start (it pulls in scipy.stats); only series filtering needs it",
    "scipy.optimize": "0.3 s of CPU at every fit/calibrate start; only discovery's τ search needs it",
    # the package's PEP 562 __getattr__ (daemon/__init__.py): `import nanodrift` and `import nanodrift.model...`
    # load neither zenoh nor numpy; a lab script's `nanodrift.Client` or `nanodrift.read_csv` loads its module
    "nanodrift.client": "zenoh, loaded only when a script names nanodrift.Client (daemon/__init__.py)",
    "nanodrift.calibration.dataset": "numpy, loaded only when a script names nanodrift.read_csv/write_csv",
    "nanodrift.model.cell_model": "numpy and the model, loaded only when a script calls nanodrift.load_model",
    "nanodrift.epics_ioc": "caproto, the [epics] extra: `nanodrift ioc` says how to install it when it is missing",
    "importlib.metadata": "the CLI reads its version only for --version (every command's parser has the option)",
    "nanodrift.service.metrics_server": "prometheus_client (with http, email, urllib: ~40 ms of a daemon's start), "
                                        "only when [metrics] listen is set; a missing one fails the start",
}

Import = tuple[str, int, bool]  # (imported module, line, inside a function)


def modules() -> Iterator[tuple[str, Path]]:
    for package, folder in FOLDERS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            parts = path.relative_to(REPO / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join([package, *parts]), path


MODULES = list(modules())
MODULE_NAMES = {name for name, _ in MODULES}
PACKAGE_NAMES = {name for name, path in MODULES if path.name == "__init__.py"}


def within(name: str, roots: Iterable[str]) -> bool:
    return any(name == root or name.startswith(root + ".") for root in roots)


def ours(name: str) -> bool:
    """A module of nanodrift (the daemon's folder or the drivers')."""
    return within(name, [TOP])


def in_daemon(name: str) -> bool:
    """A module of the daemon's folder (``nanodrift`` but not ``nanodrift.drivers``)."""
    return ours(name) and not within(name, [DRIVERS])


def unit_of(module: str) -> str:
    """``nanodrift.config`` -> itself; ``nanodrift.model.terms`` -> ``nanodrift.model``; a (sub)package is its
    own unit: ``nanodrift.calibration.discovery.workflow`` -> ``nanodrift.calibration.discovery``, not
    ``nanodrift.calibration``; a third-party module -> its distribution's top name."""
    parts = module.split(".")
    if not ours(module):
        return parts[0]
    root = DRIVERS if within(module, [DRIVERS]) else TOP
    if module in PACKAGE_NAMES or len(parts) - len(root.split(".")) <= 1:
        return module
    return ".".join(parts[:-1])


def imports_in(module: str, tree: ast.Module, *, is_package: bool = False) -> Iterator[Import]:
    """Every import statement of ``tree`` (the parsed text of ``module``), plus the modules its ``HANDLERS``
    table names (imported by string at run time)."""

    def visit(node: ast.AST, in_function: bool) -> Iterator[Import]:
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
                for alias in child.names:  # "from daemon import config" imports nanodrift.config
                    candidate = f"{target}.{alias.name}"
                    if candidate in MODULE_NAMES:
                        yield candidate, child.lineno, in_function
            yield from visit(child, nested)

    yield from visit(tree, False)
    for target, line in handler_table(tree):
        yield target, line, False


def handler_table(tree: ast.Module) -> list[tuple[str, int]]:
    """The values of a module-level ``HANDLERS = {command: "module.name", ...}`` (the CLI's dispatch)."""
    found = []
    for node in tree.body:
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            named = any(isinstance(t, ast.Name) and t.id == "HANDLERS" for t in targets)
            if named and isinstance(node.value, ast.Dict):
                for value in node.value.values:
                    if not (isinstance(value, ast.Constant) and isinstance(value.value, str)):
                        raise AssertionError(f"line {value.lineno}: HANDLERS values must be module names as strings")
                    found.append((value.value, value.lineno))
    return found


@functools.cache
def parsed(path: Path) -> ast.Module:
    """A module's syntax tree, parsed once per run: the checks below each walk every module."""
    return ast.parse(path.read_text(), filename=str(path))


@functools.cache
def imports(module: str, path: Path) -> tuple[Import, ...]:
    return tuple(imports_in(module, parsed(path), is_package=path.name == "__init__.py"))


def forbidden(importer: str, imported: str) -> str | None:
    """Why module ``importer`` may not import module ``imported``, or None when it may."""
    unit = unit_of(importer)
    target = unit_of(imported)
    top = imported.split(".")[0]
    stdlib = top in sys.stdlib_module_names or top == "__future__"
    if within(unit, [TESTING_ROOT]):
        if in_daemon(imported) and not within(target, CORE_ROOTS):
            return ("the emulators import nanodrift.drivers.base, the plugins and their libraries, "
                    "never the daemon service")
        in_kit = within(importer, [CONTRACT_KIT])
        if top in CONTRACT_KIT_THIRD_PARTY and not in_kit:
            return f"only the contract kit imports {top}: the emulators work without it"
        if within(imported, [CONTRACT_KIT]) and not in_kit:
            return "the emulators never import the contract kit (it needs pytest); a test imports it by name"
        return None
    if within(target, [TESTING_ROOT]):
        return "nanodrift.drivers.testing is for tests: nothing of nanodrift imports the emulators"
    if within(unit, CORE_ROOTS):
        if within(target, [BUS_ROOT, SERVICE_ROOT]):
            return "the pure core imports neither the bus nor the service: they import it"
        if ours(imported):
            return None if within(target, CORE_ROOTS) else "the pure core imports only itself"
        if top in CORE_FORBIDDEN_STDLIB:
            return f"the pure core computes; it never uses {top} (I/O and concurrency belong to the service)"
        if stdlib or top in CORE_THIRD_PARTY:
            return None
        return f"the pure core imports only the standard library, numpy and scipy, not {top}"
    if importer in SIMULATOR_PURE:
        if ours(imported):
            if imported in SIMULATOR_PURE or within(target, CORE_ROOTS):
                return None
            return "the simulator's physics imports only the pure core and its own pure modules, not the plugin layer"
        if stdlib or top in CORE_THIRD_PARTY:
            return None
        return f"the simulator's physics imports only the standard library, numpy and scipy, not {top}"
    if unit in DRIVER_CORE_UNITS:
        return "the drivers' contract never imports the daemon" if in_daemon(imported) else None
    if within(unit, PLUGIN_ROOTS):
        if in_daemon(imported) and not within(target, CORE_ROOTS):
            return ("a plugin imports nanodrift.drivers.base and the pure core only, "
                    "never the service, bus, config or CLI")
        own = next(root for root in PLUGIN_ROOTS if within(unit, [root]))
        if within(target, PLUGIN_ROOTS) and not within(target, [own]):
            return "a plugin never imports another plugin"
        return None
    if within(unit, ASSEMBLY_ROOTS):
        return None
    if within(unit, [PROCEDURE_ROOT]) and within(target, [SERVICE_ROOT]):
        return "the procedures drive a cell through its drivers; they never reach into the daemon's service"
    # the service layer: everything else in daemon
    if within(target, PLUGIN_ROOTS):
        return "only nanodrift.assembly and the CLI name concrete plugins"
    if within(target, ASSEMBLY_ROOTS):
        return "the service layer never imports the assembly or the CLI"
    return None


def unit_graph(edges: Iterable[tuple[str, str]]) -> dict[str, set[str]]:
    """Unit -> the other units it imports (ours only)."""
    graph: dict[str, set[str]] = {}
    for importer, imported in edges:
        source, target = unit_of(importer), unit_of(imported)
        if ours(imported) and target != source:
            graph.setdefault(source, set()).add(target)
    return graph


def module_graph(edges: Iterable[tuple[str, str]], known: set[str] | None = None) -> dict[str, set[str]]:
    """Module -> the other modules (ours only) it imports."""
    known = MODULE_NAMES if known is None else known
    graph: dict[str, set[str]] = {}
    for importer, imported in edges:
        if imported in known and imported != importer:
            graph.setdefault(importer, set()).add(imported)
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[str]:
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
    return cycles


def packages_of(module: str) -> list[str]:
    """The packages Python imports before ``module``: ``nanodrift.config._lines`` -> daemon, nanodrift.config."""
    parts = module.split(".")
    return [".".join(parts[:end]) for end in range(1, len(parts))]


def import_chain(start: str, goal: str, graph: dict[str, set[str]]) -> list[str] | None:
    """The shortest chain by which importing ``start`` imports ``goal``, or None when it never does.

    A module's parent packages count as its imports: importing ``nanodrift.config._lines`` runs
    ``daemon/config/__init__.py`` first, whatever that imports."""
    previous: dict[str, str | None] = {start: None}
    queue = [start]
    for module in queue:
        if module == goal:
            chain = [module]
            while (before := previous[chain[-1]]) is not None:
                chain.append(before)
            return chain[::-1]
        for nxt in [*packages_of(module), *sorted(graph.get(module, ()))]:
            if nxt not in previous:
                previous[nxt] = module
                queue.append(nxt)
    return None


def string_imports(tree: ast.Module) -> list[str]:
    """Calls that import a module named at run time (``importlib.import_module``, ``__import__``), except
    the CLI's dispatch through its ``HANDLERS`` table (whose values the checks above read)."""
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
        if name not in ("import_module", "__import__"):
            continue
        arg = node.args[0] if node.args else None
        through_table = (isinstance(arg, ast.Subscript) and isinstance(arg.value, ast.Name)
                         and arg.value.id == "HANDLERS")
        if not through_table:
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


def all_edges() -> list[tuple[str, str]]:
    return [(module, imported) for module, path in MODULES for imported, _, _ in imports(module, path)]


# --- the rules applied to the code ------------------------------------------------------------------


def test_every_import_goes_in_an_allowed_direction() -> None:
    violations = []
    for module, path in MODULES:
        for imported, line, _ in imports(module, path):
            why = forbidden(module, imported)
            if why:
                violations.append(f"{path.relative_to(REPO)}:{line}: {module} imports {imported}: {why}")
    assert not violations, "\n".join(violations)


def test_no_cycle_between_units() -> None:
    cycles = find_cycles(unit_graph(all_edges()))
    assert not cycles, "import cycles between units:\n" + "\n".join(cycles)


def test_no_cycle_between_modules() -> None:
    cycles = find_cycles(module_graph(all_edges()))
    assert not cycles, "import cycles between modules:\n" + "\n".join(cycles)


def test_the_bus_loads_without_plugin_discovery() -> None:
    graph = module_graph(all_edges())
    chains = [import_chain(module, PLUGIN_DISCOVERY, graph) for module in sorted(MODULE_NAMES)
              if within(module, NO_PLUGIN_DISCOVERY)]
    found = [" -> ".join(chain) for chain in chains if chain is not None]
    assert not found, "plugin discovery reached from the bus (import plain tables from nanodrift.settings):\n" + \
        "\n".join(found)


def test_function_level_imports_are_only_optional_dependencies() -> None:
    lazy = []
    for module, path in MODULES:
        for imported, line, in_function in imports(module, path):
            if in_function and not any(imported == p or imported.startswith(p + ".") for p in LAZY_ALLOWED):
                lazy.append(f"{path.relative_to(REPO)}:{line}: {imported}")
    assert not lazy, "imports inside functions (hoist them; a cycle must be broken, not hidden):\n" + "\n".join(lazy)


def is_command(module: str) -> bool:
    """``nanodrift.commands.fit`` is a command; ``nanodrift.commands._cell`` (a helper) and the package are not."""
    parts = module.split(".")
    return len(parts) == 3 and module.startswith(COMMANDS_PACKAGE + ".") and not parts[-1].startswith("_")


def command_import_problems(edges: Iterable[tuple[str, str, int]]) -> list[str]:
    """``importer:line imports command``, for every import of a command module by anything but the CLI."""
    return [f"{importer}:{line} imports {imported}: a command is imported by nanodrift.cli only (shared code "
            f"goes into a helper, {COMMANDS_PACKAGE}._name, or below the CLI)"
            for importer, imported, line in edges
            if is_command(imported) and importer != "nanodrift.cli" and importer != imported]


def test_no_command_imports_another_command() -> None:
    edges = [(module, imported, line) for module, path in MODULES for imported, line, _ in imports(module, path)]
    problems = command_import_problems(edges)
    assert not problems, "\n".join(problems)


def handler_problems(source: str) -> list[str]:
    problems = []
    for target, line in handler_table(ast.parse(source)):
        if unit_of(target) != COMMANDS_PACKAGE or target not in MODULE_NAMES:
            problems.append(f"line {line}: {target!r} is not a module of {COMMANDS_PACKAGE}")
    return problems


def test_the_cli_dispatches_to_command_modules_only_and_they_count_as_imports() -> None:
    cli = REPO / "daemon" / "cli.py"
    table = handler_table(ast.parse(cli.read_text()))
    assert len(table) >= 10, "the CLI's HANDLERS table was not found (renamed?): its imports would be unchecked"
    assert not handler_problems(cli.read_text())
    edges = {imported for imported, _, _ in imports("nanodrift.cli", cli)}
    assert {target for target, _ in table} <= edges


def test_no_module_imports_by_a_string_except_through_the_cli_table() -> None:
    found = [f"{path.relative_to(REPO)}: {call}" for _, path in MODULES for call in string_imports(parsed(path))]
    assert not found, "imports by a string are invisible to these checks:\n" + "\n".join(found)


# --- the rules themselves: each catches its violation ----------------------------------------------


@pytest.mark.parametrize(
    ("importer", "imported", "allowed"),
    [
        ("nanodrift.model", "numpy", True),
        ("nanodrift.model.terms", "math", True),
        ("nanodrift.model", "zenoh", False),
        ("nanodrift.calibration", "nanodrift.drivers.simulated.cell", False),
        ("nanodrift.model.model", "nanodrift.bus.protocol", False),  # the pure core: neither the bus ...
        ("nanodrift.calibration.residuals", "nanodrift.service.health_unit", False),  # ... nor the service
        ("nanodrift.compensation", "nanodrift.bus.protocol", False),  # the compensation of a target: no wire ...
        ("nanodrift.compensation", "nanodrift.service.table", False),  # ... no service ...
        ("nanodrift.compensation", "zenoh", False),  # ... no zenoh ...
        ("nanodrift.compensation", "asyncio", False),  # ... no asyncio ...
        ("nanodrift.compensation", "nanodrift.model.cell_model", True),  # ... the model and motion are core
        ("nanodrift.bus.protocol", "nanodrift.compensation", True),  # the bus parses into and encodes the core
        ("nanodrift.service.targets", "nanodrift.compensation", True),
        ("nanodrift.procedure.steps", "nanodrift.service.actuation", False),  # a procedure: not the service
        ("nanodrift.procedure.steps", "nanodrift.outputs", True),
        ("nanodrift.calibration", "matplotlib.pyplot", False),
        # (b) the core does no I/O concurrency, and takes none of the service's libraries
        ("nanodrift.model.identify", "asyncio", False),
        ("nanodrift.calibration.plans", "socket", False),
        ("nanodrift.calibration.discovery.workflow", "subprocess", False),
        ("nanodrift.calibration.residuals", "threading", False),
        ("nanodrift.model.model", "selectors", False),
        ("nanodrift.model", "concurrent.futures", False),
        ("nanodrift.calibration.dataset", "pydantic", False),
        ("nanodrift.calibration", "structlog", False),
        ("nanodrift.model", "serial", False),
        ("nanodrift.calibration.discovery", "pymodbus.client", False),
        ("nanodrift.calibration.discovery.workflow", "nanodrift.service.runner", False),
        ("nanodrift.calibration.discovery.workflow", "nanodrift.model.terms", True),
        ("nanodrift.drivers.base", "nanodrift.config", False),
        ("nanodrift.drivers.simulated", "nanodrift.calibration.plans", True),
        ("nanodrift.drivers.simulated", "nanodrift.service.runner", False),
        ("nanodrift.drivers.modbus", "nanodrift.drivers.simulated.cell", False),
        ("nanodrift.drivers.modbus.hub", "nanodrift.drivers.modbus.config", True),
        # (d) the simulator's computation stays free of the plugin layer
        ("nanodrift.drivers.simulated.physics", "nanodrift.drivers.base", False),
        ("nanodrift.drivers.simulated.runs", "pydantic", False),
        ("nanodrift.drivers.simulated.datasets", "nanodrift.drivers.simulated.cell", False),
        ("nanodrift.drivers.simulated.clock", "zenoh", False),
        ("nanodrift.drivers.simulated.effects", "nanodrift.config", False),
        ("nanodrift.drivers.simulated.physics", "scipy.signal", True),
        ("nanodrift.drivers.simulated.physics", "nanodrift.drivers.simulated.effects", True),
        ("nanodrift.drivers.simulated.runs", "nanodrift.calibration.plans", True),
        ("nanodrift.drivers.simulated.clock", "asyncio", True),
        ("nanodrift.drivers.simulated.plugin", "nanodrift.drivers.base", True),
        ("nanodrift.drivers.simulated.config", "pydantic", True),
        ("nanodrift.service", "nanodrift.drivers.base", True),
        ("nanodrift.service", "nanodrift.drivers.simulated.plugin", False),
        ("nanodrift.procedure", "nanodrift.assembly", False),
        ("nanodrift.assembly", "nanodrift.drivers.registry", True),
        ("nanodrift.commands", "nanodrift.drivers.simulated.datasets", True),
        # the emulators: nanodrift.drivers.base, plugins, their libraries; never the service,
        # never imported by nanodrift
        ("nanodrift.drivers.testing.modbus_server", "nanodrift.drivers.modbus.config", True),
        ("nanodrift.drivers.testing", "nanodrift.drivers.serial_line.plugin", True),
        ("nanodrift.drivers.testing.pty_devices", "nanodrift.drivers.base", True),
        ("nanodrift.drivers.testing.modbus_server", "pymodbus.server", True),
        ("nanodrift.drivers.testing.pty_devices", "serial", True),
        ("nanodrift.drivers.testing.protocol", "nanodrift.drivers.testing.pty_devices", True),
        ("nanodrift.drivers.testing.modbus_server", "nanodrift.service.runner", False),
        ("nanodrift.drivers.testing", "nanodrift.config", False),
        ("nanodrift.drivers.testing.pty_devices", "nanodrift.procedure.sampler", False),
        ("nanodrift.drivers.modbus.hub", "nanodrift.drivers.testing.modbus_server", False),
        ("nanodrift.drivers.base", "nanodrift.drivers.testing", False),
        ("nanodrift.service.runner", "nanodrift.drivers.testing.pty_devices", False),
        ("nanodrift.assembly", "nanodrift.drivers.testing", False),
        ("nanodrift.cli", "nanodrift.drivers.testing.modbus_server", False),
        # the contract kit: pytest there only, and never imported by the emulators
        ("nanodrift.drivers.testing.contract", "pytest", True),
        ("nanodrift.drivers.testing.contract", "nanodrift.drivers.registry", True),
        ("nanodrift.drivers.testing.contract", "nanodrift.service.runner", False),
        ("nanodrift.drivers.testing", "pytest", False),
        ("nanodrift.drivers.testing.pty_devices", "pytest", False),
        ("nanodrift.drivers.testing", "nanodrift.drivers.testing.contract", False),
        ("nanodrift.drivers.testing.protocol", "nanodrift.drivers.testing.contract", False),
        ("nanodrift.drivers.base", "nanodrift.drivers.testing.contract", False),
    ],
)
def test_the_rules_themselves(importer: str, imported: str, allowed: bool) -> None:
    """The checker would catch each kind of violation (so an empty list above means something)."""
    assert (forbidden(importer, imported) is None) == allowed


@pytest.mark.parametrize(
    ("module", "unit"),
    [
        ("nanodrift.config", "nanodrift.config"),
        ("nanodrift.model.terms", "nanodrift.model"),
        ("nanodrift.calibration.plans", "nanodrift.calibration"),
        ("nanodrift.calibration.discovery", "nanodrift.calibration.discovery"),
        ("nanodrift.calibration.discovery.workflow", "nanodrift.calibration.discovery"),
        ("nanodrift.drivers.modbus.hub", "nanodrift.drivers.modbus"),
        ("numpy.linalg", "numpy"),
    ],
)
def test_a_subpackage_is_a_unit_of_its_own(module: str, unit: str) -> None:
    assert unit_of(module) == unit


def test_the_cycle_checks_catch_a_subpackage_and_its_parent_and_two_modules() -> None:
    parent_and_child = [
        ("nanodrift.calibration.plans", "nanodrift.calibration.discovery.workflow"),
        ("nanodrift.calibration.discovery.workflow", "nanodrift.calibration.dataset"),
    ]
    assert find_cycles(unit_graph(parent_and_child)) == [
        "nanodrift.calibration -> nanodrift.calibration.discovery -> nanodrift.calibration"]
    assert find_cycles(unit_graph(parent_and_child[:1])) == []
    inside_a_unit = [("nanodrift.model.terms", "nanodrift.model.model"),
                     ("nanodrift.model.model", "nanodrift.model.terms")]
    assert find_cycles(unit_graph(inside_a_unit)) == []  # one unit: only the module graph sees it
    assert find_cycles(module_graph(inside_a_unit)) == [
        "nanodrift.model.model -> nanodrift.model.terms -> nanodrift.model.model"]
    assert find_cycles(module_graph(inside_a_unit[:1])) == []


def test_the_discovery_check_follows_imports_and_parent_packages() -> None:
    through_modules = {"nanodrift.bus.session": {"nanodrift.config"},
                       "nanodrift.config": {"nanodrift.config._dispatch"},
                       "nanodrift.config._dispatch": {"nanodrift.drivers.registry"}}
    assert import_chain("nanodrift.bus.session", PLUGIN_DISCOVERY, through_modules) == [
        "nanodrift.bus.session", "nanodrift.config", "nanodrift.config._dispatch", "nanodrift.drivers.registry"]
    through_a_package = {"nanodrift.bus.session": {"nanodrift.config._schema"},
                         "nanodrift.config": {"nanodrift.drivers.registry"}}
    assert import_chain("nanodrift.bus.session", PLUGIN_DISCOVERY, through_a_package) == [
        "nanodrift.bus.session", "nanodrift.config._schema", "nanodrift.config", "nanodrift.drivers.registry"]
    plain = {"nanodrift.bus.session": {"nanodrift.settings"},
             "nanodrift.settings": {"nanodrift.drivers.base", "nanodrift.motion"}}
    assert import_chain("nanodrift.bus.session", PLUGIN_DISCOVERY, plain) is None


def test_the_handler_table_is_read_and_checked() -> None:
    source = ('HANDLERS = {\n    "run": "nanodrift.commands.run",\n    "sneak": "nanodrift.drivers.simulated.cell",\n'
              '    "core": "nanodrift.service.runner",\n}\n')
    found = [(imported, line) for imported, line, _ in imports_in("nanodrift.cli", ast.parse(source))]
    assert found == [("nanodrift.commands.run", 2), ("nanodrift.drivers.simulated.cell", 3),
                     ("nanodrift.service.runner", 4)]
    assert handler_problems(source) == [
        "line 3: 'nanodrift.drivers.simulated.cell' is not a module of nanodrift.commands",
        "line 4: 'nanodrift.service.runner' is not a module of nanodrift.commands",
    ]
    with pytest.raises(AssertionError, match="module names as strings"):
        handler_table(ast.parse("HANDLERS = {'run': NAME}\n"))


def test_a_command_importing_a_command_is_caught() -> None:
    assert is_command("nanodrift.commands.fit") and not is_command("nanodrift.commands._cell")
    assert not is_command("nanodrift.commands") and not is_command("nanodrift.cli")
    source = ("from nanodrift.commands.fit import read_runs\n"
              "from nanodrift.commands import target\n"
              "from nanodrift.commands._cell import open_cell\n"
              "import nanodrift.commands.status\n")
    for importer in ("nanodrift.commands.discover", "nanodrift.commands._client"):  # a command, and a helper
        edges = [(importer, imported, line) for imported, line, _ in imports_in(importer, ast.parse(source))]
        assert command_import_problems(edges) == [
            f"{importer}:{line} imports {command}: a command is imported by nanodrift.cli only (shared code goes "
            "into a helper, nanodrift.commands._name, or below the CLI)"
            for line, command in ((1, "nanodrift.commands.fit"), (2, "nanodrift.commands.target"),
                                  (4, "nanodrift.commands.status"))]
    cli = [("nanodrift.cli", imported, line) for imported, line, _ in
           imports_in("nanodrift.cli", ast.parse('HANDLERS = {"fit": "nanodrift.commands.fit"}\n'))]
    assert cli and command_import_problems(cli) == []


def test_a_string_import_outside_the_table_is_caught() -> None:
    source = ("import importlib\n"
              "a = importlib.import_module(HANDLERS[name]).main\n"
              "b = importlib.import_module('nanodrift.drivers.simulated.cell')\n"
              "c = __import__(name)\n")
    assert string_imports(ast.parse(source)) == [
        "line 3: importlib.import_module('nanodrift.drivers.simulated.cell')", "line 4: __import__(name)"]
