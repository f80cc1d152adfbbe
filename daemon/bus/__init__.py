"""The daemon's side of Zenoh: the wire format (``protocol``: keys, parse, :class:`Command`, encode),
the session and its declarations (``session``), and :class:`ZenohActuator` (``actuator``), which
publishes a procedure's steps on the command key."""
