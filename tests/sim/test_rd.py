"""Frequency-domain RD synthesis against hand-worked values and the exact ADC-domain route."""
import math

import numpy as np
import pytest
import torch

from radarpc.sensors.radial import RADIAL_S, TINY, ideal_receiver, steering_vectors
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.adc import migration_bins, narrowband_bins, rd_from_adc, synthesize_ddma_adc, synthesize_rd_exact
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
    cfg = ideal_receiver(cfg)                       # no Tx leakage at range 0, no IF filter
    v = float(cfg.velocity_of_bin(d_bin))
    rd = synthesize_rd(cfg, one(cfg.range_of_bin(r_bin), az, el, v, rcs=10.0), noise=False)
    assert rd.shape == cfg.rd_shape and rd.dtype == torch.complex64
    power = (rd.abs() ** 2).sum(-1)                                  # (R, D)
    r_pk, d_pk = np.unravel_index(int(power.argmax()), power.shape)
    assert r_pk == r_bin
    # the n_tx replicas: Tx m at (d0 + o_m) mod N_d, all of about the same power
    replicas = (d_bin + cfg.doppler_offsets) % cfg.n_doppler
    assert d_pk in replicas
    top = torch.topk(power[r_bin], cfg.n_tx).indices.sort().values.numpy()
    np.testing.assert_array_equal(top, np.sort(replicas))
    # outside the replicas' main lobes (+-1 bin for Hamming) only sidelobes remain (< -40 dB)
    occupied = np.zeros(cfg.n_doppler, bool)
    for s in (-1, 0, 1):
        occupied[(replicas + s) % cfg.n_doppler] = True
    assert float(power[r_bin, ~occupied].max()) < 1e-4 * float(power[r_bin, replicas].min())
    # virtual snapshot in Tx order -> beamformed peak at the target's (az, el) grid cell; with the
    # measured calibration and an elevation between grid values (radial-s: 5 -> 6, -10 -> -9 deg;
    # u_y = cos(el) sin(az) couples them) within one grid step in each
    snap = rd[r_bin, torch.as_tensor(replicas), :].reshape(-1)       # (n_tx * n_rx,)
    calib = make_calibration(cfg)
    spec = (calib.dictionary() @ snap).abs()
    k = int(spec.argmax())
    n_el = calib.grid_shape[1]
    az_step = (cfg.az_grid_deg[1] - cfg.az_grid_deg[0]) / (cfg.az_grid_deg[2] - 1)
    el_step = (cfg.el_grid_deg[1] - cfg.el_grid_deg[0]) / (cfg.el_grid_deg[2] - 1)
    # + float32 rounding of the stored tables (|angle| <= 90: < 1e-5 deg)
    assert abs(float(calib.azimuth_deg[k // n_el]) - az) <= az_step + 1e-5
    assert abs(float(calib.elevation_deg[k % n_el]) - el) <= el_step + 1e-5


def test_peak_amplitude_is_the_radar_equation_times_fft_gain():
    cfg = ideal_receiver(RADIAL_S)
    r_bin, rcs = 40, 2.0
    rd = synthesize_rd(cfg, one(cfg.range_of_bin(r_bin), 0.0, 0.0, 0.0, rcs), noise=False)
    # Tx 0 / Rx 0: the true response there (errors 1 on the reference chains; coupling to the
    # neighbours, pattern 1 at boresight)
    gain2 = abs(complex(steering_vectors(cfg, 0.0, 0.0)[0])) ** 2
    snr_cell = float(rd[r_bin, 0, 0].abs() ** 2) / noise_power_rd(cfg)
    # periodic Hamming: sum w = 0.54 N, sum w^2 = N (0.54^2 + 0.46^2 / 2) -> loss 0.2916 / 0.3974
    loss = 0.54 ** 2 / (0.54 ** 2 + 0.46 ** 2 / 2)
    want = float(cfg.snr_per_sample(cfg.range_of_bin(r_bin), rcs)) * cfg.n_range * cfg.n_doppler * loss ** 2
    assert snr_cell == pytest.approx(want * gain2, rel=1e-4)
    assert abs(gain2 - 1) > 1e-3                     # coupling: channel 0 is not the bare element
    assert float(peak_snr_rd(cfg, cfg.range_of_bin(r_bin), rcs)) == pytest.approx(want, rel=1e-9)


def _targets(velocity):
    # several targets at fractional range and Doppler bins, off broadside in azimuth and elevation
    v = torch.tensor(velocity, dtype=torch.float64)
    return Scatterers(
        range_m=torch.tensor([3.37, 10.05, 17.61, 5.2, 22.9], dtype=torch.float64),
        azimuth_deg=torch.tensor([10.0, -25.0, 40.0, 0.0, -55.0], dtype=torch.float64),
        elevation_deg=torch.tensor([0.0, 5.0, -3.0, 2.0, 12.0], dtype=torch.float64),
        velocity_mps=v,
        rcs_m2=torch.tensor([1.0, 10.0, 0.5, 3.0, 20.0], dtype=torch.float64),
    )


def _bound(cfg, sc, slack_bins):
    # |exp(j x) - 1| <= |x| per ADC sample: an extra beat frequency of delta bins changes each
    # windowed sample of each element-pair tone by at most 2 pi delta of its magnitude, so per RD cell
    # |exact - fast| <= 2 pi delta * sum_s A_s max_r sum_m (sum_m' |T[m, m']|)(sum_r' |R[r, r']|)
    # * sum(w_r) * sum(w_d)   (element pattern <= 1; T, R the coupling-and-error matrices)
    from radarpc.sensors.radial import array_factors
    from radarpc.sim.rd import adc_noise_power, window_sums
    amp = np.sqrt(cfg.snr_per_sample(sc.range_m.numpy(), sc.rcs_m2.numpy()) * adc_noise_power(cfg))
    t, r = array_factors(cfg)
    g = np.abs(t).sum(1).sum() * np.abs(r).sum(1).max()
    s_r, _ = window_sums(cfg.n_range)
    s_d, _ = window_sums(cfg.n_doppler)
    return float(np.sum(2 * math.pi * np.asarray(slack_bins) * amp) * g * s_r * s_d)


def test_frequency_domain_matches_narrowband_exact_adc_synthesis_at_rest():
    cfg = TINY
    sc = _targets([0.0] * 5)
    fast = synthesize_rd(cfg, sc, noise=False).to(torch.complex128)
    exact = synthesize_rd_exact(cfg, sc, narrowband=True)
    # v = 0, array delay kept in the carrier phase only: the two models are the same function,
    # tight tolerance (complex64 output of the fast model)
    assert float((fast - exact).abs().max()) <= 1e-5 * float(exact.abs().max())
    # fractional range bins: sidelobes in every range bin, not trivially equal
    assert float(exact.abs().amax(dim=(1, 2)).min()) > 1e-6 * float(exact.abs().max())


def test_frequency_domain_within_the_stated_bound_of_the_full_exact_model():
    cfg = TINY
    for vel in ([0.0] * 5, [2.3, -7.7, 15.0, 0.4, 27.1]):   # at rest, then moderate v (one wraps)
        sc = _targets(vel)
        fast = synthesize_rd(cfg, sc, noise=False).to(torch.complex128)
        exact = synthesize_rd_exact(cfg, sc)
        # per scatterer: array delay (narrowband) + range migration over the frame, in bins
        slack = [narrowband_bins(cfg, a, e) + migration_bins(cfg, v)
                 for a, e, v in zip(sc.azimuth_deg.tolist(), sc.elevation_deg.tolist(), vel)]
        assert max(slack) < 0.15                 # TINY: <= 0.018 array + 0.108 migration bins
        err = float((fast - exact).abs().max())
        assert err <= _bound(cfg, sc, slack)
        # the bound is tight enough to catch a mirrored array (measured: 0.8 % of the peak at
        # rest, 2.0 % at these velocities; a mirrored azimuth is off by 1.8x the peak)
        mirrored = Scatterers(sc.range_m, -sc.azimuth_deg, sc.elevation_deg, sc.velocity_mps, sc.rcs_m2)
        wrong = synthesize_rd(cfg, mirrored, noise=False).to(torch.complex128)
        assert _bound(cfg, sc, slack) < 0.5 * float((wrong - exact).abs().max())
        assert err <= 0.05 * float(exact.abs().max())


def test_migration_and_narrowband_figures():
    # TINY: 32 chirps x 50 us = 1.6 ms; at 27.1 m/s the target moves 4.3 cm = 0.108 of a 0.4 m bin
    assert migration_bins(TINY, 27.1) == pytest.approx(27.1 * 32 * 50e-6 / 0.4)
    assert migration_bins(TINY, -27.1) == migration_bins(TINY, 27.1)
    # broadside: no array delay; endfire along +y: largest horizontal virtual position 4 + 3 = 7
    assert narrowband_bins(TINY, 0.0, 0.0) == 0.0
    lam = TINY.wavelength_m
    assert narrowband_bins(TINY, 90.0, 0.0) == pytest.approx(7 * lam / (4 * 0.4))


def test_exact_model_catches_a_mirrored_array_or_ddma_error():
    # the agreement test is sensitive: a mirrored azimuth or a wrong DDMA slot is far outside it
    cfg = TINY
    sc = _targets([0.0] * 5)
    exact = synthesize_rd_exact(cfg, sc, narrowband=True)
    mirrored = Scatterers(sc.range_m, -sc.azimuth_deg, sc.elevation_deg, sc.velocity_mps, sc.rcs_m2)
    wrong = synthesize_rd(cfg, mirrored, noise=False).to(torch.complex128)
    assert float((wrong - exact).abs().max()) > 0.3 * float(exact.abs().max())
    import dataclasses
    slots = dataclasses.replace(cfg, n_slots=8, tx_slots=(0, 7), n_doppler=32)
    exact_s = synthesize_rd_exact(slots, sc, narrowband=True)
    assert float((synthesize_rd(cfg, sc, noise=False).to(torch.complex128) - exact_s).abs().max()) \
        > 0.3 * float(exact_s.abs().max())


def test_adc_phase_is_the_physical_path_length_per_element():
    # independent of the plane-wave formula: spherical distances from a point target to each Tx
    # and Rx element (positions lambda/2 * p in the y-z plane); IF = tx * conj(rx) -> phase
    # +2 pi f_c tau. A target on the left (+y) is nearer the +y elements: smaller phase there.
    import dataclasses
    from radarpc.sensors.radial import SPEED_OF_LIGHT, channel_errors
    cfg = dataclasses.replace(TINY, coupling_reach=0.0)             # each channel its own element pair
    lam = cfg.wavelength_m
    target = np.array([20.0, 8.0, 1.5])                           # left (+y), slightly up
    sc = Scatterers.from_xyz(target[None].astype(np.float64), np.zeros((1, 3)), np.array([5.0]))
    adc = synthesize_ddma_adc(cfg, sc).numpy()                         # (k, n, r), Tx summed
    # isolate Tx m by its DDMA code: demodulate and average over chirps
    width = cfg.n_doppler // cfg.n_slots
    k = np.arange(cfg.n_doppler)
    g = channel_errors(cfg).reshape(cfg.n_tx, cfg.n_rx)
    for m, slot in enumerate(cfg.tx_slots):
        demod = (adc[:, 0, :] * np.exp(-2j * np.pi * slot * width * k / cfg.n_doppler)[:, None]).mean(0)
        ph = demod / g[m]                                         # (r,) sample n = 0: carrier only
        pos = lambda q: np.array([0.0, q[0] * lam / 2, q[1] * lam / 2])  # noqa: E731
        d_tx = np.linalg.norm(target - pos(cfg.tx_pos[m]))
        want = np.array([2 * np.pi * cfg.carrier_hz * (d_tx + np.linalg.norm(target - pos(q))) / SPEED_OF_LIGHT
                         for q in cfg.rx_pos])
        got_rel = np.angle(ph * np.conj(ph[0]))
        want_rel = np.angle(np.exp(1j * (want - want[0])))
        np.testing.assert_allclose(got_rel, want_rel, atol=0.02)
        assert np.all(np.diff(np.unwrap(got_rel)) < 0)              # +y elements: earlier, smaller phase


def test_target_on_the_left_beamforms_to_positive_azimuth_from_adc():
    cfg = TINY
    sc = one(cfg.range_of_bin(20), 30.0, 0.0, 0.0, rcs=10.0)
    rd = synthesize_rd_exact(cfg, sc, narrowband=True)
    replicas = cfg.doppler_offsets % cfg.n_doppler
    snap = rd[20, torch.as_tensor(replicas), :].reshape(-1).to(torch.complex64)
    calib = make_calibration(cfg)
    spec = (calib.dictionary() @ snap).abs()
    k = int(spec.argmax())
    assert calib.azimuth_deg[k // calib.grid_shape[1]] == pytest.approx(30.0)


def test_adc_noise_becomes_noise_power_rd():
    cfg = TINY
    g = torch.Generator().manual_seed(3)
    rd = rd_from_adc(cfg, synthesize_ddma_adc(cfg, empty(), noise=True, generator=g))
    n = rd.numel()
    p = float((rd.abs() ** 2).mean())
    # the windowed FFT correlates neighbouring cells: allow 6 / sqrt(n / 4) relative
    assert abs(p / noise_power_rd(cfg) - 1) < 6 / math.sqrt(n / 4)


def test_noise_floor_power_and_statistics():
    cfg = ideal_receiver(RADIAL_S)                                   # white: no IF filter, no leakage
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
    cfg = ideal_receiver(RADIAL_S)
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
