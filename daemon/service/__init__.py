"""The compensation daemon: poll the sensors, answer every target, publish commands and telemetry.

One unit per job: ``runner`` (lifecycle: signals, session, drivers, serve, cleanup), ``targets``
(the hot path), ``actuation`` (latest command wins; each ends with one ``done``), ``stop`` (a client's
``stop``), ``sensors`` (readings in, telemetry out),
``table`` (channel states), ``health_unit`` (is the model still right, per axis), ``polling`` (one task
per sensor group), ``status``, ``supervision`` (state changes, watchdog), ``reload`` (SIGHUP), ``state``
(what the target path and the loop share, behind one lock, and the one builder of the serving state).
A target becomes a command in the pure core, ``nanodrift.compensation``.
"""

from nanodrift.service.runner import Service, run_service

__all__ = ["Service", "run_service"]
