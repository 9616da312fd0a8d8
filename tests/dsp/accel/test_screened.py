"""The screened beamformer against the exact one at the edges of float32: extreme snapshot
magnitudes, power-of-two scaling, non-finite screens, and the screen bound's terms worked by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radarpc.dsp import accel
from radarpc.dsp.accel import native
from radarpc.dsp.accel.screened import _screen_select, beamform_peaks_screened, screen_bound
from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.beamform import beamform_peaks


def _float64_spectra(v: torch.Tensor, bt: torch.Tensor) -> np.ndarray:
    return np.abs(v.numpy().astype(np.complex128) @ bt.numpy().astype(np.complex128))   # (P, K)


def _beamformers(v, tables, grid):
    """(name, result) of the exact beamformer and of the screened one with each selection."""
    out = [("exact", beamform_peaks(v, tables, grid))]
    if native.native_available():
        out.append(("screened/native", beamform_peaks_screened(v, tables, grid)))
    with accel.disabled():
        out.append(("screened/torch", beamform_peaks_screened(v, tables, grid)))
    return out


@pytest.mark.parametrize("exponent", [-90, -75, 66, 70, 100])
def test_extreme_magnitudes_give_the_float64_maximum(radial_s, dictionary_snapshots, exponent):
    # |B v| ~ 2^(exponent + 8): beyond 2^64 the float32 power overflows, below ~2^-63 it goes
    # subnormal; the beamformers rescale such snapshots by a power of two first
    bt, tables, grid = radial_s
    v = torch.ldexp(torch.view_as_real(dictionary_snapshots(bt, 64, seed=1)), torch.tensor(exponent))
    v = torch.view_as_complex(v.contiguous())
    spectra = _float64_spectra(v, bt)
    best = spectra.max(1)
    assert np.isfinite(best).all() and best.min() > 0
    for name, res in _beamformers(v, tables, grid):
        picked = spectra[np.arange(len(v)), res.index.numpy()]
        np.testing.assert_allclose(picked, best, rtol=1e-6, err_msg=name)       # the maximum (to fp32 ties)
        np.testing.assert_allclose(res.amplitude.double().numpy(), best, rtol=2e-6, err_msg=name)


def test_power_of_two_scaling_is_exact(radial_s, dictionary_snapshots):
    # in range, scaling by 2^k scales every float32 value exactly: the same directions, the
    # amplitudes scaled bit for bit; out of range (2^80) the rescaled copy gives the same again
    bt, tables, grid = radial_s
    v = dictionary_snapshots(bt, 64, seed=2)
    ref = dict(_beamformers(v, tables, grid))
    for k in (-30, 25, 80, -100):
        w = torch.view_as_complex(torch.ldexp(torch.view_as_real(v), torch.tensor(k)).contiguous())
        for name, res in _beamformers(w, tables, grid):
            assert torch.equal(res.index, ref[name].index), (name, k)
            assert torch.equal(res.amplitude, torch.ldexp(ref[name].amplitude, torch.tensor(k))), (name, k)
    sec = beamform_peaks(v, tables, grid, (8, 1))
    w = torch.view_as_complex(torch.ldexp(torch.view_as_real(v), torch.tensor(90)).contiguous())
    big = beamform_peaks(w, tables, grid, (8, 1))
    assert torch.equal(big.sectors, torch.ldexp(sec.sectors, torch.tensor(90)))


def test_a_non_finite_screen_row_is_left_to_the_exact_path(radial_s, dictionary_snapshots):
    # a screen value that overflowed to inf, with a finite bound: both selections must give the
    # row up (its candidates would otherwise be only the overflowed directions)
    bt, tables, grid = radial_s
    v = dictionary_snapshots(bt, 4, seed=3)
    alpha, beta = screen_bound(v, tables.row_norm_max)
    y16 = torch.mm(torch.view_as_real(v).reshape(len(v), -1).to(torch.bfloat16), tables.screen_bf16)
    y16[1, 7] = float("inf")
    y16[2, tables.n_dir + 3] = float("nan")
    index = torch.empty(len(v), dtype=torch.long)
    amplitude = torch.empty(len(v))
    heavy = _screen_select(y16, v, tables, beta, alpha, 6, index, amplitude, Workspace())
    assert heavy is not None and {1, 2} <= set(heavy.tolist())         # rows 0, 3 may be flat too
    if native.native_available():
        _, _, flags = native.screen_select_native(y16, v, tables.rows, beta, grid, alpha, 6)
        assert flags[1] and flags[2] and set(torch.nonzero(flags).flatten().tolist()) == set(heavy.tolist())


def test_screen_bound_terms_by_hand():
    # v = (3 + 4i, 0): ||v|| = 5; n = 4 real entries; rows of norm at most 2
    v = torch.tensor([[3 + 4j, 0j]], dtype=torch.complex64)
    alpha, beta = screen_bound(v, 2.0)
    u = 2.0 ** -8
    assert alpha == u / (1 - u)
    gamma4 = 4 * 2.0 ** -24 / (1 - 4 * 2.0 ** -24)
    c = 2 * u + u * u + gamma4 * (1 + u) ** 2
    m = 6 * 2.0 ** -24
    expected = math.sqrt(2) * c * 5.0 * 2.0 * (1 + m / (1 - m)) * (1 + 2.0 ** -20) + 2.0 ** -124 * (4 + 2 * (2 + 5))
    assert float(beta[0]) == pytest.approx(expected, rel=1e-6)
    assert float(beta[0]) >= expected * (1 - 2.0 ** -23)                 # rounded up, not down
    # the norm is taken on a rescaled copy when it would underflow or overflow in float32
    for k in (-90, 90):
        w = torch.view_as_complex(torch.ldexp(torch.view_as_real(v), torch.tensor(k)).contiguous())
        _, b = screen_bound(w, 2.0)
        assert float(b[0]) == pytest.approx(math.ldexp(expected - 2.0 ** -124 * 18, k)
                                            + 2.0 ** -124 * (4 + 2 * (2 + math.ldexp(5.0, k))), rel=1e-6)
