"""Tests for radarpc.dsp.tdm: RaLD's single-chip TDM cube against a NumPy reference and a point target."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radarpc.dsp.tdm import radar_cube, rald_velocity_bin_width, tdm_spectrum
from radarpc.sensors.coloradar import AWR1843


def test_radar_cube_validation_and_batch():
    chip = AWR1843.replace(num_chirps_per_frame=8)
    with pytest.raises(ValueError, match="complex"):
        radar_cube(np.zeros((3, 4, 8, 128), np.float32), chip)
    with pytest.raises(ValueError, match="shape"):
        radar_cube(np.zeros((3, 4, 8, 64), np.complex64), chip)
    bad = np.zeros((3, 4, 8, 128), np.complex64)
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        radar_cube(bad, chip)
    rng = np.random.default_rng(0)
    x = (rng.normal(size=(2, 3, 4, 8, 128)) + 1j * rng.normal(size=(2, 3, 4, 8, 128))).astype(np.complex64)
    batch = radar_cube(x, chip, n_doppler=8)
    one = radar_cube(x[1], chip, n_doppler=8)
    assert batch.intensity_db.shape == (2, 128, 8, 2) and batch.stacked().shape == (2, 128, 8, 2, 3)
    torch.testing.assert_close(batch.intensity_db[1], one.intensity_db, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="noise_quantile"):
        radar_cube(x, chip, noise_quantile=1.0)
    with pytest.raises(ValueError, match="crop"):
        tdm_spectrum(x, chip, crop=0.5)
    spec = tdm_spectrum(x, chip, n_doppler=8)
    assert spec.shape == (2, 2, 8, 8, 128) and spec.dtype == torch.complex64
    assert not spec[..., :6].any() and not spec[..., -6:].any()               # 5 % of 128 bins zeroed


def test_velocity_bin_width_rald_and_physical_from_the_sensor_constants():
    # AWR1843 as ColoRadar records it: 77 GHz start, 100 MHz/us, 10.666 MS/s, 128 samples from 7 us,
    # idle 110 us, ramp end 19.1 us, 3 Tx, 128 loops. Worked by hand with c = 299,792,458 m/s.
    c, n = 299_792_458.0, 128
    # RaLD (dataset_preprocessor/utils/radardsp.py): lambda at the start frequency, chirp time
    # idle + 128 / f_s + ADC start = 110 + 12.0007 + 7 = 129.0007 us
    t_rald = 110e-6 + 128 / 10.666e6 + 7e-6
    rald = 2 * (c / 77e9) / (4 * 3 * t_rald) / n
    # the sampled sweep's physics: lambda at its centre 77 GHz + 1e14 Hz/s (7 us + 64 / f_s) =
    # 78.30003 GHz, chirp period idle + ramp end = 129.1 us
    f_c = 77e9 + 1.00000000377e14 * (7e-6 + 64 / 10.666e6)
    physical = 2 * (c / f_c) / (4 * 3 * (110e-6 + 19.1e-6)) / n
    assert rald == pytest.approx(0.03930, abs=5e-6) and physical == pytest.approx(0.03862, abs=5e-6)
    assert 1 - physical / rald == pytest.approx(0.017, abs=5e-4)                 # "1.7 % smaller"
    w = AWR1843.waveform
    assert rald_velocity_bin_width(w, n) == pytest.approx(rald, rel=1e-12)
    assert w.velocity_bin_width(n) == pytest.approx(physical, rel=1e-12)
    with pytest.raises(ValueError, match="n_doppler"):
        rald_velocity_bin_width(w, 0)


def test_radar_cube_velocity_axis_is_ralds():
    # a moving reflector: the cube's Doppler values are multiples of RaLD's bin width, not the
    # physical one (the cube is RaLD's)
    from radarpc.sim.coloradar_synth import Scatterers, beat_signal
    chip = AWR1843.replace(num_chirps_per_frame=16)
    s = Scatterers(torch.tensor([[5.0, 0.0, 0.0]], dtype=torch.float64), rcs=torch.tensor([1.0]),
                   phase=torch.tensor([0.0]), velocity=torch.tensor([0.5]))
    cube = radar_cube(beat_signal(s, chip), chip, n_doppler=16)
    ri, ai, ei = np.unravel_index(int(cube.intensity_db.argmax()), tuple(cube.intensity_db.shape))
    v = float(cube.doppler[ri, ai, ei])
    k = round(v / rald_velocity_bin_width(chip.waveform, 16))
    assert k != 0 and v == pytest.approx(k * rald_velocity_bin_width(chip.waveform, 16), rel=1e-6)
    assert v != pytest.approx(k * chip.waveform.velocity_bin_width(16), rel=1e-3)


def _reference_cube(adc: np.ndarray, chip) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Independent NumPy version of RaLD's single-chip processing (loops, float64), (R, A, E) outputs.
    ntx, nrx, nc, ns = adc.shape
    x = adc.astype(np.complex128) - adc.mean()
    x = x * np.blackman(ns)
    d = np.fft.fftshift(np.fft.fft(np.fft.fft(x, 128, -1), nc, -2), -2)
    for t in range(ntx):
        for c in range(nc):
            d[t, :, c, :] *= np.exp(-2j * np.pi * t * (c - nc // 2) / (ntx * nc))
    va = np.zeros((2, 8, nc, 128), np.complex128)
    for t, (ta, te) in enumerate(chip.antenna.tx_positions):
        for r, (ra, re) in enumerate(chip.antenna.rx_positions):
            va[int(te + re), int(ta + ra)] += d[t, r]
    e = np.fft.fftshift(np.fft.fft(np.fft.fftshift(np.fft.fft(va, 8, 1), 1), 2, 0), 0)
    e[..., :6] = 0
    e[..., -6:] = 0
    p = np.abs(e) ** 2                                              # (E, A, D, R)
    srt = np.sort(p, axis=2)
    valid = srt[:, :, -1] * 0.7 > srt[:, :, -2]
    w = chip.waveform                                               # RaLD's bin width, from its formula
    t_chirp = w.idle_time + w.num_adc_samples_per_chirp / w.adc_sample_frequency + w.adc_start_time
    vel = (np.argmax(p, axis=2) - nc // 2) * (299_792_458.0 / w.start_frequency) / (2 * ntx * t_chirp * nc)
    ps = p.sum(2)
    db = 10 * np.log10(ps / (np.quantile(ps, 0.3) + 1e-6) + 1)
    return db.transpose(2, 1, 0), vel.transpose(2, 1, 0), valid.transpose(2, 1, 0)


def test_radar_cube_matches_numpy_reference():
    chip = AWR1843.replace(num_chirps_per_frame=16)
    rng = np.random.default_rng(1)
    adc = (rng.normal(size=(3, 4, 16, 128)) + 1j * rng.normal(size=(3, 4, 16, 128))).astype(np.complex64)
    adc += 20 * np.exp(2j * np.pi * (0.2 * np.arange(128) + 0.1 * np.arange(16)[:, None]))  # a tone
    cube = radar_cube(adc, chip, n_doppler=16)
    db, vel, valid = _reference_cube(adc, chip)
    np.testing.assert_allclose(cube.intensity_db.numpy(), db, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(cube.doppler.numpy(), vel, atol=1e-6)
    agree = (cube.valid.numpy() == valid).mean()
    assert agree > 0.995                                            # ties at float32 precision aside


def _point_target(r: float, az_deg: float, el_deg: float):
    from radarpc.sim.coloradar_synth import Scatterers
    az, el = math.radians(az_deg), math.radians(el_deg)
    p = torch.tensor([[r * math.cos(el) * math.cos(az), r * math.cos(el) * math.sin(az), r * math.sin(el)]],
                     dtype=torch.float64)
    return Scatterers(p, torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([0.0]))


@pytest.mark.parametrize("el_deg", [15.0, -15.0])
def test_point_reflector_at_elevation_in_radar_cube(el_deg):
    # A reflector at +-15 deg elevation, on an azimuth bin centre, noise-free (the simulator's
    # public beat_signal). The 8 x 2 virtual array has rows 0 and 1 (Tx 2 raised by one unit), so
    # a zero-padded elevation FFT peaks at f_e = d sin(el): the elevation sign is recoverable
    # only with n_elevation > 2.
    from radarpc.sim.coloradar_synth import beat_signal
    chip = AWR1843.replace(num_chirps_per_frame=8)
    d = chip.element_spacing
    az_deg = math.degrees(math.asin(1 / (8 * d)))                   # centre of azimuth bin 5
    r = 40 * chip.waveform.range_bin_width(128)                     # range bin 40
    adc = beat_signal(_point_target(r, az_deg, el_deg), chip)
    cube = radar_cube(adc, chip, n_doppler=8, n_elevation=16)
    ri, ai, ei = np.unravel_index(int(cube.intensity_db.argmax()), tuple(cube.intensity_db.shape))
    assert ri == 40 and ai == 5
    assert cube.azimuth_rad[ai].item() == pytest.approx(math.radians(az_deg), abs=1e-6)
    el_bins = np.degrees(cube.elevation_rad.numpy())
    want = int(np.argmin(np.abs(np.sin(np.radians(el_bins)) - math.sin(math.radians(el_deg)))))
    assert ei == want and np.sign(el_bins[ei]) == np.sign(el_deg)   # up is +z, bins ascend
    assert abs(el_bins[ei] - el_deg) < 5.0
    # RaLD's 2-bin elevation FFT: bins f_e = -1/2 (about -79 deg) and 0; at the target's cell the
    # magnitudes are the same for +el and -el (|a +- b e^{j phi}| = |a +- b e^{-j phi}| for the
    # real row sums a, b at the azimuth peak), and the 0-deg bin holds most of the energy at 15 deg.
    # The normalisation divides by the cube's 30 % power quantile, which for this noise-free target
    # is floating-point residue of the FFTs (~1e-15 of the peak, different with every FFT kernel),
    # so the +-el symmetry is checked on the powers before normalisation, and on the level of one
    # elevation bin relative to the other within a normalised cube (the quantile cancels).
    two = tdm_spectrum(adc, chip, n_doppler=8, n_elevation=2)                         # (E, A, D, R)
    mirror = tdm_spectrum(beat_signal(_point_target(r, az_deg, -el_deg), chip), chip, n_doppler=8, n_elevation=2)
    p_two = (two.abs() ** 2).sum(-2)[:, 5, 40].double()                             # (E,) at the target
    p_mirror = (mirror.abs() ** 2).sum(-2)[:, 5, 40].double()
    # float32 from the input through 4 FFTs (log2 n butterfly stages each): relative amplitude error
    # <= eps (1 + sum log2 n) per path, doubled for a power, with a safety factor of 4
    eps = torch.finfo(torch.float32).eps
    rtol = 4 * 2 * eps * (1 + math.log2(128) + math.log2(8) + math.log2(8) + math.log2(2))
    torch.testing.assert_close(p_two, p_mirror, rtol=rtol, atol=0.0)
    cube, cube_m = (radar_cube(x, chip, n_doppler=8, n_elevation=2) for x in
                    (adc, beat_signal(_point_target(r, az_deg, -el_deg), chip)))
    gap = (cube.intensity_db[40, 5, 1] - cube.intensity_db[40, 5, 0]).item()
    gap_m = (cube_m.intensity_db[40, 5, 1] - cube_m.intensity_db[40, 5, 0]).item()
    db = 10 / math.log(10)                                    # d(10 log10 p) = db * dp / p
    # both bins' relative errors (rtol each), plus float32 rounding of two ~148 dB values
    assert gap == pytest.approx(gap_m, abs=db * 2 * rtol + 2 * 148 * eps * 4)
    assert gap == pytest.approx(10 * math.log10(p_two[1] / p_two[0]), abs=db * 2 * rtol + 2 * 148 * eps * 4)
    assert np.degrees(cube.elevation_rad.numpy())[1] == 0.0
    assert gap > 3.0                                           # the 0-deg bin holds most of the energy
