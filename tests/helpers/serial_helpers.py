"""The pty instruments, now shipped in :mod:`drivers.testing.pty_devices`; re-exported for the tests."""

from drivers.testing.pty_devices import FakeGcsController, FakeInterferometer, PtyDevice

__all__ = ["FakeGcsController", "FakeInterferometer", "PtyDevice"]
