"""Procedures that drive a cell (calibration, validation): the same code on the simulated cell's
virtual clock and on hardware. Plans and step timing are pure data in ``nanodrift.calibration.plans``."""
