"""Shared fixtures: a temp dir per test is pytest's ``tmp_path``; helpers live in their own modules."""

import sys
from pathlib import Path

# tests import their helpers as the package ``helpers`` (tests/helpers/)
sys.path.insert(0, str(Path(__file__).parent))
