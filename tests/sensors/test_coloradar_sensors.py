"""Tests for radarpc.sensors.coloradar: defaults, validation, transforms."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from radarpc.sensors.coloradar import (
    AWR1843,
    CASCADE,
    SPEED_OF_LIGHT,
    ColoRadarCalib,
    Transform,
    WaveformConfig,
    matrix_to_quaternion,
    quaternion_to_matrix,
)


def test_awr1843_numbers():
    wf = AWR1843.waveform
    # c f_s / (2 S N) equals the range bin width of the dataset's heatmap config
    assert wf.range_bin_width() == pytest.approx(SPEED_OF_LIGHT * 10_666_000 / (2 * 1.00000000377e14 * 128))
    assert wf.range_bin_width() == pytest.approx(AWR1843.heatmap.range_bin_width, rel=1e-6)
    assert AWR1843.adc_shape == (3, 4, 128, 128, 2) and AWR1843.adc_nbytes == 3 * 4 * 128 * 128 * 4
    assert CASCADE.heatmap.shape == (32, 128, 128, 2)
    assert CASCADE.waveform.range_bin_width() == pytest.approx(0.0592943951488, rel=1e-6)
    assert CASCADE.virtual_positions.shape == (192, 2)
    az = np.asarray(CASCADE.heatmap.azimuth_bins)
    assert (np.diff(az) > 0).all() and az[63] == pytest.approx(-az[64])


def test_waveform_validation():
    # an ADC window past the ramp end is a warning (recorded files round their timings), not an error
    with pytest.warns(RuntimeWarning, match="ADC window ends at 1.9800e-05 s, after ramp_end_time=1.0000e-05"):
        wf = WaveformConfig(3, 4, 128, 16, 10e6, 77e9, 1e-5, 7e-6, 10e-6, 1e14)
    assert wf.chirp_period_s == pytest.approx(2e-5)
    with pytest.raises(ValueError, match="num_tx"):
        WaveformConfig(0, 4, 128, 16, 10e6, 77e9, 1e-5, 7e-6, 30e-6, 1e14)


def test_quaternion_matches_scipy():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        np.testing.assert_allclose(quaternion_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        q2 = matrix_to_quaternion(quaternion_to_matrix(q))
        assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-9
    with pytest.raises(ValueError, match="quaternion"):
        quaternion_to_matrix([0, 0, 0, 0])


def test_transform_hand_made():
    # radar rotated +90 deg about z (its x axis = base +y), 1 m forward along base x
    s = math.sqrt(0.5)
    t_radar = Transform((1.0, 0.0, 0.0), (0.0, 0.0, s, s))
    np.testing.assert_allclose(t_radar.apply(np.array([[2.0, 0.0, 0.0]])), [[1.0, 2.0, 0.0]], atol=1e-12)
    # LiDAR at the base origin, upside-down (180 deg about x)
    t_lidar = Transform((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
    calib = ColoRadarCalib(AWR1843, None, t_radar, t_lidar, None)
    p_lidar = np.array([[1.0, 2.0, 3.0]])            # base: (1, -2, -3)
    # radar frame: R^T (p_base - t) with R = yaw 90: (x, y) -> (y, -x)
    want = np.array([[-2.0, 0.0, -3.0]])
    np.testing.assert_allclose(calib.lidar_to_single_chip().apply(p_lidar), want, atol=1e-12)
    m = calib.lidar_to_single_chip().matrix
    np.testing.assert_allclose(m, np.linalg.inv(t_radar.matrix) @ t_lidar.matrix, atol=1e-12)
