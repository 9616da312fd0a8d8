"""The subspace beamformer and the certified decision: the exact argmax (float64 reference, exact
ties), identical to the exact beamformer, native and torch, on a real-size 751 x 11 table."""
from __future__ import annotations

import math
import numpy as np
import pytest
import torch

from radarpc.dsp.accel.screened import choose_beamformer, probe_snapshots, time_modes
from radarpc.dsp.accel.subspace import beamform_peaks_subspace, group_residuals, subspace_tables
from radarpc.dsp.beamform import beamform_peaks, certified_argmax, dictionary_tables
from radarpc.sensors.radial import RADIAL, Calibration, steering_vectors


def _measured_table(n_az: int, n_el: int, seed: int = 5) -> Calibration:
    """A measured-like table: steering vectors with per-channel errors and 1 % noise per entry."""
    rng = np.random.default_rng(seed)
    az, el = np.linspace(-75, 75, n_az), np.linspace(-15, 15, n_el)
    a = steering_vectors(RADIAL, az[:, None], el[None, :])
    n = a.shape[-1]
    a = a * 10 ** (rng.normal(0, 0.5, n) / 20) * np.exp(1j * rng.normal(0, 0.1, n))
    a = a * (1 + 0.01 * (rng.standard_normal(a.shape) + 1j * rng.standard_normal(a.shape)))
    return Calibration(signal=np.conj(np.moveaxis(a, 2, 1)).astype(np.complex64), window=np.hamming(n).astype(np.float32),
                       azimuth_deg=az, elevation_deg=el)


def _tables(n_az: int, n_el: int):
    calib = _measured_table(n_az, n_el)
    t = dictionary_tables(calib.dictionary().transpose(0, 1), calib.grid_shape)
    t.subspace = subspace_tables(t.rows, t.grid)
    return t


@pytest.fixture(scope="module")
def real_size():
    return _tables(751, 11)


@pytest.fixture(scope="module")
def small():
    return _tables(61, 11)


def _reference(v: torch.Tensor, t) -> torch.Tensor:
    """float64 argmax over k (exact ties in these inputs do not occur except where constructed)."""
    return (v.to(torch.complex128) @ t.rows.to(torch.complex128).T).abs().argmax(1)


def test_subspace_and_exact_give_the_float64_argmax_on_a_751x11_table(real_size, selection):
    t = real_size
    v = probe_snapshots(t, 48, seed=1)
    ex = beamform_peaks(v, t, t.grid)
    sub = beamform_peaks_subspace(v, t, t.grid)
    assert torch.equal(ex.index, _reference(v, t))
    assert torch.equal(sub.index, ex.index) and torch.equal(sub.amplitude, ex.amplitude)


@pytest.mark.parametrize("exponent", [-90, -60, 50, 100])
def test_extreme_magnitudes_give_the_exact_beamformers_answer(small, selection, exponent):
    # |v| far outside float32's comfortable range: the snapshots are rescaled by a power of two,
    # and the residual bound (||v||^2 - ||y_g||^2, in double) must still hold there
    t = small
    v = probe_snapshots(t, 48, seed=11)
    v = torch.view_as_complex(torch.ldexp(torch.view_as_real(v), torch.tensor(exponent)).contiguous())
    ex = beamform_peaks(v, t, t.grid)
    sub = beamform_peaks_subspace(v, t, t.grid)
    assert torch.equal(sub.index, ex.index) and torch.equal(sub.amplitude, ex.amplitude)
    assert torch.equal(ex.index, _reference(v, t))


