"""Receiver effects of the RD synthesis: IF filter, ADC floor, Tx leakage, phase-noise skirts."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from radarpc.sensors.radial import RADIAL, RADIAL_S, TINY, ideal_receiver, steering_vectors
from radarpc.sim.adc import butterworth_gain, rd_from_adc, synthesize_ddma_adc, synthesize_rd_exact
from radarpc.sim.rd import (
    Scatterers,
    adc_noise_power,
    beat_hz,
    leakage_coefficients,
    noise_power_rd,
    noise_profile_rd,
    receiver_gain,
    skirt_power_rd,
    synthesize_rd,
    window_psf,
    window_sums,
)

# TINY with every receiver effect on (its own is ideal): f_s = 1.6 MHz, 25 kHz per bin
TINY_RX = dataclasses.replace(TINY, if_highpass_hz=100e3, aa_order=6, adc_floor_db=-15.0,
                              leakage_db=30.0, pn_dbc_hz=-85.0)


def one(range_m, az, el, v, rcs=1.0):
    t = lambda x: torch.tensor([float(x)], dtype=torch.float64)  # noqa: E731
    return Scatterers(t(range_m), t(az), t(el), t(v), t(rcs))


def empty():
    z = torch.zeros(0, dtype=torch.float64)
    return Scatterers(z, z, z, z, z)


def test_if_filter_gain_is_the_butterworth_closed_form():
    cfg = RADIAL                    # 512 bins, f_s = 12.8 MHz: 25 kHz per bin
    assert beat_hz(cfg, 6.0) == pytest.approx(150e3)
    # HPF corner (bin 6): -3 dB; one octave below (bin 3, order 2): 1 / (1 + 2^4); AA corner
    # 0.8 f_s (bin 409.6): -3 dB; last bin: 1 / (1 + (511 / 409.6)^16); mid-range: both ~ 1
    hp = lambda b: (b / 6.0) ** 4 / (1 + (b / 6.0) ** 4)             # noqa: E731
    aa = lambda b: 1 / (1 + (b / 409.6) ** 16)                       # noqa: E731
    bins = np.array([3.0, 6.0, 100.0, 409.6, 511.0])
    want = np.sqrt(hp(bins) * aa(bins))
    np.testing.assert_allclose(receiver_gain(cfg, bins), want, rtol=1e-12)
    assert receiver_gain(cfg, 6.0) == pytest.approx(math.sqrt(0.5), rel=1e-6)
    assert receiver_gain(cfg, 409.6) == pytest.approx(math.sqrt(0.5), rel=1e-6)
    assert 20 * math.log10(receiver_gain(cfg, 3.0)) == pytest.approx(10 * math.log10(1 / 17), abs=1e-3)
    # the pole-product form the exact ADC model uses gives the same magnitudes
    f = beat_hz(cfg, np.linspace(0.5, 511, 40))
    poles = (butterworth_gain(f, 150e3, 2, highpass=True)
             * butterworth_gain(f, 0.8 * cfg.sample_rate_hz, 8, highpass=False))
    np.testing.assert_allclose(poles, receiver_gain(cfg, np.linspace(0.5, 511, 40)), rtol=1e-9)
    # torch and numpy agree
    np.testing.assert_allclose(receiver_gain(cfg, torch.tensor(bins, dtype=torch.float64)).numpy(), want, rtol=1e-12)


@pytest.mark.parametrize("r_bin", [2.0, 4.0, 30.3, 52.0, 60.7])
def test_scatterers_pass_the_filter_at_their_beat_frequency(r_bin):
    cfg = dataclasses.replace(TINY_RX, leakage_db=None)
    sc = one(cfg.range_of_bin(r_bin), 12.0, 0.0, 3.1, rcs=5.0)
    got = synthesize_rd(cfg, sc, noise=False)
    ideal = synthesize_rd(ideal_receiver(cfg), sc, noise=False)
    g = float(receiver_gain(cfg, r_bin))
    assert float((got - g * ideal).abs().max()) <= 1e-5 * float(ideal.abs().max())
    # HPF corner bin 4 (100 kHz), AA corner bin 51.2: attenuated outside, not at mid-range
    assert g > 0.99 if r_bin == 30.3 else g < 0.75


def test_noise_follows_the_filter_and_far_rows_go_dark():
    cfg = dataclasses.replace(RADIAL_S, leakage_db=None, pn_dbc_hz=None)
    rd = synthesize_rd(cfg, [empty()] * 4, generator=torch.Generator().manual_seed(0))
    p = (rd.abs() ** 2).double().mean(dim=(0, 2, 3)).numpy()          # (R,)
    prof = noise_profile_rd(cfg)
    # closed form: noise_power_rd * (|H|^2 + 10^(-1.5))
    floor = 10 ** (-15 / 10)
    np.testing.assert_allclose(prof, noise_power_rd(cfg) * (receiver_gain(cfg, np.arange(128)) ** 2 + floor))
    # each row: 4 frames x 64 Doppler x 16 Rx exponential cells (pairs correlated by the Doppler
    # window): relative std <= sqrt(2 / 4096); 6 sigma
    np.testing.assert_allclose(p / prof, 1.0, atol=6 * math.sqrt(2 / 4096))
    # the far rows are dark: the last bin at least 10 dB below mid-range, above the ADC floor
    assert prof[-1] < 0.1 * prof[64] and prof[-1] > floor * noise_power_rd(cfg)
    assert p[-4:].mean() < 0.1 * p[40:90].mean()


def test_tx_leakage_sits_at_range_zero_on_every_tx_ddma_offset():
    cfg = TINY_RX
    rd = synthesize_rd(cfg, empty(), noise=False)
    power = (rd.abs() ** 2).sum(-1)                                  # (R, D)
    r_pk, _ = np.unravel_index(int(power.argmax()), power.shape)
    assert r_pk == 0
    top = torch.topk(power[0], cfg.n_tx).indices.sort().values.numpy()
    np.testing.assert_array_equal(top, np.sort(cfg.doppler_offsets))
    # closed form of each on-bin cell: sqrt(10^(L/10) noise) |c_m,r| |W_r(-b_L)| / sum w_r
    b_l = cfg.leakage_range_m / cfg.range_res_m
    s_r, _ = window_sums(cfg.n_range)
    w = float(window_psf(torch.tensor([-b_l]), cfg.n_range).abs()[0]) / s_r
    want = math.sqrt(10 ** (cfg.leakage_db / 10) * noise_power_rd(cfg)) * np.abs(leakage_coefficients(cfg)) * w
    got = rd[0, torch.as_tensor(cfg.doppler_offsets), :].abs().double().numpy()   # (n_tx, n_rx)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # static (on-bin): outside the Hamming main lobes (+-1 bin) of the offsets only sidelobes (< -40 dB)
    lobes = (cfg.doppler_offsets[:, None] + np.array([-1, 0, 1])[None, :]) % cfg.n_doppler
    other = np.setdiff1d(np.arange(cfg.n_doppler), lobes)
    assert float(power[0, other].max()) < 1e-4 * float(power[0, cfg.doppler_offsets].min())
    assert synthesize_rd(ideal_receiver(cfg), empty(), noise=False).abs().max() == 0


def test_phase_noise_skirt_has_the_stated_power_and_range_correlation():
    cfg = dataclasses.replace(TINY_RX, leakage_db=None, pn_dbc_hz=-60.0)
    r_m, rcs = 20.0, 1e4
    sc = one(r_m, 0.0, 0.0, 0.0, rcs)
    clean = synthesize_rd(cfg, sc, noise=False)
    b = r_m / cfg.range_res_m                                         # bin 50
    rows = np.r_[25:45, 56:62]                                        # away from the main lobe
    acc = np.zeros(cfg.n_range)
    n_seed = 60
    for seed in range(n_seed):
        diff = synthesize_rd(cfg, sc, generator=torch.Generator().manual_seed(seed)) - clean
        acc += (diff.abs() ** 2).double().mean(dim=(1, 2)).numpy()
    got = acc[rows] / n_seed
    # expected: noise profile + skirt * A^2 sum w_r^2 sum w_d^2 * mean_rx sum_m |a_m,rx|^2
    _, q_r = window_sums(cfg.n_range)
    _, q_d = window_sums(cfg.n_doppler)
    a2 = cfg.snr_per_sample(r_m, rcs) * adc_noise_power(cfg)
    arr = (np.abs(steering_vectors(cfg, 0.0, 0.0)) ** 2).reshape(cfg.n_tx, cfg.n_rx).sum(0).mean()
    skirt = skirt_power_rd(cfg, r_m, rows) * a2 * q_r * q_d * arr
    want = noise_profile_rd(cfg)[rows] + skirt
    assert skirt.min() > 3 * noise_profile_rd(cfg)[rows].max()       # the skirt dominates there
    # 26 rows x 60 draws of a rank-one field (|eta|^2 exponential per row and draw): 5 sigma
    assert got.sum() / want.sum() == pytest.approx(1.0, abs=5 * math.sqrt(2 / (len(rows) * n_seed)))
    # range correlation: 4 sin^2(pi f tau); at the same offset a target at 2 m has ~1/100 the skirt
    near = skirt_power_rd(cfg, 2.0, 5.0 + 10.0) / skirt_power_rd(cfg, 20.0, 50.0 + 10.0)
    f = beat_hz(cfg, 10.0)
    ratio = math.sin(math.pi * f * 4.0 / 299_792_458.0) ** 2 / math.sin(math.pi * f * 40.0 / 299_792_458.0) ** 2
    gains = (receiver_gain(cfg, 15.0) / receiver_gain(cfg, 60.0)) ** 2
    assert near == pytest.approx(ratio * gains, rel=1e-9) and ratio < 0.02
    # no phase noise, no skirt; noise=False draws nothing
    plain = dataclasses.replace(cfg, pn_dbc_hz=None)
    d0 = synthesize_rd(plain, sc, generator=torch.Generator().manual_seed(0)) - synthesize_rd(plain, sc, noise=False)
    assert float((d0.abs() ** 2).double().mean(dim=(1, 2))[rows].sum()) < 2 * noise_profile_rd(cfg)[rows].sum()


def test_receiver_frames_are_bit_reproducible():
    cfg = TINY_RX
    sc = Scatterers(*(torch.tensor(x, dtype=torch.float32) for x in
                      ([3.0, 9.5, 20.0], [0.0, 30.0, -20.0], [0.0, 2.0, -1.0], [1.0, -4.0, 6.0], [1e4, 10.0, 3.0])))
    a = synthesize_rd(cfg, sc, generator=torch.Generator().manual_seed(3))
    b = synthesize_rd(cfg, sc, generator=torch.Generator().manual_seed(3))
    c = synthesize_rd(cfg, sc, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_exact_adc_model_agrees_with_the_fast_one_with_the_receiver_on():
    cfg = TINY_RX
    sc = Scatterers(
        range_m=torch.tensor([1.37, 10.05, 17.61, 5.2, 23.9], dtype=torch.float64),   # bins 3.4 .. 59.8
        azimuth_deg=torch.tensor([10.0, -25.0, 40.0, 0.0, -55.0], dtype=torch.float64),
        elevation_deg=torch.tensor([0.0, 5.0, -3.0, 2.0, 12.0], dtype=torch.float64),
        velocity_mps=torch.zeros(5, dtype=torch.float64),
        rcs_m2=torch.tensor([1.0, 10.0, 0.5, 3.0, 20.0], dtype=torch.float64),
    )
    fast = synthesize_rd(cfg, sc, noise=False).to(torch.complex128)
    exact = synthesize_rd_exact(cfg, sc, narrowband=True)
    # same function at rest in the narrowband model (the filter from its poles there, the closed
    # form here; the leakage tone through the DDMA codes there): complex64 rounding of the fast one
    assert float((fast - exact).abs().max()) <= 1e-5 * float(exact.abs().max())
    # the receiver changed the cube by far more than that
    plain = synthesize_rd_exact(ideal_receiver(cfg), sc, narrowband=True)
    assert float((plain - exact).abs().max()) > 0.1 * float(exact.abs().max())


def test_exact_adc_noise_has_the_mean_power_of_the_profile():
    cfg = TINY_RX
    g = torch.Generator().manual_seed(3)
    rd = torch.stack([rd_from_adc(cfg, synthesize_ddma_adc(cfg, empty(), noise=True, generator=g))
                      - synthesize_rd_exact(cfg, empty()) for _ in range(4)])
    # Parseval: the mean over range bins of the windowed periodogram of noise with spectrum |H_n|^2
    # is sigma^2 sum w^2 mean_n |H_n|^2 -- the mean of noise_profile_rd; 4 x 8192 cells, 6 sigma
    p = float((rd.abs() ** 2).mean())
    assert p / float(noise_profile_rd(cfg).mean()) == pytest.approx(1.0, abs=6 * math.sqrt(2 / rd.numel()))
