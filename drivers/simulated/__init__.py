"""The simulated cell: the paper's single-axis PZT stage, its thermal drift and sensors, as a driver plugin.

See README.md in this directory for the physics, the scenarios and the hidden-effect catalogue.
"""
