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
