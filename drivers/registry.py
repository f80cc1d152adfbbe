"""Find driver plugins by name through the ``nanodrift.drivers`` entry-point group, and answer the two
questions asked of them all: which plugin owns a top-level config table, which one is the virtual cell.

A lab adds a driver by installing a package that declares an entry point in that group; nanodrift
itself needs no change. The config (when it validates) and the assembly (when it builds) ask these
questions here, so both get the same answer.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from functools import cache
from importlib.metadata import entry_points

from nanodrift.drivers.base import DriverPlugin, VirtualCellPlugin

GROUP = "nanodrift.drivers"

#: how a kind becomes its plugin: :func:`load_plugin` (raises), or a caller's loader that reports a
#: failure its own way and returns None
Loader = Callable[[str], DriverPlugin | None]


class UnknownDriverError(LookupError):
    pass


@cache
def available() -> dict[str, str]:
    """Driver kind -> the entry point's target, for messages and ``--help``."""
    return {ep.name: ep.value for ep in entry_points(group=GROUP)}


@cache
def load_plugin(kind: str) -> DriverPlugin:
    """The plugin for ``kind``; an error listing the installed kinds when there is none."""
    for ep in entry_points(group=GROUP):
        if ep.name == kind:
            plugin = ep.load()
            if not isinstance(plugin, DriverPlugin):
                raise UnknownDriverError(
                    f"driver {kind!r} ({ep.value}) is not a nanodrift.drivers.base.DriverPlugin instance")
            return plugin
    names = ", ".join(sorted(available())) or "none (is nanodrift installed?)"
    raise UnknownDriverError(f"unknown sensor kind {kind!r}; installed driver kinds: {names}")


def owner_of_section(name: str, kinds: Iterable[str] = (), load: Loader = load_plugin) -> str | None:
    """The kind whose plugin owns the top-level table ``name`` (its ``section``), or None: no plugin does.

    ``kinds`` (those the config uses) are asked first, then every other installed kind, each loaded
    with ``load``.
    """
    first = list(kinds)
    for kind in first:  # before the entry points are listed: a config's own kind owns its table (~4 ms a listing)
        plugin = load(kind)
        if plugin is not None and plugin.section == name:
            return kind
    for kind in (k for k in available() if k not in first):
        plugin = load(kind)
        if plugin is not None and plugin.section == name:
            return kind
    return None


def virtual_cell_plugin(kinds: Iterable[str], load: Loader = load_plugin) -> tuple[str, VirtualCellPlugin] | None:
    """The first of ``kinds`` whose plugin is a virtual cell (a :class:`VirtualCellPlugin`): its kind and
    plugin, or None (a real cell)."""
    for kind in kinds:
        plugin = load(kind)
        if isinstance(plugin, VirtualCellPlugin):
            return kind, plugin
    return None


def quietly(kind: str) -> DriverPlugin | None:
    """:func:`load_plugin`, None for a plugin that fails to load (it is reported where it is used)."""
    try:
        return load_plugin(kind)
    except Exception:  # a broken third-party plugin must not hide the installed ones that work
        return None
