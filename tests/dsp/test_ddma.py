"""DDMA consolidation: envelope, Tx-0 hypothesis, replica bins and snapshots vs direct numpy."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp.ddma import (check_finite_envelope, check_rd, ddma_envelope, gap_window_sums, rd_envelope,
                              replica_bins, resolve_tx0_doppler, rx_magnitude_sum, virtual_snapshots)
from radarpc.sensors.radial import RADIAL_S, TINY
from radarpc.sim.rd import Scatterers, synthesize_rd


def _random_rd(cfg, b, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn((b, *cfg.rd_shape), dtype=torch.complex64, generator=g)


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S])
def test_all_slots_envelope_matches_numpy(cfg):
    rd = _random_rd(cfg, 2)
    e = rd_envelope(rd, cfg, envelope="all-slots")
    x = rd.numpy().astype(np.complex128)
    a = np.abs(x).sum(-1)                                            # (B, Nr, Nd)
    ref = np.zeros((2, cfg.n_range, cfg.slot_width))
    for s in range(cfg.n_slots):
        ref += a[:, :, s * cfg.slot_width:(s + 1) * cfg.slot_width]
    assert e.shape == (2, cfg.n_range, cfg.slot_width)
    np.testing.assert_allclose(e.numpy(), ref, rtol=1e-5)
    np.testing.assert_allclose(rx_magnitude_sum(rd).numpy(), a, rtol=1e-5)
    np.testing.assert_allclose(rd_envelope(rd[1], cfg, "all-slots")[0].numpy(), ref[1], rtol=1e-5)


def _tx0_reference(a_rl: np.ndarray, cfg, l: int) -> int:
    """RADIal rpl.py's rule written with a cumulative sum over the circularly extended slots."""
    x = np.array([a_rl[l + s * cfg.slot_width] for s in range(cfg.n_slots)])
    g = cfg.n_empty_slots
    ext = np.concatenate([x, x[:g]])
    c = np.cumsum(ext)
    mean_after = (c[g:] - c[:-g]) / g              # mean of x[s+1..s+g]
    return int(np.argmin(mean_after)) * cfg.slot_width + l


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S])
def test_replica_envelope_is_the_sum_over_the_replica_bins(cfg):
    # seed eq. 1: for every consolidated cell, sum_rx |R| summed over its n_tx replica bins (12 for
    # RADIAL_S), the bins of the Tx-0 hypothesis of RADIal's gap rule; the empty slots are left out
    rd = _random_rd(cfg, 2, seed=3)
    e = rd_envelope(rd, cfg)                                          # default: replicas
    a = np.abs(rd.numpy().astype(np.complex128)).sum(-1)              # (B, Nr, Nd)
    ref = np.zeros((2, cfg.n_range, cfg.slot_width))
    d0_ref = np.zeros(ref.shape, dtype=np.int64)
    for b in range(2):
        for r in range(cfg.n_range):
            for l in range(cfg.slot_width):
                d0 = _tx0_reference(a[b, r], cfg, l)
                bins = [(d0 + int(o)) % cfg.n_doppler for o in cfg.doppler_offsets]
                assert len(set(bins)) == cfg.n_tx
                ref[b, r, l] = a[b, r, bins].sum()
                d0_ref[b, r, l] = d0
    assert e.shape == ref.shape
    np.testing.assert_allclose(e.numpy(), ref, rtol=1e-5)
    # strictly less than the all-slot sum (the noise of the empty slots is not added)
    assert bool((e < rd_envelope(rd, cfg, envelope="all-slots")).all())
    env = ddma_envelope(rx_magnitude_sum(rd), cfg)                   # the same search gives d0
    np.testing.assert_array_equal((env.tx0_slot * cfg.slot_width + torch.arange(cfg.slot_width)).numpy(), d0_ref)
    with pytest.raises(ValueError, match="envelope must be one of"):
        rd_envelope(rd, cfg, envelope="sum")


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S])
def test_resolve_tx0_matches_reference_on_random_magnitudes(cfg):
    rng = np.random.default_rng(0)
    a = rng.exponential(size=(3, cfg.n_range, cfg.n_doppler))
    p = 50
    b = rng.integers(0, 3, p)
    r = rng.integers(0, cfg.n_range, p)
    l = rng.integers(0, cfg.slot_width, p)
    d0 = resolve_tx0_doppler(torch.from_numpy(a), cfg, torch.from_numpy(r), torch.from_numpy(l),
                             torch.from_numpy(b))
    ref = [_tx0_reference(a[bi, ri], cfg, li) for bi, ri, li in zip(b, r, l)]
    np.testing.assert_array_equal(d0.numpy(), ref)


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S])
def test_every_doppler_hypothesis_is_resolved(cfg):
    # one on-grid target per true Doppler bin: its replicas fill the Tx slots, the gap follows slot(d0)
    vres = cfg.velocity_res_mps
    half = cfg.n_doppler // 2
    d_true = np.arange(0, cfg.n_doppler, 1 if cfg is TINY else 5)
    frames = []
    for d in d_true:
        v = ((d + half) % cfg.n_doppler - half) * vres
        frames.append(Scatterers(torch.tensor([20 * cfg.range_res_m]), torch.tensor([10.0]), torch.tensor([0.0]),
                                 torch.tensor([float(v)]), torch.tensor([10.0])))
    rd = synthesize_rd(cfg, frames, noise=False)
    a = rx_magnitude_sum(rd)
    n = len(d_true)
    b = torch.arange(n)
    r = torch.full((n,), 20)
    l = torch.from_numpy(d_true % cfg.slot_width)
    d0 = resolve_tx0_doppler(a, cfg, r, l, b)
    np.testing.assert_array_equal(d0.numpy(), d_true)