def test_near_ties_and_exact_ties_are_decided_exactly(small, selection):
    t = small
    n_az, n_el = t.grid
    g = torch.Generator().manual_seed(0)
    v = torch.stack([t.rows[k].conj() for k in (100, 432, 300)])
    v = v + 1e-7 * torch.randn(v.shape, dtype=torch.complex64, generator=g) * v.abs().mean()
    k1 = (v.to(torch.complex128) @ t.rows.to(torch.complex128).T).abs().argmax(1).tolist()
    rows = t.rows.clone()
    for a, b in zip(k1, (k1[0] + 3 * n_el, k1[1] - 1, k1[2] - 5 * n_el)):   # b: a copy of a, nudged by 1 ulp
        rows[b] = rows[a]
        re = torch.view_as_real(rows)
        re[b, 3, 0] = torch.nextafter(re[b, 3, 0], torch.tensor(float("inf")))
    near = dictionary_tables(rows.T.contiguous(), t.grid)
    ref = (v.to(torch.complex128) @ rows.to(torch.complex128).T).abs()
    top2 = ref.topk(2, dim=1)
    assert bool(((top2.values[:, 0] - top2.values[:, 1]) / top2.values[:, 0] < 1e-6).all())   # float32 cannot order them
    ex = beamform_peaks(v, near, t.grid)
    sub = beamform_peaks_subspace(v, near, t.grid)
    assert torch.equal(ex.index, ref.argmax(1)) and torch.equal(sub.index, ex.index)
    assert torch.equal(sub.amplitude, ex.amplitude)
    # an exactly duplicated row: a true tie, settled like the exact GEMM's first column el n_az + az
    w = t.rows[200].conj()[None].clone()
    top = int((w.to(torch.complex128) @ t.rows.to(torch.complex128).T).abs().argmax())
    other = top + 2 * n_el if top + 2 * n_el < n_az * n_el else top - 2 * n_el
    dup = t.rows.clone()
    dup[other] = dup[top]
    tied = dictionary_tables(dup.T.contiguous(), t.grid)
    first = min(top, other, key=lambda k: (k % n_el) * n_az + k // n_el)
    for res in (beamform_peaks(w, tied, t.grid), beamform_peaks_subspace(w, tied, t.grid)):
        assert int(res.index) == first
    idx, _ = certified_argmax(w, dup, t.grid, torch.zeros(2, dtype=torch.long), torch.tensor([other, top]))
    assert int(idx) == first
    zero = torch.zeros(1, rows.shape[1], dtype=torch.complex64)   # all-zero snapshot: every direction ties
    assert int(beamform_peaks(zero, t, t.grid).index) == 0 == int(beamform_peaks_subspace(zero, t, t.grid).index)


def _bound_parts(t, v):
    """Float32 screen ``z^`` ``(P, K)`` complex128, the float64 spectrum ``s``, ``R`` ``(P, G)`` and ``||v||``."""
    st = t.subspace
    x = torch.view_as_real(v).reshape(len(v), -1)
    y = x @ st.w1
    z = torch.bmm(y.view(len(v), st.n_groups, -1).transpose(0, 1), st.w2)      # (G, P, 2M)
    m = z.shape[2] // 2
    zc = torch.complex(z[..., :m], z[..., m:]).transpose(0, 1).reshape(len(v), -1)[:, :t.n_dir]
    s = v.to(torch.complex128) @ t.rows.to(torch.complex128).T
    vn2 = torch.view_as_real(v).double().square().sum(dim=(1, 2))
    return zc.to(torch.complex128), s, group_residuals(y, vn2, st), vn2.sqrt()


def _projection_residual(t, v):
    """``||(I - P_g) v||`` ``(P, G)`` in float64, from an orthonormal basis of each group's stored ``Q_g``
    (an independent computation: QR of the basis rows, not the Gram bound of group_residuals)."""
    st = t.subspace
    n, two_r = t.rows.shape[1], 2 * st.rank
    w = st.w1.double().view(n, 2, st.n_groups, two_r)                 # stack_real: rows 2n and 2n + 1
    q = torch.complex(w[:, 0, :, :st.rank], -w[:, 1, :, :st.rank])    # (N, G, r): Q_g^T
    vd = v.to(torch.complex128)
    out = []
    for g in range(st.n_groups):
        basis, _ = torch.linalg.qr(q[:, g, :].conj())                  # orthonormal basis of span(Q_g^H)
        out.append(torch.linalg.vector_norm(vd - (vd @ basis.conj()) @ basis.T, dim=1))
    return torch.stack(out, dim=1)


def test_residual_and_subspace_bounds_hold(real_size):
    # R_g >= ||(I - P_g) v|| (against a QR projection), and |s_k - z^_k| <= resid_k R_g + slack_k ||v||
    # against float64, on random and frame-like snapshots
    t = real_size
    st = t.subspace
    g = torch.Generator().manual_seed(2)
    noise = torch.randn(32, t.rows.shape[1], dtype=torch.complex64, generator=g)
    v = torch.cat([noise, probe_snapshots(t, 32, seed=7)])
    zc, s, r, vn = _bound_parts(t, v)
    true_r = _projection_residual(t, v)
    assert bool((r >= true_r).all()) and bool((r <= vn[:, None] * (1 + 2.0 ** -30)).all())
    # and tight: it adds only the first GEMM's rounding (y_error) and the basis' departure from orthonormal
    extra = 4 * st.y_error + 4 * float((st.gram_max - 1).max())
    assert bool((r <= torch.sqrt(true_r ** 2 + extra * vn[:, None] ** 2) * (1 + 1e-9)).all())
    group = torch.arange(t.n_dir) // (st.group * t.grid[1])
    err = (s - zc).abs()
    bound = st.resid[:t.n_dir].double()[None] * r[:, group] + st.slack[:t.n_dir].double()[None] * vn[:, None]
    assert bool((err <= bound).all())
    assert float((err / bound).max()) > 1e-3                              # the bound is not vacuous
    # frame-like points lie mostly in one group's subspace: their bound there is a small part of ||v||
    best = s[32:].abs().argmax(1) // (st.group * t.grid[1])
    assert float((r[32:].gather(1, best[:, None]).squeeze(1) / vn[32:]).median()) < 0.5


def test_choice_is_the_fastest_measured_and_rejects_bad_timings():
    assert choose_beamformer({"exact": 2.0, "subspace": 1.0, "screened": 3.0}) == "subspace"
    assert choose_beamformer({"exact": 1.0, "subspace": 1.0}) == "exact"  # a tie: the earlier one
    assert choose_beamformer({"screened": 0.5, "exact": 1.0}) == "screened"
    with pytest.raises(ValueError, match="no timing"):
        choose_beamformer({"fast": 1.0})
    with pytest.raises(ValueError, match="finite number"):
        choose_beamformer({"exact": float("nan")})


def test_timing_survives_one_stall_and_cuts_off_slow_modes():
    # the probe behind "auto": a mode whose first timed call stalls once is still timed in full
    # and wins; a mode 10x slower than the best so far is cut off after the 16-snapshot calls
    v = torch.zeros(64, 4, dtype=torch.complex64)
    seconds = {"exact": [1.0], "subspace": [50.0, 0.2], "screened": [10.0]}   # per snapshot, call by call
    calls = {m: 0 for m in seconds}

    def clock(f, x):
        mode = f(x)
        per = seconds[mode]
        i = calls[mode]
        calls[mode] += 1
        return per[min(i, len(per) - 1)]

    run = {m: (lambda m: lambda x: m)(m) for m in seconds}
    out = time_modes(run, v, clock)
    assert out == {"exact": 1.0, "subspace": 0.2, "screened": 10.0}
    assert calls == {"exact": 4, "subspace": 4, "screened": 2}               # screened: cut off at 16
    assert choose_beamformer(out) == "subspace"


def test_bad_input_errors(small):
    t = small
    v = probe_snapshots(t, 4)
    with pytest.raises(ValueError, match="complex64"):
        beamform_peaks_subspace(v.to(torch.complex128), t.rows.T.to(torch.complex128), t.grid)
    with pytest.raises(ValueError, match="max_candidates"):
        beamform_peaks_subspace(v, t, t.grid, max_candidates=0)
    with pytest.raises(ValueError, match="rank must be an int"):
        subspace_tables(t.rows, t.grid, rank=0)
    with pytest.raises(ValueError, match="does not match"):
        subspace_tables(t.rows, (60, 11))


def _screen(t, v):
    """Float32 screen ``|z^_k|`` ``(P, K)``, group projections ``||y_g||`` ``(P, G)``, ``R`` ``(P, G)``
    and ``||v||``."""
    st = t.subspace
    zc, _, r, vn = _bound_parts(t, v)
    x = torch.view_as_real(v).reshape(len(v), -1)
    yn = torch.linalg.vector_norm((x @ st.w1).view(len(v), st.n_groups, -1).double(), dim=2)
    return zc.abs(), yn, r, vn


def test_group_bound_holds_and_prunes(real_size):
    # the native selection skips group g when cmax_g ||y_g|| + 2 (rmax_g R_g + smax_g ||v||) < L; that
    # needs |z^_k| <= cmax_g ||y_g|| + e_k for every k of g (Cauchy-Schwarz plus the product's rounding)
    t = real_size
    st = t.subspace
    g = torch.Generator().manual_seed(4)
    v = torch.cat([probe_snapshots(t, 64, seed=3), torch.randn(16, t.rows.shape[1], dtype=torch.complex64, generator=g)])
    a, yn, r, vn = _screen(t, v)
    group = torch.arange(t.n_dir) // (st.group * t.grid[1])
    e = st.resid[:t.n_dir].double()[None] * r[:, group] + st.slack[:t.n_dir].double()[None] * vn[:, None]
    assert bool((a <= st.cmax.double()[group][None] * yn[:, group] + e).all())
    # on frame-like points most groups cannot hold the maximum: the shortcut is not vacuous
    low = (a - e).amax(1, keepdim=True)
    ub = st.cmax.double()[None] * yn + 2 * (st.rmax.double()[None] * r + st.smax.double()[None] * vn[:, None])
    assert float((ub[:64] < low[:64]).double().mean()) > 0.5


@pytest.mark.parametrize("kernel", ["scalar", "avx"])
def test_flat_spectra_and_their_near_ties_are_decided_exactly(real_size, built, kernel):
    # noise-like snapshots leave tens to hundreds of candidates: the float32 pass must keep the winner,
    # also when the top two directions differ only by the rounding of the table
    if kernel not in built._screen.kernels():
        pytest.skip(f"the {kernel} kernel cannot run on this CPU")
    t = real_size
    st = t.subspace
    g = torch.Generator().manual_seed(6)
    v = torch.randn(24, t.rows.shape[1], dtype=torch.complex64, generator=g)
    rows = t.rows.clone()
    tops = (v.to(torch.complex128) @ rows.to(torch.complex128).T).abs().argmax(1).tolist()
    phase = torch.exp(2j * math.pi * torch.rand(len(tops), generator=g, dtype=torch.float64))
    for j, top in enumerate(tops):                  # each point's best direction gets a twin in another group:
        twin = (top + (300 + 2 * j) * t.grid[1]) % t.n_dir                  # the same row turned by a phase, so the
        rows[twin] = (rows[top].to(torch.complex128) * phase[j]).to(torch.complex64)   # two differ by rounding only
    near = dictionary_tables(rows.T.contiguous(), t.grid)
    near.subspace = subspace_tables(near.rows, near.grid)
    ns = near.subspace
    ref = (v.to(torch.complex128) @ rows.to(torch.complex128).T).abs()
    top2 = ref.topk(2, dim=1).values
    assert int(((top2[:, 0] - top2[:, 1]) / top2[:, 0] < 1e-6).sum()) >= 16   # (a twin may land on another top)
    a, _, r, vn = _screen(near, v)
    group = torch.arange(t.n_dir) // (ns.group * t.grid[1])
    e = ns.resid[:t.n_dir].double()[None] * r[:, group] + ns.slack[:t.n_dir].double()[None] * vn[:, None]
    assert int(((a + e) >= (a - e).amax(1, keepdim=True)).sum(1).min()) > 8     # the float32 pass runs past 8
    x = torch.view_as_real(v).reshape(len(v), -1)
    xn = (torch.linalg.vector_norm(v, dim=1) * (1 + 2.0 ** -14)).contiguous()
    idx, amp, amb, heavy = built.subspace_select_native(
        x @ ns.w1, ns, xn, v, near.rows, near.n_dir, row_norm_max=near.row_norm_max * (1 + 2.0 ** -20), kernel=kernel)
    assert not bool(heavy.any()) and int(amb.sum()) < len(v) // 2          # (ambiguous: exact rationals, below)
    assert torch.equal(idx[~amb], ref.argmax(1)[~amb])
    assert torch.equal(beamform_peaks_subspace(v, near, t.grid).index, ref.argmax(1))
    assert torch.equal(beamform_peaks(v, near, t.grid).index, ref.argmax(1))
