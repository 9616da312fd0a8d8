"""The calibration table of a simulated unit: a measurement of its true array response."""
import math

import numpy as np
import pytest
import torch

from radarpc.data.radial_format import load_calibration, save_calibration
from radarpc.dsp.pointcloud import SpectralPointCloud
from radarpc.sensors.radial import RADIAL, RADIAL_S, TINY, channel_errors, steering_vectors
from radarpc.sim.radial_calibration import calibration_error_bound, make_calibration, measure_array_response
from radarpc.sim.rd import Scatterers, synthesize_rd


def _truth(cfg):
    return steering_vectors(cfg, cfg.azimuth_table_deg[:, None], cfg.elevation_table_deg[None, :])


@pytest.mark.parametrize("cfg", [TINY, RADIAL], ids=lambda c: c.name)
def test_measured_table_is_within_its_bound_and_not_the_truth(cfg):
    m = measure_array_response(cfg)                                 # (n_az, n_el, V)
    truth = _truth(cfg)
    err = np.abs(m - truth)
    bound = calibration_error_bound(cfg)                             # (V,)
    assert m.shape == truth.shape and bound.shape == (cfg.n_virtual,)
    assert (err <= bound).all(), float((err / bound).max())
    # a measurement, not the truth: every entry off by more than rounding, the typical error about
    # the chamber noise (sigma = 0.01 at 40 dB) plus drift, and the bound not vacuous
    sigma = 10 ** (-cfg.cal_snr_db / 20)
    assert err.min() > 1e-9 and np.median(err) > sigma / 2
    assert err.max() > 0.1 * bound.max()
    assert np.array_equal(m, measure_array_response(cfg))           # seeded by the unit


def test_bound_grows_with_each_error_source():
    import dataclasses
    b0 = calibration_error_bound(TINY)
    for kw in ({"cal_snr_db": 30.0}, {"cal_positioner_deg": (0.2, 0.05)}, {"cal_drift": (0.5, 1.0)}):
        assert (calibration_error_bound(dataclasses.replace(TINY, **kw)) > b0).all(), kw
    # no error at all: the bound is the 5 sigma noise term of a 300 dB chamber only
    perfect = dataclasses.replace(TINY, cal_snr_db=300.0, cal_positioner_deg=(0.0, 0.0), cal_drift=(0.0, 0.0))
    np.testing.assert_allclose(calibration_error_bound(perfect), 5e-15)
    np.testing.assert_allclose(measure_array_response(perfect), _truth(perfect), rtol=0, atol=1e-13)


def test_table_is_the_normalised_conjugate_measurement():
    cfg = TINY
    m = measure_array_response(cfg)
    calib = make_calibration(cfg)
    want = np.conj(m / np.sqrt((np.abs(m) ** 2).mean(-1, keepdims=True))).transpose(0, 2, 1)
    np.testing.assert_allclose(calib.signal, want.astype(np.complex64), rtol=0, atol=1e-6)


