"""The beamformers at the edges of float32: extreme snapshot magnitudes, non-finite screens,
the screen bound's terms worked by hand, the float32 matmul precision setting, and the native
thread pool's error path."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import torch

from radarpc.dsp import native
from radarpc.dsp.beamform import (_screen_select, beamform_peaks, beamform_peaks_screened, dictionary_tables,
                                  reduced_fp32_matmul, screen_bound)
from radarpc.dsp.workspace import Workspace
from radarpc.sensors.radial import RADIAL_S, make_calibration


@pytest.fixture(scope="module")
def radial_s():
    calib = make_calibration(RADIAL_S)
    bt = calib.dictionary().transpose(0, 1).contiguous()                  # (n_virtual, K)
    return bt, dictionary_tables(bt, calib.grid_shape), calib.grid_shape


def _targets(bt: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """``n`` snapshots: one or two steering vectors of the dictionary plus weak noise."""
    g = torch.Generator().manual_seed(seed)
    rows = bt.transpose(0, 1)
    k1, k2 = (torch.randint(0, rows.shape[0], (n,), generator=g) for _ in range(2))
    second = (torch.rand(n, generator=g) * 0.9).to(torch.complex64)
    noise = torch.randn(n, bt.shape[0], dtype=torch.complex64, generator=g) * 0.05
    return rows[k1].conj() + second[:, None] * rows[k2].conj() + noise


def _float64_spectra(v: torch.Tensor, bt: torch.Tensor) -> np.ndarray:
    return np.abs(v.numpy().astype(np.complex128) @ bt.numpy().astype(np.complex128))   # (P, K)


def _beamformers(v, tables, grid, monkeypatch):
    """(name, result) of the exact beamformer and of the screened one with each selection."""
    out = [("exact", beamform_peaks(v, tables, grid))]
    if native.native_available():
        out.append(("screened/native", beamform_peaks_screened(v, tables, grid)))
    with monkeypatch.context() as m:
        m.setenv(native.DISABLE_ENV, "1")
        out.append(("screened/torch", beamform_peaks_screened(v, tables, grid)))
    return out


@pytest.mark.parametrize("exponent", [-90, -75, 66, 70, 100])
def test_extreme_magnitudes_give_the_float64_maximum(radial_s, exponent, monkeypatch):
    # |B v| ~ 2^(exponent + 8): beyond 2^64 the float32 power overflows, below ~2^-63 it goes
    # subnormal; the beamformers rescale such snapshots by a power of two first
    bt, tables, grid = radial_s
    v = torch.ldexp(torch.view_as_real(_targets(bt, 200, seed=1)), torch.tensor(exponent))
    v = torch.view_as_complex(v.contiguous())
    spectra = _float64_spectra(v, bt)
    best = spectra.max(1)
    assert np.isfinite(best).all() and best.min() > 0
    for name, res in _beamformers(v, tables, grid, monkeypatch):
        picked = spectra[np.arange(len(v)), res.index.numpy()]
        np.testing.assert_allclose(picked, best, rtol=1e-6, err_msg=name)       # the maximum (to fp32 ties)
        np.testing.assert_allclose(res.amplitude.double().numpy(), best, rtol=2e-6, err_msg=name)


def test_power_of_two_scaling_is_exact(radial_s, monkeypatch):
    # in range, scaling by 2^k scales every float32 value exactly: the same directions, the
    # amplitudes scaled bit for bit; out of range (2^80) the rescaled copy gives the same again
    bt, tables, grid = radial_s
    v = _targets(bt, 300, seed=2)
    ref = dict(_beamformers(v, tables, grid, monkeypatch))
    for k in (-30, 25, 80, -100):
        w = torch.view_as_complex(torch.ldexp(torch.view_as_real(v), torch.tensor(k)).contiguous())
        for name, res in _beamformers(w, tables, grid, monkeypatch):
            assert torch.equal(res.index, ref[name].index), (name, k)
            assert torch.equal(res.amplitude, torch.ldexp(ref[name].amplitude, torch.tensor(k))), (name, k)
    sec = beamform_peaks(v, tables, grid, (8, 1))
    w = torch.view_as_complex(torch.ldexp(torch.view_as_real(v), torch.tensor(90)).contiguous())
    big = beamform_peaks(w, tables, grid, (8, 1))
    assert torch.equal(big.sectors, torch.ldexp(sec.sectors, torch.tensor(90)))


def test_a_non_finite_screen_row_is_left_to_the_exact_path(radial_s, monkeypatch):
    # a screen value that overflowed to inf, with a finite bound: both selections must give the
    # row up (its candidates would otherwise be only the overflowed directions)
    bt, tables, grid = radial_s
    v = _targets(bt, 4, seed=3)
    alpha, beta = screen_bound(v, tables.row_norm_max)
    y16 = torch.mm(torch.view_as_real(v).reshape(len(v), -1).to(torch.bfloat16), tables.screen_bf16)
    y16[1, 7] = float("inf")
    y16[2, tables.n_dir + 3] = float("nan")
    index = torch.empty(len(v), dtype=torch.long)
    amplitude = torch.empty(len(v))
    heavy = _screen_select(y16, v, tables, beta, alpha, 6, index, amplitude, Workspace())
    assert heavy is not None and heavy.tolist() == [1, 2]
    if native.native_available():
        _, _, flags = native.screen_select_native(y16, v, tables.rows, beta, grid, alpha, 6)
        assert flags.tolist() == [False, True, True, False]


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


def test_reduced_float32_matmul_precision_is_warned_not_changed(radial_s):
    bt, tables, grid = radial_s
    v = _targets(bt, 50, seed=4)
    assert not reduced_fp32_matmul("cpu")                              # torch's default: exact
    prev = torch.get_float32_matmul_precision()
    try:
        for precision in ("medium", "high"):
            torch.set_float32_matmul_precision(precision)
            assert reduced_fp32_matmul("cpu")
            with pytest.warns(RuntimeWarning, match="float32 matmul precision is reduced"):
                beamform_peaks(v, tables, grid)
            assert torch.get_float32_matmul_precision() == precision    # the setting is the user's
    finally:
        torch.set_float32_matmul_precision(prev)


def test_per_backend_precision_api_does_not_break_the_beamformer():
    # torch >= 2.9: after the per-backend fp32_precision settings, the legacy getter raises; run in a
    # fresh process, since that state cannot be undone reliably within one
    import subprocess
    import sys

    code = """