def test_replica_bins_and_snapshots():
    cfg = RADIAL_S
    d0 = torch.tensor([0, 3, 63, 37])
    bins = replica_bins(cfg, d0)
    assert bins.shape == (4, cfg.n_tx)
    for j, d in enumerate(d0.tolist()):
        ref = [(d + s * cfg.slot_width) % cfg.n_doppler for s in cfg.tx_slots]
        assert bins[j].tolist() == ref
    rd = _random_rd(cfg, 2, seed=1)
    b = torch.tensor([0, 1, 1, 0])
    r = torch.tensor([5, 0, 127, 64])
    v = virtual_snapshots(rd, cfg, b, r, d0)
    assert v.shape == (4, cfg.n_virtual) and v.dtype == torch.complex64
    x = rd.numpy()
    for j in range(4):
        for tx in range(cfg.n_tx):
            for rx in range(cfg.n_rx):
                assert v[j, tx * cfg.n_rx + rx].item() == x[b[j], r[j], bins[j, tx], rx]


def test_bad_cubes():
    with pytest.raises(ValueError, match="complex"):
        check_rd(torch.ones(TINY.rd_shape), TINY)
    with pytest.raises(ValueError, match=r"\(B, 64, 32, 4\).*got \(64, 16, 4\)"):
        check_rd(torch.ones((64, 16, 4), dtype=torch.complex64), TINY)
    with pytest.raises(ValueError, match="complex torch.Tensor"):
        check_rd(np.ones(TINY.rd_shape, dtype=np.complex64), TINY)
    rd = _random_rd(TINY, 3)
    rd[2, 5, 5, 1] = complex(float("nan"), 0.0)
    with pytest.raises(ValueError, match=r"NaN.*\[2\]"):
        rd_envelope(rd, TINY)


U32 = 2.0 ** -24                                                      # float32 unit roundoff


def _gamma(n: int) -> float:
    """``gamma_n = n u / (1 - n u)``: a float32 sum of ``n + 1`` non-negative terms, in any order,
    is within ``gamma_n`` (relative) of the exact sum (Higham, Accuracy and Stability, sec. 4.2)."""
    return n * U32 / (1 - n * U32)


def _gap_reference(x: np.ndarray, n_gap: int) -> np.ndarray:
    """G_s over the last axis by the definition, in float64: ``x_{s+1} + ... + x_{s+n_gap}`` (mod n)."""
    n = x.shape[-1]
    x = x.astype(np.float64)
    return np.stack([sum(x[..., (s + k) % n] for k in range(1, n_gap + 1)) for s in range(n)], axis=-1)


@pytest.mark.parametrize("n,n_gap", [(4, 1), (4, 2), (4, 3), (16, 4), (16, 1), (16, 15), (7, 3)])
def test_gap_window_sums_against_the_definition(n, n_gap):
    g = torch.Generator().manual_seed(n * 31 + n_gap)
    x = torch.rand(3, 5, n, generator=g) * 1e3
    x[0] = x[0].round()                                               # ties
    ref = _gap_reference(x.numpy(), n_gap)
    got = gap_window_sums(x, n_gap, dim=-1)
    np.testing.assert_allclose(got.numpy(), ref, rtol=_gamma(n_gap - 1), atol=0)
    np.testing.assert_array_equal(got[0].numpy(), ref[0])              # integer sums < 2^24: exact
    # along a middle axis (the envelope's layout): the same values bit for bit, so that the
    # whole-map envelope and the per-peak search (both call this function) pick the same slot
    xt = x.transpose(-1, -2).contiguous()                             # (3, n, 5)
    assert torch.equal(gap_window_sums(xt, n_gap, dim=-2), got.transpose(-1, -2))