def test_radial_table_has_the_real_size_and_layout(tmp_path):
    calib = make_calibration(RADIAL)
    assert calib.signal.shape == (751, 192, 11) and calib.signal.dtype == np.complex64
    assert calib.window.shape == (192,)
    np.testing.assert_allclose(calib.azimuth_deg, np.arange(-750, 751, 2) / 10.0, atol=1e-5)
    assert calib.elevation_deg.shape == (11,) and calib.elevation_deg[5] == 0.0    # rpl.py reads index 5
    assert make_calibration(RADIAL_S).signal.shape == (751, 192, 11)
    save_calibration(tmp_path / "calibration.npz", calib)
    back = load_calibration(tmp_path / "calibration.npz")
    assert np.array_equal(back.signal, calib.signal) and np.array_equal(back.elevation_deg, calib.elevation_deg)
    with np.load(tmp_path / "calibration.npz") as z:
        assert z["Signal"].shape == (751, 192, 11) and z["H"].shape == (1, 192)


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S], ids=lambda c: c.name)
@pytest.mark.parametrize("az,el", [(0.0, 0.0), (21.0, 5.0), (-47.0, -10.0)])
def test_calibrated_beamformer_peaks_at_source(cfg, az, el):
    calib = make_calibration(cfg)
    v = torch.as_tensor(steering_vectors(cfg, az, el)).to(torch.complex64)
    spec = (calib.dictionary() @ v).abs().reshape(calib.grid_shape)
    # independent: Signal[az, :, el] @ (H * v), the RADIal formula, evaluated with numpy
    ref = np.abs(np.einsum("avb,v->ab", calib.signal, calib.window * v.numpy()))
    np.testing.assert_allclose(spec.numpy(), ref, rtol=1e-4, atol=1e-3 * ref.max())
    ia, ie = np.unravel_index(np.argmax(ref), ref.shape)
    # within one grid step (an off-grid elevation moves the joint argmax along u_y = cos(el) sin(az));
    # + float32 rounding of the stored tables
    az_step = (cfg.az_grid_deg[1] - cfg.az_grid_deg[0]) / (cfg.az_grid_deg[2] - 1)
    el_step = (cfg.el_grid_deg[1] - cfg.el_grid_deg[0]) / (cfg.el_grid_deg[2] - 1)
    assert abs(calib.azimuth_deg[ia] - az) <= az_step + 1e-5
    assert abs(calib.elevation_deg[ie] - np.clip(el, *cfg.el_grid_deg[:2])) <= el_step + 1e-5


def test_true_response_is_not_the_geometric_one():
    cfg = RADIAL_S
    err = channel_errors(cfg)
    assert err.shape == (192,) and not np.allclose(err, 1.0)
    ideal = steering_vectors(cfg, 10.0, 0.0, hardware=False)
    true = steering_vectors(cfg, 10.0, 0.0)
    # coupling and pattern on top of the channel errors: not a per-channel factor of the geometry
    ratio = true / (ideal * err)
    assert np.ptp(np.abs(ratio)) > 0.05 and np.ptp(np.angle(ratio)) > 0.05


@pytest.fixture(scope="module")
def radial_s_point_cloud():
    """The point-cloud pipeline of radial-s with its measured table, tau = 10: one instance for the three
    targets, so that its beamformer tables (the factorised 751 x 11 dictionary) are built once."""
    return SpectralPointCloud(RADIAL_S, make_calibration(RADIAL_S), tau=10.0)


@pytest.mark.parametrize("az", [-40.1, 12.33, 33.07])
def test_point_target_is_recovered_with_the_measured_calibration(az, radial_s_point_cloud):
    # full receiver (IF filter, leakage, phase noise, thermal noise), true response in the cube,
    # the measured table in the point-cloud pipeline: the target's point within one azimuth grid
    # step (0.2 deg) of its true azimuth, elevation 0 on the grid
    cfg = RADIAL_S
    r_bin, d_bin = 40.3, 9
    v = float(cfg.velocity_of_bin(d_bin))
    t = lambda x: torch.tensor([float(x)])  # noqa: E731
    sc = Scatterers(t(r_bin * cfg.range_res_m), t(az), t(0.0), t(v), t(30.0))
    rd = synthesize_rd(cfg, [sc], generator=torch.Generator().manual_seed(5))
    c = radial_s_point_cloud(rd).frame(0)
    near = (c.range_bin - r_bin).abs() <= 1
    assert near.any()
    j = torch.nonzero(near).flatten()[c.amplitude[near].argmax()]
    assert int(c.doppler_full[j]) == d_bin
    step = (cfg.az_grid_deg[1] - cfg.az_grid_deg[0]) / (cfg.az_grid_deg[2] - 1)
    assert abs(float(c.azimuth_deg[j]) - az) <= step + 1e-5
    assert abs(float(c.elevation_deg[j])) <= 1e-5
    assert math.isfinite(float(c.snr[j])) and float(c.snr[j]) > 10.0
