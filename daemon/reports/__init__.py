"""Reports for people: Table I text, figures (matplotlib) and markdown, written atomically.

Kept apart from the pure core so that ``daemon.model`` and ``daemon.calibration`` never import
matplotlib."""
