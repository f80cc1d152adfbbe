"""The GCS error codes a piezo controller driven by SVA/MOV/SVO reports, with their texts.

Codes and texts from the GCS error table as PIPython 2.13.0.2 ships it (``pipython/pidevice/gcserror.py``,
the ``PI_GCS_ERRORS`` texts); an excerpt: the controller-side codes a drift compensator's commands can
meet. A code outside it is still reported with its number, and the message says where to look it up.
"""

from __future__ import annotations

GCS_ERRORS: dict[int, str] = {
    0: "No error",
    1: "Parameter syntax error",
    2: "Unknown command",
    3: "Command length out of limits or command buffer overrun",
    5: "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
    7: "Position out of limits",
    8: "Velocity out of limits",
    10: "Controller was stopped by command",
    15: "Invalid axis identifier",
    17: "Parameter out of range",
    23: "Illegal axis or channel",
    24: "Incorrect number of parameters",
    54: "Unknown parameter",
    66: "Voltage out of limits",
    73: "Motion commands are not allowed when wave generator output is active; use WGO to disable generator output",
    79: "Open-loop commands are not allowed when servo is on",
    89: "Command not allowed in current motion mode",
    93: "This command is not allowed while the affected axis or its master is in motion.",
    95: "This parameter cannot be changed in current servo mode.",
    301: "Send buffer overflow",
    302: "Voltage out of limits",
    303: "Open-loop motion attempted when servo ON",
    304: "Received command is too long",
    506: "Servo loop was unstable due to wrong parameter setting and switched off to avoid damage.",
}

UNKNOWN_COMMAND = 2


def error_text(code: int) -> str:
    """``PI error N: <text>``, the form every message of the plugin uses."""
    text = GCS_ERRORS.get(code, "not in nanodrift's excerpt of the GCS error table (see the controller's manual)")
    return f"PI error {code}: {text}"
