"""Normalized AUC against hand-computed cases (flat, linear, uneven spacing, an interval between
points), the seed's Table 2 read both ways, and the checks of its input."""
import math

import numpy as np
import pytest

from radarpc.eval.curves import DensityCurve, normalized_auc, seed_statistics

SWEEP = [0.007, 0.016, 0.057, 0.088, 0.19, 0.308, 0.562]     # the seed's densities, unevenly spaced


def test_flat_curve_is_its_height():
    assert normalized_auc(SWEEP, [0.7] * len(SWEEP)) == pytest.approx(0.7, abs=1e-15)


def test_linear_curve_is_its_value_at_the_interval_midpoint():
    # the trapezoid rule is exact on a line: the mean of a + b d over [lo, hi] is a + b (lo + hi) / 2
    a, b = 0.6, 0.5
    f = [a + b * d for d in SWEEP]
    assert normalized_auc(SWEEP, f) == pytest.approx(a + b * (SWEEP[0] + SWEEP[-1]) / 2, rel=1e-13)
    assert normalized_auc(SWEEP, f, (0.01, 0.3)) == pytest.approx(a + b * (0.01 + 0.3) / 2, rel=1e-13)


def test_uneven_spacing_weighs_each_segment_by_its_width():
    # segments [1, 2] and [2, 5]: (0.2 + 0.6) / 2 * 1 + (0.6 + 0.8) / 2 * 3 = 0.4 + 2.1 = 2.5, over 4
    assert normalized_auc([1, 2, 5], [0.2, 0.6, 0.8]) == pytest.approx(0.625, abs=1e-15)
    assert np.mean([0.2, 0.6, 0.8]) != pytest.approx(0.625)          # not the plain mean of the points
    # the same in percent: the unit of density cancels
    assert normalized_auc([100, 200, 500], [0.2, 0.6, 0.8]) == pytest.approx(0.625, abs=1e-15)


def test_interval_ends_between_points_are_interpolated():
    # over (1.5, 4): F1(1.5) = 0.4, F1(4) = 0.6 + 0.2 * 2 / 3; (0.4 + 0.6) / 2 * 0.5 + (0.6 + F1(4)) / 2 * 2
    f4 = 0.6 + 0.2 * 2 / 3
    want = ((0.4 + 0.6) / 2 * 0.5 + (0.6 + f4) / 2 * 2) / 2.5
    assert normalized_auc([1, 2, 5], [0.2, 0.6, 0.8], (1.5, 4)) == pytest.approx(want, abs=1e-15)
    # an interval within one segment: the mean of the line there
    assert normalized_auc([1, 2, 5], [0.2, 0.6, 0.8], (2.5, 3.5)) == pytest.approx(0.6 + 0.2 * 1 / 3, abs=1e-15)


def test_the_seeds_table_2_is_integrated_over_density_not_its_logarithm():
    # Table 2: PointPillars and SpectralPillars F1 (%) at their densities (%). The seed reports
    # SpectralPillars +0.8 average F1 over PointPillars across the sweep.
    pp_d, pp_f = [0.7, 1.6, 5.7, 8.8, 19.0, 30.8, 56.2], [81.0, 86.0, 90.2, 90.2, 90.5, 91.5, 92.8]
    sp_d, sp_f = [0.7, 1.8, 5.6, 7.2, 17.2, 32.7, 56.4], [74.3, 86.0, 90.9, 91.6, 91.3, 92.9, 93.7]
    lo, hi = 0.7, 56.2

    def mean_over(x, y, transform):       # an independent integration: a fine grid of the polyline
        g = np.linspace(transform(lo), transform(hi), 2_000_001)
        return np.trapezoid(np.interp(g, transform(np.array(x)), y), g) / (transform(hi) - transform(lo))

    gain = normalized_auc(sp_d, sp_f, (lo, hi)) - normalized_auc(pp_d, pp_f, (lo, hi))
    assert gain == pytest.approx(mean_over(sp_d, sp_f, lambda v: v) - mean_over(pp_d, pp_f, lambda v: v), abs=1e-6)
    assert 0.5 < gain < 1.2                                           # the seed: +0.8
    log_gain = mean_over(sp_d, sp_f, np.log) - mean_over(pp_d, pp_f, np.log)
    assert log_gain < 0                                               # over log density the sign turns


@pytest.mark.parametrize("density, score, interval, match", [
    ([0.1], [0.5], None, "at least two points"),
    ([0.1, 0.2], [0.5], None, "same length"),
    ([0.1, 0.2], [0.5, math.nan], None, "finite"),
    ([0.1, math.inf], [0.5, 0.6], None, "finite"),
    ([0.2, 0.1], [0.5, 0.6], None, "strictly increasing"),
    ([0.1, 0.1, 0.2], [0.5, 0.6, 0.7], None, "strictly increasing"),
    ([[0.1, 0.2]], [[0.5, 0.6]], None, "one-dimensional"),
    (["a", "b"], [0.5, 0.6], None, "numbers"),
    ([0.1, 0.2], [0.5, 0.6], (0.05, 0.2), "outside the measured densities"),
    ([0.1, 0.2], [0.5, 0.6], (0.1, 0.3), "outside the measured densities"),
    ([0.1, 0.2], [0.5, 0.6], (0.2, 0.1), "d_lo < d_hi"),
    ([0.1, 0.2], [0.5, 0.6], (0.15, 0.15), "d_lo < d_hi"),
])
def test_bad_input_is_refused_with_the_reason(density, score, interval, match):
    with pytest.raises(ValueError, match=match):
        normalized_auc(density, score, interval)


def test_seed_statistics_use_the_sample_deviation():
    s = seed_statistics([0.80, 0.82])
    assert (s.n, s.low, s.high) == (2, 0.80, 0.82)
    assert s.mean == pytest.approx(0.81, abs=1e-15)
    assert s.std == pytest.approx(math.sqrt(2 * 0.01 ** 2 / 1), abs=1e-15)      # n - 1 = 1
    one = seed_statistics([0.5])
    assert one.mean == 0.5 and one.std is None                                   # one run: no spread
    with pytest.raises(ValueError, match="no runs"):
        seed_statistics([])
    with pytest.raises(ValueError, match="finite"):
        seed_statistics([0.5, math.nan])


def test_density_curve_pairs_densities_with_runs():
    c = DensityCurve("pp", (0.01, 0.05), ((0.5, 0.7), (0.8,)))
    assert [s.mean for s in c.statistics] == pytest.approx([0.6, 0.8])
    with pytest.raises(ValueError, match="2 densities but 1"):
        DensityCurve("pp", (0.01, 0.05), ((0.5,),))
    with pytest.raises(ValueError, match="without runs"):
        DensityCurve("pp", (0.01,), ((),))
