"""Reports for people: Table I text, figures (matplotlib) and markdown, written atomically.

Kept apart from the pure core so that ``nanodrift.model`` and ``nanodrift.calibration`` never import
matplotlib."""
