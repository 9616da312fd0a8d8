"""Native selection step of the screened beamformer (radarpc.dsp.accel.native.screen_select_native):
hand-worked rows, the torch selection on real screens, thread/stride invariance, bad input."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp.accel import DISABLE_ENV, native
from radarpc.dsp.accel.native import screen_select_native
from radarpc.dsp.accel.screened import _screen_select, screen_bound
from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.beamform import column_to_direction, dictionary_tables, stack_real
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_calibration import make_calibration


def _screen_rows(s_em: torch.Tensor) -> torch.Tensor:
    """bfloat16 screen rows ``[Re | Im]`` of elevation-major spectra ``(P, K)`` complex."""
    return torch.cat([s_em.real, s_em.imag], dim=1).to(torch.bfloat16)


def test_hand_worked_rows(built):
    # grid 3 azimuths x 2 elevations, N = 2 channels; B rows k = az * 2 + el
    rows = torch.tensor([[1, 0], [0, 1], [1, 1], [1, -1], [2, 0], [2, 0]], dtype=torch.complex64)
    v = torch.tensor([[1, 0],                 # |B v| = [1, 0, 1, 1, 2, 2]: tie between k = 4 and 5
                      [0, 3],                 # |B v| = [0, 3, 3, 3, 0, 0]: k = 1, 2, 3 tie -> 1
                      [0, 0]],                # flat (zero) spectrum: every azimuth a candidate
                     dtype=torch.complex64)
    exact = v @ rows.transpose(0, 1)                                   # (P, K), k = az n_el + el
    col = torch.arange(6)
    s_em = exact[:, column_to_direction(col, (3, 2))]                  # elevation-major columns
    y = _screen_rows(s_em)
    beta = torch.zeros(3)
    index, amplitude, heavy = screen_select_native(y, v, rows, beta, (3, 2), 0.0, 2)
    assert heavy.tolist() == [False, False, True]
    assert index.tolist() == [4, 1, -1]                                # ties go to the smaller k
    assert amplitude[:2].tolist() == [2.0, 3.0] and amplitude[2] == 0.0
    # row 1 has candidates in 2 azimuths: with max_candidates = 1 it is left to the caller
    _, _, heavy = screen_select_native(y, v, rows, beta, (3, 2), 0.0, 1)
    assert heavy.tolist() == [False, True, True]
    # the screen only proposes: the amplitude is the exact |B[k] v|, not the screen's value
    y_off = _screen_rows(s_em * 1.05)
    index, amplitude, _ = screen_select_native(y_off, v, rows, torch.full((3,), 0.01), (3, 2), 0.01, 3)
    assert index[:2].tolist() == [4, 1] and amplitude[:2].tolist() == [2.0, 3.0]


def _real_screen(n: int, seed: int):
    """Snapshots of a TINY sensor (noise, strong targets, zeros, NaN/inf), their bfloat16
    screen computed as beamform_peaks_screened does, and the bound."""
    calib = make_calibration(TINY)
    bt = calib.dictionary().transpose(0, 1).contiguous()
    tables = dictionary_tables(bt, calib.grid_shape)
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(n, bt.shape[0], dtype=torch.complex64, generator=g)
    k_true = torch.randint(0, bt.shape[1], (n,), generator=g)
    gain = (10.0 ** torch.linspace(-2, 5, n)).to(torch.complex64)
    v = torch.cat([noise, bt.transpose(0, 1)[k_true].conj() * gain[:, None] + noise])
    v[::11] = 0
    v[5, 3] = complex(float("nan"), 0.0)
    v[6, 0] = complex(float("inf"), 1.0)
    x16 = torch.view_as_real(v).reshape(v.shape[0], -1).to(torch.bfloat16)
    y16 = torch.mm(x16, tables.screen_bf16)
    alpha, beta = screen_bound(v, tables.row_norm_max)
    return v, tables, y16, alpha, beta


@pytest.mark.parametrize("max_candidates", [1, 6, 40])
@pytest.mark.parametrize("kernel", ["auto", "avx", "scalar"])
def test_matches_the_torch_selection(built, max_candidates, kernel):
    if kernel not in ("auto",) + native._screen.kernels():
        kernel = "auto"                                                       # no AVX here: auto is scalar
    v, t, y16, alpha, beta = _real_screen(300, seed=1)
    index, amplitude, heavy = screen_select_native(y16, v, t.rows, beta, t.grid, alpha, max_candidates,
                                                   kernel=kernel)
    ref_index = torch.empty(len(v), dtype=torch.long)
    ref_amp = torch.empty(len(v))
    ref_heavy = _screen_select(y16, v, t, beta, alpha, max_candidates, ref_index, ref_amp, Workspace())
    flags = torch.zeros(len(v), dtype=torch.bool)
    if ref_heavy is not None:
        flags[ref_heavy] = True
    assert torch.equal(heavy, flags)
    assert bool(heavy[5]) and bool(heavy[6]) and bool(heavy[::11].all())      # NaN, inf, zeros
    light = ~heavy
    if max_candidates >= 6:                                                   # most rows settled here
        assert int(light.sum()) > len(v) // 4                               # (noise rows are flat)
    assert torch.equal(index[light], ref_index[light])
    torch.testing.assert_close(amplitude[light], ref_amp[light], rtol=1e-6, atol=0)
    assert bool((index[heavy] == -1).all())
    # and the picked amplitude is the float64 |B[k] v| of the picked direction
    exact = np.abs(v[light].numpy().astype(np.complex128) @ t.rows.numpy().T.astype(np.complex128))
    picked = exact[np.arange(len(exact)), index[light].numpy()]
    np.testing.assert_allclose(amplitude[light].numpy(), picked, rtol=2e-6)
    np.testing.assert_allclose(picked, exact.max(1), rtol=1e-6)


def test_threads_items_and_row_stride_do_not_change_the_result(built, monkeypatch):
    v, t, y16, alpha, beta = _real_screen(100, seed=2)
    ref = screen_select_native(y16, v, t.rows, beta, t.grid, alpha, 6, threads=1)
    monkeypatch.setattr(native, "_SCREEN_ROWS", 3)
    wide = torch.zeros(y16.shape[0], y16.shape[1] + 7, dtype=torch.bfloat16)
    wide[:, :y16.shape[1]] = y16
    for threads in (1, 2, 5):
        for y in (y16, wide[:, :y16.shape[1]], wide):                   # padded rows: stride > 2K
            got = screen_select_native(y, v, t.rows, beta, t.grid, alpha, 6, threads=threads)
            assert all(torch.equal(a, b) for a, b in zip(got, ref)), threads
    # the two dot kernels: the same directions, amplitudes within float32 rounding of the sums
    got = screen_select_native(y16, v, t.rows, beta, t.grid, alpha, 6, kernel="scalar")
    assert torch.equal(got[0], ref[0]) and torch.equal(got[2], ref[2])
    torch.testing.assert_close(got[1], ref[1], rtol=1e-6, atol=0)
    # a snapshot length that is not a multiple of 8 complex values exercises the kernels' tails
    n = 13
    rows = torch.randn(t.n_dir, n, dtype=torch.complex64, generator=torch.Generator().manual_seed(0))
    w = torch.randn(len(v), n, dtype=torch.complex64, generator=torch.Generator().manual_seed(1))
    tables = dictionary_tables(rows.transpose(0, 1).contiguous(), t.grid)
    a, b = screen_bound(w, tables.row_norm_max)
    y = torch.mm(torch.view_as_real(w).reshape(len(w), -1).to(torch.bfloat16), tables.screen_bf16)
    exact = np.abs(w.numpy().astype(np.complex128) @ rows.numpy().T.astype(np.complex128))
    for kernel in native._screen.kernels():
        index, amplitude, heavy = screen_select_native(y, w, tables.rows, b, t.grid, a, 40, kernel=kernel)
        light = (~heavy).numpy()
        assert light.sum() > len(w) // 2
        np.testing.assert_allclose(amplitude.numpy()[light], exact[light].max(1), rtol=2e-6)
        np.testing.assert_allclose(exact[light, index.numpy()[light]], exact[light].max(1), rtol=1e-6)
    empty = screen_select_native(y16[:0], v[:0], t.rows, beta[:0], t.grid, alpha, 6)
    assert [e.shape for e in empty] == [(0,), (0,), (0,)]


def test_bad_input(built):
    v, t, y16, alpha, beta = _real_screen(8, seed=3)
    args = (y16, v, t.rows, beta, t.grid, alpha, 6)

    def call(i, value, **kw):
        a = list(args)
        a[i] = value
        return screen_select_native(*a, **kw)

    with pytest.raises(ValueError, match="screen must be bfloat16"):
        call(0, y16.float())
    with pytest.raises(ValueError, match="screen must be bfloat16"):
        call(0, y16[:, :-1])                                            # shorter than 2K
    with pytest.raises(ValueError, match="unit column stride"):
        call(0, y16.t().contiguous().t())
    with pytest.raises(ValueError, match="snapshots must be"):
        call(1, v.conj())
    with pytest.raises(ValueError, match="snapshots must be"):
        call(1, v[:-1])
    with pytest.raises(ValueError, match="rows must be"):
        call(2, t.rows[:-1].contiguous())
    with pytest.raises(ValueError, match="beta must be"):
        call(3, beta.double())
    with pytest.raises(ValueError, match="CPU"):
        call(3, beta.to("meta"))
    with pytest.raises(ValueError, match="alpha"):
        call(5, 1.0)
    with pytest.raises(ValueError, match="max_candidates"):
        call(6, 0)
    with pytest.raises(ValueError, match="threads"):
        call(6, 6, threads=0)
    with pytest.raises(ValueError, match="kernel must be one of"):
        call(6, 6, kernel="avx9")
    with pytest.raises(ValueError, match="n_az"):                        # the C entry point checks too
        native._screen.screen_select(0, 0, 0, 0, 0, 1, 0, 1, 1, 0.0, 1, 0, 0, 0)
    with pytest.raises(ValueError, match="non-null"):
        native._screen.screen_select(0, 2, 0, 0, 0, 1, 1, 1, 1, 0.0, 1, 0, 0, 0)
    with pytest.raises(ValueError, match="kernel 'sse9'"):
        native._screen.screen_select(0, 2, 0, 0, 0, 1, 1, 1, 1, 0.0, 1, 0, 0, 0, "sse9")
    assert native._screen.screen_select(0, 2, 0, 0, 0, 0, 1, 1, 1, 0.0, 1, 0, 0, 0, "scalar") == (0, "scalar")
    assert native._screen.kernels()[-1] == "scalar"


def test_disabled_raises(monkeypatch):
    for ext in ("_rxsum", "_screen"):
        if getattr(native, ext) is None:
            monkeypatch.setattr(native, ext, object())
    monkeypatch.setenv(DISABLE_ENV, "1")
    v, t, y16, alpha, beta = _real_screen(4, seed=4)
    with pytest.raises(RuntimeError, match="RADARPC_NO_NATIVE"):
        screen_select_native(y16, v, t.rows, beta, t.grid, alpha, 6)


def test_stack_real_screen_layout():
    """The screen rows this kernel reads are [Re | Im] of the elevation-major spectrum."""
    v, t, y16, _, _ = _real_screen(4, seed=5)
    v = v[7:12]
    y = torch.view_as_real(v).reshape(len(v), -1).double() @ stack_real(
        t.rows.transpose(0, 1)[:, column_to_direction(torch.arange(t.n_dir), t.grid)]).double()
    s = (v.to(torch.complex128) @ t.rows.transpose(0, 1).to(torch.complex128))
    s_em = s[:, column_to_direction(torch.arange(t.n_dir), t.grid)]
    torch.testing.assert_close(y, torch.cat([s_em.real, s_em.imag], dim=1))
