"""The daemon's side of Zenoh: the wire format (``protocol``: keys, parse into and encode from the pure core's
:class:`nanodrift.compensation.Command`),
the session and its declarations (``session``), and :class:`ZenohActuator` (``actuator``), which
publishes a procedure's steps on the command key."""
