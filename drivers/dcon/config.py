"""The ``[[hubs]]`` and ``[[sensors]]`` keys of DCON thermocouple modules (ADAM-4018/4118, ICP DAS I-7018)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from nanodrift.drivers.base import SensorConfig, StrictModel


class DconHubConfig(StrictModel):
    """A ``[[hubs]]`` entry: one RS-485 bus (a serial port) or one TCP gateway to it, shared by every module on it.

    The serial defaults are the modules' factory settings (ADAM 4000 manual: 9600 bps, 8 data bits, no
    parity, 1 stop bit); ``timeout_s`` bounds the wait for one answer (a module at a wrong address
    answers nothing).
    """

    name: str
    type: Literal["serial", "tcp"] = "serial"
    port: int | str = Field(description="serial device (type = 'serial', e.g. /dev/ttyUSB0) or TCP port (type = 'tcp')")
    host: str = Field(default="127.0.0.1", description="the gateway's address (type = 'tcp')")
    baudrate: int = Field(default=9600, gt=0)
    bytesize: Literal[7, 8] = 8
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    timeout_s: float = Field(default=0.5, gt=0, le=60, description="an answer must come within this")

    @model_validator(mode="after")
    def _port_fits_type(self) -> DconHubConfig:
        if self.type == "serial" and not isinstance(self.port, str):
            raise ValueError(f"port: type = 'serial' needs the serial device (e.g. '/dev/ttyUSB0'), got {self.port!r}")
        if self.type == "tcp" and not (isinstance(self.port, int) and 0 < self.port < 65536):
            raise ValueError(f"port: type = 'tcp' needs the gateway's TCP port (1-65535), got {self.port!r}")
        return self

    @property
    def url(self) -> str:
        """What pyserial's ``serial_for_url`` opens."""
        return f"socket://{self.host}:{self.port}" if self.type == "tcp" else str(self.port)

    @property
    def endpoint(self) -> str:
        return f"{self.host}:{self.port}" if self.type == "tcp" else str(self.port)


class DconSensorConfig(SensorConfig):
    """One thermocouple channel of a DCON module: which hub, which module (``address``), which ``channel``.

    Every channel of one module is read by one ``#AA`` exchange, so its sensors form one group; they must
    agree on the module's settings (``checksum``, ``open_detection``), checked across entries.
    """

    kind: Literal["dcon"] = "dcon"
    role: Literal["temperature"] = "temperature"
    hub: str = Field(description="name of a [[hubs]] entry (type = 'serial' or 'tcp')")
    address: int = Field(ge=0, le=255, description="the module's address, sent as two hex digits (1 -> '01')")
    channel: int = Field(ge=0, le=7, description="the module's input channel")
    checksum: bool = Field(default=False, description="the module is configured to check and send checksums")
    open_detection: bool = Field(default=False, description="ask $AAB each poll (ADAM-4015/4018+/4019+): a "
                                                            "channel the module diagnoses open or out of range "
                                                            "is a fault")
    unit: str = Field(default="degC", description="unit of the module's values (engineering units)")

    def hub_name(self) -> str:
        return self.hub

    @property
    def module(self) -> tuple[str, int]:
        return self.hub, self.address
