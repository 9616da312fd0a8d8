"""Curves of a score against data density: the seeds' mean and spread, and the normalized area
under the curve (seed Sec. 4) that summarises a curve over a density sweep in one number.

Normalized AUC. The seed summarises an F1-density curve "over a fixed interval using trapezoidal
integration", divided by the interval's length, "which yields the mean F1 over the sweep". Over
the interval ``[d_lo, d_hi]`` of density ``d`` (a fraction of RD cells; the same number in percent
gives the same value),

    AUC_norm = 1 / (d_hi - d_lo) * integral_{d_lo}^{d_hi} F1(d) dd

             ~ 1 / (d_K - d_1) * sum_{k=1}^{K-1} (d_{k+1} - d_k) * (F1_k + F1_{k+1}) / 2

for measured points ``d_1 < ... < d_K`` spanning the interval (the curve taken as linear between
them; an interval end between two points is interpolated linearly). The integral runs over the
density itself, not its logarithm, although the seed's figures draw density on a log axis: the
seed's Table 2 gives PointPillars and SpectralPillars F1 at 7 densities each (0.7 % to 56 %), and
their difference of normalized AUCs over that interval is +0.95 F1 points over the density and
-0.16 over its logarithm, against the "+0.8 average F1" the seed reports for that comparison (from
its unrounded curves). Being a mean over density, the value weighs the dense end of a sweep most
(56 % - 31 % is 45 % of a 0.7-56 % interval).

Differences of normalized AUCs between two curves over the same interval are average F1 gains
across the sweep, as the seed reads them.
"""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["normalized_auc", "SeedStatistics", "seed_statistics", "DensityCurve"]


def _vector(values: Sequence[float], name: str) -> np.ndarray:
    try:
        v = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}") from None
    if v.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must hold finite numbers, got {v.tolist()}")
    return v


def normalized_auc(density: Sequence[float], score: Sequence[float],
                   interval: tuple[float, float] | None = None) -> float:
    """The mean of ``score`` over the density interval: the trapezoid area under the curve divided
    by the interval's length (see the module docstring for the equation and why density is not
    taken on a log scale).

    Parameters
    ----------
    density : sequence of float
        Densities of the measured points, strictly increasing, at least two.
    score : sequence of float
        The score (e.g. F1) at each density.
    interval : (float, float), optional
        ``(d_lo, d_hi)`` with ``d_lo < d_hi`` inside ``[density[0], density[-1]]``; the curve is
        interpolated linearly at ends between two points. Default: the measured range.

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Fewer than two points, lengths that differ, non-finite values, densities not strictly
        increasing, or an interval that is empty or reaches outside the measured densities.

    Examples
    --------
    >>> normalized_auc([0.01, 0.03], [0.5, 0.7])            # a straight line: its mean height
    0.6
    >>> normalized_auc([1, 2, 4], [0.0, 1.0, 1.0])           # (0.5 * 1 + 1.0 * 2) / 3
    0.8333333333333334
    """
    d = _vector(density, "density")
    f = _vector(score, "score")
    if len(d) != len(f):
        raise ValueError(f"density and score must have the same length, got {len(d)} and {len(f)}")
    if len(d) < 2:
        raise ValueError(f"a curve needs at least two points to have an area, got {len(d)}")
    if np.any(np.diff(d) <= 0):
        raise ValueError(f"density must be strictly increasing (one score per density), got {d.tolist()}")
    lo, hi = (float(d[0]), float(d[-1])) if interval is None else (float(interval[0]), float(interval[1]))
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"interval must be (d_lo, d_hi) with d_lo < d_hi, got {interval}")
    if lo < d[0] or hi > d[-1]:
        raise ValueError(f"interval ({lo:g}, {hi:g}) reaches outside the measured densities "
                         f"[{d[0]:g}, {d[-1]:g}]: the curve is not known there")
    inside = (d > lo) & (d < hi)
    x = np.concatenate(([lo], d[inside], [hi]))
    y = np.concatenate(([np.interp(lo, d, f)], f[inside], [np.interp(hi, d, f)]))
    area = float(np.sum(np.diff(x) * (y[1:] + y[:-1]) / 2))
    return area / (hi - lo)


@dataclass(frozen=True)
class SeedStatistics:
    """A score over the runs of one configuration (seeds): ``n`` runs, their mean, and the sample
    standard deviation (``n - 1`` in the denominator; None for a single run, which has no spread)."""

    n: int
    mean: float
    std: float | None
    low: float
    high: float


def seed_statistics(values: Sequence[float]) -> SeedStatistics:
    """Mean, sample standard deviation, lowest and highest of the runs' ``values``.

    Raises
    ------
    ValueError
        No value, or a value that is not a finite number.
    """
    v = _vector(values, "values")
    if len(v) == 0:
        raise ValueError("no runs to summarise")
    vals = [float(x) for x in v]
    return SeedStatistics(len(vals), statistics.fmean(vals), statistics.stdev(vals) if len(vals) > 1 else None,
                          min(vals), max(vals))


@dataclass(frozen=True)
class DensityCurve:
    """One configuration's score against density, as a figure draws it.

    Attributes
    ----------
    label : str
        Legend entry.
    density : tuple of float
        Densities (fractions of RD cells), increasing.
    runs : tuple of tuple of float
        The score of each run (seed) at each density.
    auc : float or None
        The normalized AUC of the mean curve (:func:`normalized_auc`), None when not computed.
    """

    label: str
    density: tuple[float, ...]
    runs: tuple[tuple[float, ...], ...]
    auc: float | None = None

    def __post_init__(self) -> None:
        if len(self.density) != len(self.runs):
            raise ValueError(f"curve {self.label!r}: {len(self.density)} densities but {len(self.runs)} sets of runs")
        if any(len(r) == 0 for r in self.runs):
            raise ValueError(f"curve {self.label!r}: a density without runs")

    @property
    def statistics(self) -> list[SeedStatistics]:
        """:func:`seed_statistics` at each density."""
        return [seed_statistics(r) for r in self.runs]
