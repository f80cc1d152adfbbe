"""Shared fixtures: a temp dir per test is pytest's ``tmp_path``; helpers live in their own modules."""

import sys
from pathlib import Path

# tests import their helper modules (synthetic.py, daemon_harness.py, ...) by name
sys.path.insert(0, str(Path(__file__).parent))
