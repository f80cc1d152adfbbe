"""Does the stage follow? The first moves of a procedure, checked against the position sensor.

A four-hour calibration of a stage that never moved (amplifier off, cable on the wrong channel, a
volts-per-micrometre ten times off, an output node that is not running) must stop within minutes.
The first ``steps`` commanded moves (of at least ``min_move_um``) are compared with what the
position sensor saw between the two steps' averaging windows: a move off by more than
``tolerance`` times the commanded one stops the procedure with a message an operator can act on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from nanodrift.calibration.plans import StepResult
from nanodrift.errors import UserError


class StageNotFollowingError(UserError):
    """The position sensor did not see the commanded move."""


@dataclass
class FollowCheck:
    channel: str  # the position sensor's name, for the message
    tolerance: float = 0.5  # fraction of the commanded move
    steps: int = 3  # moves checked; 0 = off
    min_move_um: float = 1.0  # smaller moves are not checked (noise, drift)
    checked: int = 0
    _previous: StepResult | None = None

    @property
    def done(self) -> bool:
        return self.checked >= self.steps

    def observe(self, result: StepResult, axis: str) -> None:
        """Compare ``result`` on ``axis`` with the previous step; :class:`StageNotFollowingError` when the stage
        stayed put."""
        previous, self._previous = self._previous, (result if result.valid else None)
        if self.done or previous is None or not result.valid:
            return
        commanded = result.q_um[axis] - previous.q_um[axis]
        if abs(commanded) < self.min_move_um:
            return
        moved = result.positions_um[axis] - previous.positions_um[axis]
        self.checked += 1
        if not math.isfinite(moved) or abs(moved - commanded) > self.tolerance * abs(commanded):
            raise StageNotFollowingError(
                f"the stage did not follow: commanded {commanded:+.4g} µm, the {self.channel} moved {moved:+.2f} µm; "
                "check the amplifier and [actuator]")
