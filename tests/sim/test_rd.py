"""Frequency-domain RD synthesis against hand-worked values and the exact ADC-domain route."""
import math

import numpy as np
import pytest
import torch

from radarpc.sensors.radial import RADIAL_S, TINY, make_calibration, steering_vectors
from radarpc.sim.adc import rd_from_adc, synthesize_adc, synthesize_rd_exact
from radarpc.sim.rd import (
    Scatterers,
    noise_power_rd,
    peak_snr_rd,
    psf_columns,
    steering_torch,
    synthesize_rd,
    window,
    window_psf,
)


def one(range_m, az, el, v, rcs=1.0):
    t = lambda x: torch.tensor([float(x)], dtype=torch.float64)  # noqa: E731
    return Scatterers(t(range_m), t(az), t(el), t(v), t(rcs))


def empty():
    z = torch.zeros(0, dtype=torch.float64)
    return Scatterers(z, z, z, z, z)


@pytest.mark.parametrize("cfg, r_bin, d_bin, az, el", [
    (TINY, 23, 5, 14.0, 10.0),
    (TINY, 40, 29, -30.0, -10.0),
    (RADIAL_S, 50, 7, 20.0, 5.0),
    (RADIAL_S, 90, 60, -37.0, -10.0),
])
def test_point_target_bins_replicas_and_angle(cfg, r_bin, d_bin, az, el):
    v = float(cfg.velocity_of_bin(d_bin))
    rd = synthesize_rd(cfg, one(cfg.range_of_bin(r_bin), az, el, v, rcs=10.0), noise=False)
    assert rd.shape == cfg.rd_shape and rd.dtype == torch.complex64
    power = (rd.abs() ** 2).sum(-1)                                  # (R, D)
    r_pk, d_pk = np.unravel_index(int(power.argmax()), power.shape)
    assert r_pk == r_bin
    # the n_tx replicas: Tx m at (d0 + o_m) mod N_d, all of the same power (|a_v| ~ 1)
    replicas = (d_bin + cfg.doppler_offsets) % cfg.n_doppler
    assert d_pk in replicas
    top = torch.topk(power[r_bin], cfg.n_tx).indices.sort().values.numpy()
    np.testing.assert_array_equal(top, np.sort(replicas))
    # outside the replicas' main lobes (+-1 bin for Hamming) only sidelobes remain (< -40 dB)
    occupied = np.zeros(cfg.n_doppler, bool)
    for s in (-1, 0, 1):
        occupied[(replicas + s) % cfg.n_doppler] = True
    assert float(power[r_bin, ~occupied].max()) < 1e-4 * float(power[r_bin, replicas].min())
    # virtual snapshot in Tx order -> beamformed peak at the target's (az, el) grid cell
    snap = rd[r_bin, torch.as_tensor(replicas), :].reshape(-1)       # (n_tx * n_rx,)
    calib = make_calibration(cfg)
    spec = (calib.dictionary() @ snap).abs()
    k = int(spec.argmax())
    n_el = calib.grid_shape[1]
    assert calib.azimuth_deg[k // n_el] == pytest.approx(az)
    assert calib.elevation_deg[k % n_el] == pytest.approx(el)


def test_peak_amplitude_is_the_radar_equation_times_fft_gain():
    cfg = RADIAL_S
    r_bin, rcs = 40, 2.0
    rd = synthesize_rd(cfg, one(cfg.range_of_bin(r_bin), 0.0, 0.0, 0.0, rcs), noise=False)
    # Tx 0 / Rx 0 is the hardware reference channel (gain exactly 1)
    snr_cell = float(rd[r_bin, 0, 0].abs() ** 2) / noise_power_rd(cfg)
    # periodic Hamming: sum w = 0.54 N, sum w^2 = N (0.54^2 + 0.46^2 / 2) -> loss 0.2916 / 0.3974
    loss = 0.54 ** 2 / (0.54 ** 2 + 0.46 ** 2 / 2)
    want = float(cfg.snr_per_sample(cfg.range_of_bin(r_bin), rcs)) * cfg.n_range * cfg.n_doppler * loss ** 2
    assert snr_cell == pytest.approx(want, rel=1e-4)
    assert float(peak_snr_rd(cfg, cfg.range_of_bin(r_bin), rcs)) == pytest.approx(want, rel=1e-9)


def test_frequency_domain_matches_exact_adc_synthesis_on_tiny():
    cfg = TINY
    # several targets at fractional range and Doppler bins, one beyond v_max (wraps)
    sc = Scatterers(
        range_m=torch.tensor([3.37, 10.05, 17.61, 5.2, 22.9], dtype=torch.float64),
        azimuth_deg=torch.tensor([10.0, -25.0, 40.0, 0.0, -55.0], dtype=torch.float64),
        elevation_deg=torch.tensor([0.0, 5.0, -3.0, 2.0, 12.0], dtype=torch.float64),
        velocity_mps=torch.tensor([2.3, -7.7, 15.0, 0.4, 27.1], dtype=torch.float64),
        rcs_m2=torch.tensor([1.0, 10.0, 0.5, 3.0, 20.0], dtype=torch.float64),
    )
    fast = synthesize_rd(cfg, sc, noise=False)
    exact = synthesize_rd_exact(cfg, sc)
    # stated tolerance: max abs difference <= 1e-5 of the cube's peak magnitude (complex64 result)
    err = float((fast.to(torch.complex128) - exact).abs().max())
    assert err <= 1e-5 * float(exact.abs().max())
    # ... and not trivially: the sidelobe region is far from zero
    assert float(exact.abs().min()) > 0


def test_adc_noise_becomes_noise_power_rd():
    cfg = TINY
    g = torch.Generator().manual_seed(3)
    rd = rd_from_adc(cfg, synthesize_adc(cfg, empty(), noise=True, generator=g))
    n = rd.numel()
    p = float((rd.abs() ** 2).mean())
    # the windowed FFT correlates neighbouring cells: allow 6 / sqrt(n / 4) relative
    assert abs(p / noise_power_rd(cfg) - 1) < 6 / math.sqrt(n / 4)


def test_noise_floor_power_and_statistics():
    cfg = RADIAL_S
    g = torch.Generator().manual_seed(0)
    rd = synthesize_rd(cfg, empty(), generator=g)
    n = rd.numel()                                                   # 131072 independent cells
    p = (rd.abs() ** 2).double()
    # |n|^2 is exponential: relative std of its mean is 1/sqrt(n); 5 sigma
    assert abs(float(p.mean()) / noise_power_rd(cfg) - 1) < 5 / math.sqrt(n)
    # circular: real and imaginary parts carry half each, zero mean
    re, im = rd.real.double(), rd.imag.double()
    half = noise_power_rd(cfg) / 2
    assert abs(float((re ** 2).mean()) / half - 1) < 5 * math.sqrt(2 / n)
    assert abs(float((im ** 2).mean()) / half - 1) < 5 * math.sqrt(2 / n)
    assert abs(float(re.mean())) < 5 * math.sqrt(half / n)


def test_far_weak_target_below_noise_and_strong_one_above():
    cfg = RADIAL_S
    weak = one(100.0, 0.0, 0.0, 0.0, rcs=1e-3)
    assert float(peak_snr_rd(cfg, 100.0, 1e-3)) < 0.1
    rd = synthesize_rd(cfg, weak, noise=False)
    assert float((rd.abs() ** 2).max()) < 0.2 * noise_power_rd(cfg)
    g = torch.Generator().manual_seed(1)
    noisy = synthesize_rd(cfg, weak, generator=g)
    r_bin = round(100.0 / cfg.range_res_m)
    # the weak target's cell is not distinguishable: below the largest of the noise
    assert float(noisy[r_bin, 0].abs().pow(2).mean()) < float(noisy.abs().pow(2).mean(-1).max())
    strong = synthesize_rd(cfg, one(20.0, 0.0, 0.0, 0.0, rcs=1.0), generator=g)
    assert float(strong[round(20.0 / cfg.range_res_m), 0].abs().pow(2).mean()) > 1e3 * noise_power_rd(cfg)


def test_noise_is_reproducible_from_the_generator():
    cfg = TINY
    a = synthesize_rd(cfg, empty(), generator=torch.Generator().manual_seed(7))
    b = synthesize_rd(cfg, empty(), generator=torch.Generator().manual_seed(7))
    c = synthesize_rd(cfg, empty(), generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_doppler_wraps_and_batches():
    cfg = TINY
    v = 3.3
    a = synthesize_rd(cfg, one(7.0, 5.0, 0.0, v), noise=False)
    b = synthesize_rd(cfg, one(7.0, 5.0, 0.0, v + 2 * cfg.max_velocity_mps), noise=False)
    assert torch.allclose(a, b, rtol=0, atol=1e-4 * float(a.abs().max()))
    batch = synthesize_rd(cfg, [one(7.0, 5.0, 0.0, v), empty()], noise=False)
    assert batch.shape == (2, *cfg.rd_shape)
    assert torch.equal(batch[0], a) and not bool(batch[1].abs().any())


def test_window_psf_is_the_dtft_of_the_window():
    n = 16
    w = window(n)
    delta = torch.tensor([0.0, 0.25, -0.5, 1.0, 3.7, -7.9, 8.0, 15.5, 16.0])
    k = torch.arange(n, dtype=torch.float64)
    brute = (w[None, :] * torch.exp(-2j * math.pi * delta[:, None].double() * k[None, :] / n)).sum(1)
    torch.testing.assert_close(window_psf(delta, n), brute, rtol=0, atol=1e-12)


def test_psf_columns_equal_the_closed_form():
    n = 64
    b = torch.tensor([0.0, 3.25, 17.5, 63.9, -2.3, 100.7], dtype=torch.float64)
    i = torch.arange(n, dtype=torch.float64)
    torch.testing.assert_close(psf_columns(b, n), window_psf(i[:, None] - b[None, :], n), rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="real"):
        psf_columns(torch.zeros(3, dtype=torch.complex64), n)


def test_steering_torch_matches_numpy_reference():
    az = torch.tensor([-70.0, 0.0, 33.3])
    el = torch.tensor([5.0, -8.0, 0.0])
    ref = steering_vectors(RADIAL_S, az.numpy(), el.numpy())
    np.testing.assert_allclose(steering_torch(RADIAL_S, az, el).numpy(), ref, rtol=0, atol=1e-9)


def test_from_xyz_geometry_and_static_clutter_velocity():
    v_ego = 12.0
    p = torch.tensor([[10.0, 10.0, 0.0], [3.0, 0.0, 4.0]])
    vel = torch.tensor([[-v_ego, 0.0, 0.0], [-v_ego, 0.0, 0.0]])      # static world seen from ego
    sc = Scatterers.from_xyz(p, vel, torch.tensor([1.0, 2.0]))
    torch.testing.assert_close(sc.range_m, torch.tensor([math.sqrt(200.0), 5.0]))
    torch.testing.assert_close(sc.azimuth_deg, torch.tensor([45.0, 0.0]))
    torch.testing.assert_close(sc.elevation_deg, torch.tensor([0.0, math.degrees(math.asin(0.8))]))
    # static clutter approaches: -v_ego cos(az) cos(el)
    want = -v_ego * torch.cos(torch.deg2rad(sc.azimuth_deg)) * torch.cos(torch.deg2rad(sc.elevation_deg))
    torch.testing.assert_close(sc.velocity_mps, want)


def test_bad_input_is_rejected_with_a_clear_message():
    with pytest.raises(ValueError, match="xyz must have shape"):
        Scatterers.from_xyz(torch.zeros(4, 2), torch.zeros(4, 2), torch.ones(4))
    with pytest.raises(ValueError, match="origin"):
        Scatterers.from_xyz(torch.zeros(1, 3), torch.zeros(1, 3), torch.ones(1))
    with pytest.raises(ValueError, match="rcs_m2 must have shape"):
        Scatterers.from_xyz(torch.ones(2, 3), torch.zeros(2, 3), torch.ones(3))
    with pytest.raises(ValueError, match="NaN"):
        one(float("nan"), 0, 0, 0)
    with pytest.raises(ValueError, match="range_m must be > 0"):
        one(-1.0, 0, 0, 0)
    with pytest.raises(ValueError, match="rcs_m2 must be >= 0"):
        one(1.0, 0, 0, 0, rcs=-1.0)
    with pytest.raises(ValueError, match="shape"):
        Scatterers(torch.ones(2), torch.ones(3), torch.ones(2), torch.ones(2), torch.ones(2))
    with pytest.raises(ValueError, match="real float"):
        Scatterers(torch.ones(2, dtype=torch.complex64), *(torch.ones(2),) * 4)
    with pytest.raises(ValueError, match="expects Scatterers"):
        synthesize_rd(TINY, torch.ones(3))
    with pytest.raises(ValueError, match="n_doppler, n_range, n_rx"):
        rd_from_adc(TINY, torch.zeros(2, 2, 2, dtype=torch.complex64))