def test_gap_window_sums_bad_gap():
    x = torch.ones(2, 4)
    for bad in (0, 4, 5, 2.0):
        with pytest.raises(ValueError, match=r"n_gap must be an int in \[1, 4\)"):
            gap_window_sums(x, bad)


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S])
@pytest.mark.parametrize("kind", ["random", "ties", "zeros"])
def test_envelope_and_tx0_against_direct_search(cfg, kind):
    # E and every Tx-0 slot against the plain search in float64: G_s by definition, the first
    # minimum over the slots; float32 sums within gamma bounds, exact where the sums are exact
    g = torch.Generator().manual_seed(7)
    a = torch.rand(3, cfg.n_range, cfg.n_doppler, generator=g) * 4
    if kind == "ties":
        a = a.floor()                                                 # integers 0..3: many equal G_s
    elif kind == "zeros":
        a = a * (a > 3.5)                                             # noise-free cube: mostly G_s = 0
    ns, ng, w = cfg.n_slots, cfg.n_empty_slots, cfg.slot_width
    x = a.numpy().reshape(3, cfg.n_range, ns, w).swapaxes(-1, -2)     # (B, Nr, W, n_slots)
    gap = _gap_reference(x, ng)                                       # float64 G_s
    e_all = x.astype(np.float64).sum(-1)
    env = ddma_envelope(a, cfg)
    if kind == "ties":                                                # small integers: every sum exact
        slot = np.argmin(gap, axis=-1)                                # first on ties
        np.testing.assert_array_equal(env.all_slots.numpy(), e_all)
        np.testing.assert_array_equal(env.replicas.numpy(), e_all - gap.min(-1))
        np.testing.assert_array_equal(env.tx0_slot.numpy(), slot)
    else:
        np.testing.assert_allclose(env.all_slots.numpy(), e_all, rtol=_gamma(ns - 1), atol=0)
        # E = E_all - min_s G_s: both terms within their gamma bound of E_all (G_s <= E_all), one
        # rounding of the difference, none from the clamp at 0
        tol = (_gamma(ns - 1) + _gamma(ng - 1) + U32) * (1 + U32) * e_all
        assert (np.abs(env.replicas.numpy() - np.maximum(e_all - gap.min(-1), 0)) <= tol).all()
        # the slot is a minimum of the exact G_s up to the rounding of two float32 sums ...
        slot = env.tx0_slot.numpy()
        picked = np.take_along_axis(gap, slot[..., None], axis=-1)[..., 0]
        assert (picked - gap.min(-1) <= 2 * _gamma(ng - 1) * gap.max(-1)).all()
        # ... and the first one where G_s = 0 exactly (a sum of non-negative terms is 0 only if
        # every term is, in any order)
        zero = gap.min(-1) == 0
        np.testing.assert_array_equal(slot[zero], np.argmin(gap, axis=-1)[zero])
        if kind == "zeros":
            assert zero.mean() > 0.5
    d0_map = torch.from_numpy(slot) * w + torch.arange(w)
    # few cells (gathered per cell), many cells (whole map), then the cached whole map: the same slots
    for frac in (0.1, 0.8, 0.1):
        kept = torch.rand(3, cfg.n_range, w, generator=g) < frac
        b, r, l = torch.nonzero(kept, as_tuple=True)
        d0 = env.tx0_doppler(b, r, l)
        assert d0.dtype == torch.long and torch.equal(d0, d0_map[b, r, l])
        assert torch.equal(resolve_tx0_doppler(a, cfg, r, l, b), d0)
    fresh = ddma_envelope(a, cfg)
    assert torch.equal(fresh.tx0_doppler(b, r, l), d0_map[b, r, l])   # per-cell path on a fresh map


def test_replica_bins_any_integer_d0():
    cfg = RADIAL_S
    d0 = torch.tensor([-1, 0, 63, 64, 200, -70])
    ref = [[(d + int(o)) % cfg.n_doppler for o in cfg.doppler_offsets] for d in d0.tolist()]
    assert replica_bins(cfg, d0).tolist() == ref
    assert replica_bins(cfg, d0.int()).dtype == torch.long


def test_finite_envelope_check_names_frames():
    e = torch.ones(4, 8, 3)
    check_finite_envelope(e)
    e[1, 2, 0] = float("inf")
    e[3, 0, 2] = float("nan")
    with pytest.raises(ValueError, match=r"frame\(s\) \[1, 3\]"):
        check_finite_envelope(e)


def test_envelope_row_blocks_equal_one_block(monkeypatch):
    import radarpc.dsp.ddma as ddma_mod
    cfg = RADIAL_S
    a = rx_magnitude_sum(_random_rd(cfg, 3, seed=4))
    whole = ddma_envelope(a, cfg)
    row_bytes = cfg.n_doppler * a.element_size()
    monkeypatch.setattr(ddma_mod, "_ENVELOPE_BLOCK_BYTES", 37 * row_bytes)  # 37-row blocks, a short last one
    blocked = ddma_envelope(a, cfg)
    for name in ("all_slots", "replicas", "gap_sums", "tx0_slot"):
        assert torch.equal(getattr(blocked, name), getattr(whole, name)), name
    assert blocked.gap_sums.shape == (3, cfg.n_range, cfg.n_slots, cfg.slot_width)
