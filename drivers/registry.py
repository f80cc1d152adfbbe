"""Find driver plugins by name through the ``nanodrift.drivers`` entry-point group.

A lab adds a driver by installing a package that declares an entry point in that group; nanodrift
itself needs no change.
"""

from __future__ import annotations

from functools import cache
from importlib.metadata import entry_points

from drivers.base import DriverPlugin

GROUP = "nanodrift.drivers"


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
                    f"driver {kind!r} ({ep.value}) is not a drivers.base.DriverPlugin instance")
            return plugin
    names = ", ".join(sorted(available())) or "none (is nanodrift installed?)"
    raise UnknownDriverError(f"unknown sensor kind {kind!r}; installed driver kinds: {names}")
