"""Where the residuals disagree: binned means and a one-way ANOVA per variable, deflated for lag-1
autocorrelation (an effective sample size n(1-ρ)/(1+ρ)), plus Durbin-Watson."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.discovery.settings import DEFAULT_SETTINGS, Settings
from nanodrift.model.effect_terms import CREEP_DEADBAND_UM, Rate
from nanodrift.model.model import json_float
from nanodrift.model.segments import features, first_rows, run_time_s
from nanodrift.model.terms import Direction


def lag1_autocorr(r: np.ndarray) -> float:
    r = np.asarray(r, dtype=np.float64) - float(np.mean(r))
    denom = float(r @ r)
    return float(r[1:] @ r[:-1]) / denom if denom > 0 and r.size > 2 else 0.0


def durbin_watson(r: np.ndarray) -> float:
    r = np.asarray(r, dtype=np.float64)
    denom = float(r @ r)
    return float(np.sum(np.diff(r) ** 2) / denom) if denom > 0 else 2.0


def ar1_deflation(r: np.ndarray) -> float:
    """(1-ρ)/(1+ρ) for positively autocorrelated residuals, else 1: effective rows per row."""
    rho = lag1_autocorr(r)
    return (1.0 - rho) / (1.0 + rho) if rho > 0 else 1.0


@dataclass
class Disagreement:
    variable: str
    description: str
    f_stat: float
    p_value: float  # AR(1)-deflated
    p_value_iid: float
    eta2: float  # share of the residual variance the bins explain
    spread_um: float  # largest minus smallest bin mean
    bins: list[dict[str, float]]
    significant: bool
    values: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "variable": self.variable, "description": self.description, "f_stat": json_float(self.f_stat),
            "p_value": json_float(self.p_value), "p_value_iid": json_float(self.p_value_iid),
            "eta2": json_float(self.eta2), "spread_um": json_float(self.spread_um),
            "significant": self.significant, "bins": self.bins,
        }


def structure_variables(data: Dataset, settings: Settings = DEFAULT_SETTINGS) -> dict[str, tuple[str, np.ndarray]]:
    """The variables residuals are checked against: name -> (description, value per row)."""
    t, x = np.asarray(data.t, dtype=np.float64), np.asarray(data.x, dtype=np.float64)
    out: dict[str, tuple[str, np.ndarray]] = {
        "t": ("time since the start of the run (s)", run_time_s(data)),
        "x": ("position x (µm)", x),
    }
    for axis, position in data.positions.items():  # a multi-axis cell: every axis' position
        if axis != "x":
            out[axis] = (f"position {axis} (µm)", np.asarray(position, dtype=np.float64))
    x = np.asarray(data.own_position, dtype=np.float64)  # the motion below is the modelled axis'
    own = "" if data.axis == "x" else f" of axis {data.axis}"
    out.update({c: (f"temperature {c} (°C)", np.asarray(v, dtype=np.float64)) for c, v in data.channels.items()})
    tau = settings.rate_probe_tau_s
    out.update({f"rate({c})": (f"rate of change of {c} (°C/h, smoothed over {tau:g} s)",
                               features(Rate(c, tau), data) * 3600.0) for c in data.channels})
    direction = Direction(axis=data.axis)
    out["dir"] = (f"direction of the last move{own} (+1 up, -1 down)", features(direction, data))
    first = first_rows(data)  # several runs: a run's first row follows no step
    step = np.diff(x, prepend=x[:1])
    step[first == np.arange(x.size)] = 0.0
    moved = np.abs(step) > CREEP_DEADBAND_UM
    idx = np.maximum(np.where(moved, np.arange(x.size), 0), first)
    np.maximum.accumulate(idx, out=idx)
    out["last_step"] = (f"size of the last step{own} (µm)", np.where(moved[idx], step[idx], 0.0))
    out["time_since_step"] = (f"time since the last step{own} (s)", t - t[idx])
    return out


def residual_structure(
    residual: np.ndarray, variables: Mapping[str, tuple[str, np.ndarray]], settings: Settings = DEFAULT_SETTINGS
) -> list[Disagreement]:
    """Binned residual means per variable and their significance, most structured first."""
    r = np.asarray(residual, dtype=np.float64)
    n = r.size
    deflate = ar1_deflation(r)
    found: list[Disagreement] = []
    for name, (desc, values) in variables.items():
        values = np.asarray(values, dtype=np.float64)
        uniq = np.unique(values)
        if uniq.size < 2:
            continue
        if uniq.size <= settings.bins:
            labels = np.searchsorted(uniq, values)
            edges = np.concatenate((uniq, uniq[-1:]))
            categorical = True
        else:
            edges = np.unique(np.quantile(values, np.linspace(0.0, 1.0, settings.bins + 1)))
            labels = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
            categorical = False
        k = int(labels.max()) + 1
        counts = np.bincount(labels, minlength=k).astype(np.float64)
        keep = counts > 0
        if keep.sum() < 2:
            continue
        sums = np.bincount(labels, weights=r, minlength=k)
        means = np.divide(sums, counts, out=np.zeros(k), where=keep)
        grand = float(r.mean())
        ss_between = float(np.sum(counts[keep] * (means[keep] - grand) ** 2))
        ss_total = float(np.sum((r - grand) ** 2))
        ss_within = max(ss_total - ss_between, 1e-300)
        groups = int(keep.sum())
        df1, df2 = groups - 1, n - groups
        if df2 <= 0:
            continue
        f_stat = (ss_between / df1) / (ss_within / df2)
        p_iid = float(special.fdtrc(df1, df2, f_stat))
        df2_eff = max(n * deflate - groups, 2.0)
        p = float(special.fdtrc(df1, df2_eff, f_stat * deflate))
        sq = np.bincount(labels, weights=r * r, minlength=k)
        var = np.divide(sq, counts, out=np.zeros(k), where=keep) - means**2
        bins = []
        for j in np.flatnonzero(keep):
            lo = float(edges[j])
            hi = lo if categorical else float(edges[j + 1])
            bins.append({
                "lo": lo, "hi": hi, "n": int(counts[j]), "mean_um": float(means[j]),
                "se_um": float(math.sqrt(max(var[j], 0.0) / counts[j] / deflate)) if counts[j] > 1 else 0.0,
            })
        eta2 = ss_between / ss_total if ss_total > 0 else 0.0
        spread = float(means[keep].max() - means[keep].min())
        found.append(Disagreement(
            variable=name, description=desc, f_stat=f_stat, p_value=p, p_value_iid=p_iid, eta2=eta2,
            spread_um=spread, bins=bins, significant=p * len(variables) < settings.p_max and eta2 >= 0.05,
            values=values,
        ))
    found.sort(key=lambda d: (not d.significant, -d.eta2))
    return found
