"""The simulated cell: the paper's PZT stage (or a stack of two or three), its drift and sensors, as a plugin.

See README.md in this directory for the physics, the scenarios and the hidden-effect catalogue.
"""
