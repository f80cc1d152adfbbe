"""Discovery: where a model and measured data disagree, which physical effect is missing, and its terms.

Pure computation (numpy/scipy, no I/O). The method, step by step and with its special rules, is in
``METHOD.md`` beside this file. The modules, in the order the workflow uses them: ``settings`` (the
bar), ``diagnostics`` (residual structure), ``workspace`` (the regression), ``candidates`` (judging
one), ``catalogue`` (the effects), ``workflow`` (the loop), ``confirmation`` (what a fresh run should
show, the τ range), ``summary`` (the finding in words); ``cell``: the loop per axis of a multi-axis cell.
"""

from nanodrift.calibration.discovery.candidates import Candidate
from nanodrift.calibration.discovery.cell import CellDiscoveryResult, discover_cell
from nanodrift.calibration.discovery.workflow import DiscoveryError, DiscoveryResult, discover

__all__ = ["Candidate", "CellDiscoveryResult", "DiscoveryError", "DiscoveryResult", "discover", "discover_cell"]