import warnings, torch
from radarpc.dsp.beamform import beamform_peaks, dictionary_tables, reduced_fp32_matmul
from radarpc.sensors.radial import TINY, make_calibration
if not hasattr(torch.backends.mkldnn.matmul, "fp32_precision"):
    print("no per-backend API"); raise SystemExit(0)
torch.backends.mkldnn.matmul.fp32_precision = "bf16"
calib = make_calibration(TINY)
bt = calib.dictionary().transpose(0, 1).contiguous()
v = torch.randn(8, bt.shape[0], dtype=torch.complex64)
assert reduced_fp32_matmul("cpu")
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    res = beamform_peaks(v, dictionary_tables(bt, calib.grid_shape), calib.grid_shape)
assert res.index.shape == (8,) and any("precision is reduced" in str(x.message) for x in w)
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() in ("ok", "no per-backend API")


def test_run_items_waits_for_every_item_before_raising():
    # the caller's buffers must outlive the work: an error in one item may not return early
    done, lock = [], threading.Lock()

    def item(start: int, count: int) -> None:
        if threading.current_thread() is not threading.main_thread() and not failed.is_set():
            failed.set()
            raise MemoryError("an item failed")                      # the first pool thread's item
        time.sleep(0.05)
        with lock:
            done.append(start)

    for threads in (2, 3, 4):
        done.clear()
        failed = threading.Event()
        with pytest.raises(MemoryError, match="an item failed"):
            native._run_items(item, 8, 1, threads=threads)
        assert len(done) == 7, threads                                 # every other item finished
