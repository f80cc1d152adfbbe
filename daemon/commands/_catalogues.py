"""The simulated cell's scenario and effect catalogues as ``--help`` text, from the one place they are defined.

``simulate``, ``calibrate``, ``validate`` and ``demo`` list them under their options (numpy only, no
zenoh: listing them costs no more than the catalogues themselves).
"""

from __future__ import annotations

import textwrap

from nanodrift.drivers.simulated.effects import EFFECTS
from nanodrift.drivers.simulated.scenarios import SCENARIOS


def _epilog(title: str, items: dict[str, str]) -> str:
    width = max(len(name) for name in items) + 2
    lines = [f"{title}:"]
    for name, text in items.items():
        wrapped = textwrap.wrap(text, 96 - width) or [""]
        lines.append(f"  {name:<{width}}{wrapped[0]}")
        lines.extend(f"  {'':<{width}}{more}" for more in wrapped[1:])
    return "\n".join(lines)


def scenario_names() -> str:
    return ", ".join(SCENARIOS)


def effect_names() -> str:
    return ", ".join(EFFECTS)


def scenario_epilog() -> str:
    return _epilog("scenarios", {name: s.description for name, s in SCENARIOS.items()})


def effects_epilog() -> str:
    items = {
        name: f"{spec.physics} (parameters: "
        + ", ".join(f"{key}={value:g}" for key, value in spec.defaults.items()) + ")"
        for name, spec in EFFECTS.items()
    }
    return _epilog("effects (--effects name[:param=value...],name...)", items)
