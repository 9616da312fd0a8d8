"""Sensor configs and array model of the RADIal-like DDMA radar."""
import dataclasses
import json

import numpy as np
import pytest

from radarpc.sensors.radial import (
    RADIAL,
    RADIAL_S,
    TINY,
    DDMARadarConfig,
    coupling_matrix,
    element_gain,
    ideal_receiver,
    radial_sensor,
    steering_vectors,
)


def test_radial_numbers_match_the_dataset():
    assert RADIAL.rd_shape == (512, 256, 16)
    assert RADIAL.n_virtual == 192
    assert RADIAL.slot_width == 16 and RADIAL.n_empty_slots == 4
    assert tuple(RADIAL.tx_slots) == (0, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
    np.testing.assert_array_equal(RADIAL.doppler_offsets, [0] + list(range(80, 256, 16)))
    assert RADIAL.max_range_m == pytest.approx(103.0)
    # c / (2 B) is one range bin
    assert 299_792_458.0 / (2 * RADIAL.bandwidth_hz) == pytest.approx(RADIAL.range_res_m)
    # lambda / (2 N Tc) and the wrap at +-v_max
    lam = 299_792_458.0 / 77e9
    assert RADIAL.velocity_res_mps == pytest.approx(lam / (2 * 256 * 50e-6))
    assert RADIAL.velocity_of_bin(0) == 0
    assert RADIAL.velocity_of_bin(255) == pytest.approx(-RADIAL.velocity_res_mps)
    assert RADIAL.velocity_of_bin(128) == pytest.approx(-RADIAL.max_velocity_mps)
    assert RADIAL.doppler_bin_of_velocity(-RADIAL.velocity_res_mps) == pytest.approx(255)


def test_radial_s_keeps_array_and_field_of_view():
    assert RADIAL_S.rd_shape == (128, 64, 16)
    assert RADIAL_S.n_virtual == 192 and RADIAL_S.tx_pos == RADIAL.tx_pos
    assert RADIAL_S.max_range_m == pytest.approx(RADIAL.max_range_m)
    assert RADIAL_S.max_velocity_mps == pytest.approx(RADIAL.max_velocity_mps)
    assert RADIAL_S.slot_width == 4


def test_virtual_channel_order_is_tx_major():
    p = RADIAL.virtual_positions
    tx, rx = 7, 3
    np.testing.assert_allclose(p[tx * 16 + rx], np.add(RADIAL.tx_pos[tx], RADIAL.rx_pos[rx]))


def test_radar_equation_scales_with_r4_and_rcs():
    s1 = RADIAL.snr_per_sample(10.0, 1.0)
    assert RADIAL.snr_per_sample(20.0, 1.0) == pytest.approx(s1 / 16)
    assert RADIAL.snr_per_sample(10.0, 10.0) == pytest.approx(10 * s1)


def test_array_phase_sign_is_the_physical_one():
    # IF = tx * conj(rx): phase +2 pi f_c tau. A target on the left (+y) is nearer the elements at
    # larger horizontal position, so their delay (and phase) is smaller by pi * p_h * sin(az):
    # exp(-j pi p . u), hand-worked for one element at p = (3, 0) and one at p = (0, 1).
    cfg = TINY
    a = steering_vectors(cfg, 30.0, 0.0, hardware=False)            # sin 30 deg = 0.5
    p = cfg.virtual_positions
    k = int(np.flatnonzero((p[:, 0] == 3.0) & (p[:, 1] == 0.0))[0])
    assert np.angle(a[k] / a[0]) == pytest.approx(np.angle(np.exp(-1j * np.pi * 1.5)))
    up = steering_vectors(cfg, 0.0, 30.0, hardware=False)
    k = int(np.flatnonzero((p[:, 0] == 4.0) & (p[:, 1] == 1.0))[0])
    assert np.angle(up[k] / up[0]) == pytest.approx(np.angle(np.exp(-1j * np.pi * (4 * 0.0 + 0.5))))


def test_config_dict_round_trip_and_validation():
    d = json.loads(json.dumps(RADIAL_S.to_dict()))
    assert DDMARadarConfig.from_dict(d) == RADIAL_S
    assert radial_sensor("tiny") is TINY
    with pytest.raises(ValueError, match="unknown sensor 'radal'"):
        radial_sensor("radal")
    with pytest.raises(ValueError, match="multiple of n_slots"):
        dataclasses.replace(RADIAL, n_doppler=250)
    with pytest.raises(ValueError, match="tx_slots must be Tx 0 in slot 0"):
        dataclasses.replace(RADIAL, tx_slots=tuple(range(12)))
    with pytest.raises(ValueError, match="unknown sensor config keys"):
        DDMARadarConfig.from_dict({**d, "colour": 1})


def test_element_pattern_attenuates_70_deg_by_the_stated_amount():
    # stated: one way -4.5 / -7.0 / -8.8 dB at 60 / 70 / 75 deg azimuth, -1.3 dB at 10 deg elevation
    # (closed form 10 log10 cos^q, q_az = 1.5, q_el = 20)
    g = 10 * np.log10(element_gain(RADIAL, np.array([60.0, 70.0, 75.0]), 0.0))
    np.testing.assert_allclose(g, [-4.5, -7.0, -8.8], atol=0.05)
    np.testing.assert_allclose(g, 15 * np.log10(np.cos(np.deg2rad([60.0, 70.0, 75.0]))), rtol=1e-12)
    assert 10 * np.log10(element_gain(RADIAL, 0.0, 10.0)) == pytest.approx(200 * np.log10(np.cos(np.deg2rad(10))))
    assert element_gain(RADIAL, 0.0, 0.0) == 1.0 and element_gain(RADIAL, 95.0, 0.0) == 0.0
    # in the synthesis: a target at 70 deg against the same target at 0 deg, per channel, is the
    # two-way power (G/G0)^2 = cos(70)^3 = -14.0 dB (coupling off: otherwise each channel mixes
    # its neighbours with direction-dependent phases)
    import torch
    from radarpc.sim.rd import Scatterers, synthesize_rd
    cfg = ideal_receiver(dataclasses.replace(TINY, coupling_reach=0.0))
    t = lambda x: torch.tensor([float(x)], dtype=torch.float64)  # noqa: E731
    peak = []
    for az in (0.0, 70.0):
        rd = synthesize_rd(cfg, Scatterers(t(8.0), t(az), t(0.0), t(0.0), t(10.0)), noise=False)
        peak.append(rd[20, torch.as_tensor(cfg.doppler_offsets), :].abs().double().numpy() ** 2)   # (n_tx, n_rx)
    np.testing.assert_allclose(peak[1] / peak[0], np.cos(np.deg2rad(70.0)) ** 3, rtol=1e-5)
    assert 10 * np.log10(np.cos(np.deg2rad(70.0)) ** 3) == pytest.approx(-14.0, abs=0.05)


def test_coupling_is_banded_and_symmetric():
    c = coupling_matrix(RADIAL, RADIAL.rx_pos)
    assert np.allclose(c, c.T) and np.all(np.diag(c) == 1)
    # stated: -22 dB to the neighbour (1 half wavelength), -34 dB to the next (1/d^2), none beyond 9
    assert 20 * np.log10(abs(c[5, 6])) == pytest.approx(-22.0)
    assert 20 * np.log10(abs(c[5, 7])) == pytest.approx(-22.0 - 40 * np.log10(2))
    assert c[0, 10] == 0 and c[0, 9] != 0
    # phase of the path between the elements: exp(-j pi d)
    assert np.angle(c[5, 7] / abs(c[5, 7])) == pytest.approx(np.angle(np.exp(-2j * np.pi)), abs=1e-12)
    tx = coupling_matrix(RADIAL, RADIAL.tx_pos)
    assert np.abs(tx - np.eye(12)).max() < 10 ** (-45 / 20)          # Tx >= 4 half wavelengths apart


def test_calibration_grids():
    # radial and radial-s: RADIAL's real table size, 0.2 deg over +-75 deg, 11 elevations (0 in the middle)
    for cfg in (RADIAL, RADIAL_S):
        az, el = cfg.azimuth_table_deg, cfg.elevation_table_deg
        assert az.shape == (751,) and el.shape == (11,)
        np.testing.assert_allclose(np.diff(az), 0.2, atol=1e-9)
        assert az[0] == -75.0 and az[-1] == 75.0 and el[5] == 0.0
    assert TINY.azimuth_table_deg.shape == (61,)


def test_receiver_settings_are_validated():
    with pytest.raises(ValueError, match="aa_order must be an integer >= 0"):
        dataclasses.replace(RADIAL, aa_order=-1)
    with pytest.raises(ValueError, match="if_highpass_hz must be >= 0"):
        dataclasses.replace(RADIAL, if_highpass_hz=-5.0)
    with pytest.raises(ValueError, match="leakage_range_m must be > 0 with leakage on"):
        dataclasses.replace(RADIAL, leakage_range_m=0.0)
    with pytest.raises(ValueError, match="cal_positioner_deg"):
        dataclasses.replace(RADIAL, cal_drift=(0.1,))
    off = ideal_receiver(RADIAL)
    assert off.leakage_db is None and off.pn_dbc_hz is None and off.aa_order == 0
    d = json.loads(json.dumps(RADIAL.to_dict()))
    assert DDMARadarConfig.from_dict(d) == RADIAL
    assert DDMARadarConfig.from_dict(json.loads(json.dumps(off.to_dict()))) == off
