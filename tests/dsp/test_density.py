"""Density of peak sets and the density controller (per frame, per dataset) on simulated frames."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp.density import density_of_mask, max_density, tau_for_density
from radarpc.dsp.pointcloud import SpectralPointCloud
from radarpc.sensors.radial import RADIAL_S, TINY, make_calibration
from radarpc.sim.rd import Scatterers, synthesize_rd


def _frames(cfg, n, seed=0):
    """Simulated frames: a few random scatterers each, plus thermal noise."""
    g = torch.Generator().manual_seed(seed)
    scenes = []
    for _ in range(n):
        k = 6
        u = torch.rand(5, k, generator=g)
        scenes.append(Scatterers(range_m=(3 + u[0] * 0.8 * cfg.max_range_m),
                                 azimuth_deg=(u[1] - 0.5) * 100, elevation_deg=(u[2] - 0.5) * 4,
                                 velocity_mps=(u[3] - 0.5) * 1.8 * cfg.max_velocity_mps,
                                 rcs_m2=1 + 30 * u[4]))
    return synthesize_rd(cfg, scenes, noise=True, generator=g)


def test_density_of_mask_hand_worked():
    cfg = TINY                                                      # Nr*Nd = 2048, n_tx = 2, W = 8
    m = torch.zeros(2, cfg.n_range, cfg.slot_width, dtype=torch.bool)
    m[0, :3, 0] = True
    m[1, 10, :] = True
    np.testing.assert_allclose(density_of_mask(m, cfg).numpy(), [2 * 3 / 2048, 2 * 8 / 2048])
    full = torch.zeros(cfg.n_range, cfg.n_doppler, dtype=torch.bool)
    full[0, :5] = True
    assert float(density_of_mask(full, cfg)) == pytest.approx(5 / 2048)
    assert max_density(cfg) == 0.5 and max_density(RADIAL_S) == 0.75
    with pytest.raises(ValueError, match="consolidated"):
        density_of_mask(torch.zeros(64, 7, dtype=torch.bool), cfg)


@pytest.mark.parametrize("target", [0.007, 0.057, 0.3])
def test_per_frame_controller_hits_target(target):
    cfg = RADIAL_S
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=target)
    clouds = spc(_frames(cfg, 3))
    assert np.all(np.abs(clouds.density.numpy() / target - 1) < 0.10), clouds.density
    # the thresholds are real SNR thresholds: re-thresholding with them gives the same peak set
    _, res, mask = spc.detect(_frames(cfg, 3))
    tau = tau_for_density(res.snr, cfg, target)
    torch.testing.assert_close(mask, res.snr > tau[:, None, None])


def test_per_dataset_controller_hits_mean_target():
    cfg = RADIAL_S
    target = 0.057
    rd = _frames(cfg, 4, seed=1)
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=target, density_mode="per-dataset")
    clouds = spc(rd)
    assert torch.unique(clouds.tau).numel() == 1
    assert abs(float(clouds.density.mean()) / target - 1) < 0.10
    # calibrate on a "training split", reuse the single tau as a fixed threshold
    tau = spc.calibrate_tau([rd[:2], rd[2:]])
    assert tau == pytest.approx(float(clouds.tau[0]))
    fixed = SpectralPointCloud(cfg, make_calibration(cfg), tau=tau)(rd)
    torch.testing.assert_close(fixed.density, clouds.density)


def test_controller_counts_exactly_on_random_snr():
    cfg = TINY
    g = torch.Generator().manual_seed(5)
    snr = torch.rand(4, cfg.n_range, cfg.slot_width, generator=g, dtype=torch.float64) * 10
    target = 0.1
    n = round(target * cfg.n_range * cfg.n_doppler / cfg.n_tx)
    tau = tau_for_density(snr, cfg, target)
    assert tau.shape == (4,)
    assert ((snr > tau[:, None, None]).flatten(1).sum(1) == n).all()
    tau_d = tau_for_density(snr, cfg, target, mode="per-dataset")
    m = round(target * 4 * cfg.n_range * cfg.n_doppler / cfg.n_tx)   # pooled count (410, not 4 * 102)
    assert tau_d.ndim == 0 and int((snr > tau_d).sum()) == m
    # the pooled threshold is the value an independent sort gives
    s = np.sort(snr.numpy().ravel())[::-1]
    assert float(tau_d) == pytest.approx(0.5 * (s[m - 1] + s[m]))


def test_density_decreases_as_tau_grows():
    cfg = RADIAL_S
    rd = _frames(cfg, 2, seed=2)
    calib = make_calibration(cfg)
    dens = [SpectralPointCloud(cfg, calib, tau=t)(rd).density.numpy() for t in (0.5, 1.0, 1.585, 3.0, 10.0, 100.0)]
    dens = np.stack(dens)                                           # (n_tau, B)
    assert np.all(np.diff(dens, axis=0) <= 0) and dens[0].min() > dens[-1].max()


@pytest.mark.parametrize("target,match", [(0.0, r"\(0, 1\]"), (1.2, r"\(0, 1\]"), (-0.5, r"\(0, 1\]"),
                                          (0.6, "unreachable"), (True, "number")])
def test_bad_targets(target, match):
    snr = torch.ones(1, TINY.n_range, TINY.slot_width)
    with pytest.raises(ValueError, match=match):
        tau_for_density(snr, TINY, target)


def test_bad_mode_and_shape():
    with pytest.raises(ValueError, match="mode"):
        tau_for_density(torch.ones(1, 64, 8), TINY, 0.1, mode="per-split")
    with pytest.raises(ValueError, match=r"\(B, 64, 8\)"):
        tau_for_density(torch.ones(1, 64, 9), TINY, 0.1)
