"""systemd's notify protocol (sd_notify(3)) in a few lines: one datagram per state change.

``$NOTIFY_SOCKET`` names a unix datagram socket: a path, or an abstract socket written with a
leading ``@``. Without it (not started by systemd, or ``Type=simple``) every call is a no-op, so
the daemon needs no special mode for a terminal. ``$WATCHDOG_USEC`` (and ``$WATCHDOG_PID``) tell
how often systemd expects ``WATCHDOG=1``.
"""

from __future__ import annotations

import os
import socket


class Notifier:
    def __init__(self, address: str | None = None) -> None:
        address = os.environ.get("NOTIFY_SOCKET") if address is None else address
        self._address: str | None = None
        self._socket: socket.socket | None = None
        if address:
            self._address = "\0" + address[1:] if address.startswith("@") else address
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._socket is not None

    def notify(self, **fields: str | int) -> bool:
        """Send ``KEY=value`` lines (``notify(READY=1, STATUS="serving")``); False if not delivered."""
        if self._socket is None or self._address is None:
            return False
        message = "\n".join(f"{key}={value}" for key, value in fields.items()).encode("utf-8", "replace")
        try:
            self._socket.sendto(message, self._address)
        except OSError:
            return False  # systemd gone or socket full: never let notification break the service
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify(READY=1, STATUS=status) if status else self.notify(READY=1)

    def status(self, status: str) -> bool:
        return self.notify(STATUS=status.replace("\n", " "))

    def watchdog(self) -> bool:
        return self.notify(WATCHDOG=1)

    def stopping(self, status: str = "stopping") -> bool:
        return self.notify(STOPPING=1, STATUS=status)

    def reloading(self, monotonic_usec: int) -> bool:
        """``Type=notify-reload`` style: RELOADING=1 with the time, then READY=1 when done."""
        return self.notify(RELOADING=1, MONOTONIC_USEC=monotonic_usec)

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None


def watchdog_interval_s() -> float | None:
    """Half the watchdog period systemd asked for (the recommended ping rate), or None."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 2e6 if value > 0 else None
