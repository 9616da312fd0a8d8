"""The synthesized calibration table of a simulated unit corrects its hardware errors."""
import numpy as np
import pytest
import torch

from radarpc.sensors.radial import RADIAL_S, TINY, channel_errors, steering_vectors
from radarpc.sim.radial_calibration import make_calibration


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S])
@pytest.mark.parametrize("az,el", [(0.0, 0.0), (21.0, 5.0), (-47.0, -10.0)])
def test_calibrated_beamformer_peaks_at_source(cfg, az, el):
    calib = make_calibration(cfg)
    v = torch.as_tensor(steering_vectors(cfg, az, el)).to(torch.complex64)
    spec = (calib.dictionary() @ v).abs().reshape(calib.grid_shape)
    # independent: Signal[az, :, el] @ (H * v), the RADIal formula, evaluated with numpy
    ref = np.abs(np.einsum("avb,v->ab", calib.signal, calib.window * v.numpy()))
    np.testing.assert_allclose(spec.numpy(), ref, rtol=1e-4, atol=1e-3 * ref.max())
    ia, ie = np.unravel_index(np.argmax(ref), ref.shape)
    step_az = np.diff(calib.azimuth_deg[:2])[0]
    assert abs(calib.azimuth_deg[ia] - az) <= step_az / 2 + 1e-6
    assert calib.elevation_deg[ie] == pytest.approx(np.clip(el, *cfg.el_grid_deg[:2]), abs=(cfg.el_grid_deg[1] - cfg.el_grid_deg[0]) / (cfg.el_grid_deg[2] - 1) / 2 + 1e-6)


def test_hardware_errors_are_what_calibration_corrects():
    cfg = RADIAL_S
    err = channel_errors(cfg)
    assert err.shape == (192,) and not np.allclose(err, 1.0)
    ideal = steering_vectors(cfg, 10.0, 0.0, hardware=False)
    np.testing.assert_allclose(steering_vectors(cfg, 10.0, 0.0), ideal * err)
    # the calibration table equals the conjugate of the true (with errors) response
    calib = make_calibration(cfg)
    ia = int(np.argmin(np.abs(calib.azimuth_deg - 10.0)))
    ie = int(np.argmin(np.abs(calib.elevation_deg - 0.0)))
    np.testing.assert_allclose(calib.signal[ia, :, ie], np.conj(ideal * err).astype(np.complex64), rtol=1e-5, atol=1e-6)
