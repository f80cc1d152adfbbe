"""The pty instruments, now shipped in :mod:`nanodrift.drivers.testing.pty_devices`; re-exported for the tests."""

from nanodrift.drivers.testing.pty_devices import FakeGcsController, FakeInterferometer, PtyDevice

__all__ = ["FakeGcsController", "FakeInterferometer", "PtyDevice"]
