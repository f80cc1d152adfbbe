"""What every writer of an output device shares: the daemon's actuation and the procedures (calibrate,
validate) alike.

Two rules, one owner: where the stage is after the device opens (its read-back, believed only as
:func:`nanodrift.motion.trusted_start` allows), and the voltage the device will really receive for a command
(a DAC's count, a controller's digits), which must lie inside the limits in force or nothing is written.
Kept out of ``nanodrift.service`` so that a procedure driving a cell never reaches into the daemon.
"""

from __future__ import annotations

from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator
from nanodrift.motion import StartPoint, trusted_start

#: tolerance on a sent voltage against the limits: float rounding of a count times a scale, not a volt more
SENT_SLACK_V = 1e-9


async def locate_stage(actuator: Actuator, config: ActuatorConfig, sent_v: tuple[float, ...] = (), *,
                       sent_here: bool = True, prove: bool = False) -> StartPoint:
    """Where the stage is after ``actuator.open()`` (:func:`nanodrift.motion.trusted_start` on its read-back);
    a failed read back raises, like a failed write. ``prove`` (the daemon): a first start believes only the
    output's ``power_up_voltage_v``, and a claim nothing confirms is ``unproven``; the procedures (which keep
    no record) believe a read-back inside the limits."""
    read = await actuator.read_back()
    read_v = None
    if read is not None:
        field_name, value = read
        read_v = value if field_name == "voltage_v" else config.voltage(value)
    return trusted_start(config, read_v, sent_v, config.safe_voltage_v, tolerance_v=config.read_back_tolerance_v,
                         sent_here=sent_here, power_up_v=config.power_up_voltage_v if prove else None)


def bind_limits(actuator: Actuator, config: ActuatorConfig) -> None:
    """Tell the device the limits in force before it opens: the voltages, and the command range they mean
    (a controller sent positions keeps those inside it, as a DAC keeps its counts inside the voltages)."""
    actuator.limits_v = (config.v_min, config.v_max)
    ends_um = (config.q_um_for(config.v_min), config.q_um_for(config.v_max))
    actuator.limits_q_um = (min(ends_um), max(ends_um))


def checked_sent_voltage(actuator: Actuator, config: ActuatorConfig, voltage_v: float) -> float:
    """The voltage the device will receive for ``voltage_v``; ValueError (write nothing) when that is
    outside the limits in force."""
    sent = actuator.sent_voltage(voltage_v)
    if not config.v_min - SENT_SLACK_V <= sent <= config.v_max + SENT_SLACK_V:
        raise ValueError(f"{actuator.description}: {voltage_v:.6f} V would be sent as {sent:.6f} V, outside "
                         f"[{config.v_min:g}, {config.v_max:g}] V: nothing written")
    return sent
