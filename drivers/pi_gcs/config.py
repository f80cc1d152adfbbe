"""The ``[actuator] kind = "pi_gcs"`` keys: how to reach the controller, which axis, which loop."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, FiniteFloat, model_validator

from nanodrift.drivers.base import ActuatorOptions, OutputClaim

#: PI's TCP port for GCS (PIPython ``pisocket.py``: ``port=50000``)
GCS_TCP_PORT = 50000
#: decimals of every number written (SVA volts, MOV micrometres): 1 uV, 1 pm; far finer than a piezo
#: amplifier's noise or a stage's drift, so formatting never moves the stage
DECIMALS = 6


class PiGcsActuatorConfig(ActuatorOptions):
    """A PI controller speaking GCS 2.0 as the stage's output.

    ``transport = "tcp"``: ``host`` and ``port`` (default 50000); ``"serial"``: ``port`` (a device path or
    anything pyserial's ``serial_for_url`` accepts) and ``baudrate`` (8N1, as PI's controllers ship).
    ``mode = "open_loop"``: every command is ``SVA <axis> <voltage_v>`` with the servo off;
    ``"closed_loop"``: ``MOV <axis> <q_um>`` with the servo on, ``q_um`` bounded by ``[q_min_um, q_max_um]``
    (default: the controller's travel range ``TMN?``/``TMX?``).
    """

    kind: Literal["pi_gcs"] = "pi_gcs"
    transport: Literal["tcp", "serial"] = "tcp"
    host: str = Field(default="", description="the controller's address (transport = tcp)")
    port: int | str | None = Field(default=None, description=f"tcp: the TCP port (default {GCS_TCP_PORT}); serial: "
                                                             "the device, e.g. /dev/ttyUSB0")
    baudrate: int = Field(default=115200, gt=0, description="serial only")
    axis: str = Field(default="1", pattern=r"^[A-Za-z0-9_]{1,16}$", description="the controller's axis identifier")
    piezo_channel: int | None = Field(default=None, ge=1, description="the piezo channel of VMI?/VMA?/VOL? "
                                      "(default: the axis identifier when it is a number)")
    mode: Literal["open_loop", "closed_loop"] = "open_loop"
    q_min_um: FiniteFloat | None = Field(default=None, description="closed loop: lowest MOV (default TMN?)")
    q_max_um: FiniteFloat | None = Field(default=None, description="closed loop: highest MOV (default TMX?)")
    timeout_s: float = Field(default=1.0, gt=0, le=60.0, description="each answer must come within this")

    @model_validator(mode="after")
    def _transport_keys(self) -> PiGcsActuatorConfig:
        if self.transport == "tcp":
            if not self.host:
                raise ValueError('host: transport = "tcp" needs the controller\'s address, e.g. host = "192.168.0.20"')
            if self.port is not None and not isinstance(self.port, int):
                raise ValueError(f"port: transport = \"tcp\" takes a TCP port number (default {GCS_TCP_PORT}), not "
                                 f"{self.port!r}")
            if isinstance(self.port, int) and not 0 < self.port < 65536:
                raise ValueError(f"port: {self.port} is not a TCP port (1..65535)")
        else:
            if not isinstance(self.port, str) or not self.port:
                raise ValueError('port: transport = "serial" needs the serial device, e.g. port = "/dev/ttyUSB0"')
            if self.host:
                raise ValueError('host: transport = "serial" has no host (it names the device with port)')
        if self.piezo_channel is None and not self.axis.isdigit():
            raise ValueError(f"piezo_channel: axis {self.axis!r} is not a number, so the piezo channel whose voltage "
                             "limits (VMI?/VMA?) bound it must be named, e.g. piezo_channel = 1")
        if self.mode == "open_loop" and (self.q_min_um is not None or self.q_max_um is not None):
            raise ValueError('q_min_um: only mode = "closed_loop" moves to positions; open loop is bounded by '
                             "[v_min, v_max]")
        if self.q_min_um is not None and self.q_max_um is not None and not self.q_min_um < self.q_max_um:
            raise ValueError(f"q_max_um: {self.q_max_um:g} is not above q_min_um = {self.q_min_um:g}")
        return self

    @property
    def tcp_port(self) -> int:
        return self.port if isinstance(self.port, int) else GCS_TCP_PORT

    @property
    def channel(self) -> int:
        """The piezo channel of the axis (VMI?/VMA?/VOL?)."""
        return self.piezo_channel if self.piezo_channel is not None else int(self.axis)

    @property
    def address(self) -> str:
        """Where the controller is, for messages and for sharing one connection between axes."""
        return f"{self.host}:{self.tcp_port}" if self.transport == "tcp" else str(self.port)

    def claims(self) -> list[OutputClaim]:
        """The controller's axis: two cell axes on it would each undo the other's commands."""
        return [OutputClaim(f"the PI controller at {self.address}", frozenset({f"axis {self.axis!r}"}))]
