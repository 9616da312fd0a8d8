"""Density of peak sets and the density controller (per frame, per dataset, on S(tau) and, with the
RD-neighbourhood enrichment, on S*(tau)) on simulated frames.

The point clouds here beamform with the exact beamformer: every mode gives the same points, and
the subspace one (what "auto" picks on most CPUs) factorises the dictionary anew in each
``SpectralPointCloud``, which costs more than these tests' frames."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp.density import (DENSITY_MODES, density_of_mask, max_density, neighbourhood_mask,
                                 neighbourhood_snr, tau_for_density)
from radarpc.dsp.pointcloud import SpectralPointCloud
from radarpc.sensors.radial import RADIAL_S, TINY
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.radial_writer import SimulatedRADIal
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
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=target, beamforming="exact")
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
    calib = make_calibration(cfg)
    spc = SpectralPointCloud(cfg, calib, density=target, density_mode="per-dataset", beamforming="exact")
    clouds = spc(rd)
    assert torch.unique(clouds.tau).numel() == 1
    assert abs(float(clouds.density.mean()) / target - 1) < 0.10
    # calibrate on a "training split", reuse the single tau as a fixed threshold
    tau = spc.calibrate_tau([rd[:2], rd[2:]])
    assert tau == pytest.approx(float(clouds.tau[0]))
    fixed = SpectralPointCloud(cfg, calib, tau=tau, beamforming="exact")(rd)
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
    dens = [SpectralPointCloud(cfg, calib, tau=t, beamforming="exact")(rd).density.numpy()
            for t in (0.5, 1.0, 1.585, 3.0, 10.0, 100.0)]
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


# ---- RD-neighbourhood enrichment: the target applies to S*(tau) (eq. 9) -------------------------
def _np_dilate(mask: np.ndarray, n: int) -> np.ndarray:
    """Union of the n x n neighbourhoods of the True cells over the last two axes, truncated at
    the borders (eq. 8), by shifted ORs: an independent numpy version of P*(tau)."""
    h = n // 2
    nr, w = mask.shape[-2:]
    out = np.zeros_like(mask)
    for dr in range(-h, h + 1):
        for dl in range(-h, h + 1):
            # cell (r, l) is covered by a peak at (r + dr, l + dl)
            out[..., max(0, -dr):nr - max(0, dr), max(0, -dl):w - max(0, dl)] |= \
                mask[..., max(0, dr):nr - max(0, -dr), max(0, dl):w - max(0, -dl)]
    return out


def _reachable_counts(snr: np.ndarray, n: int) -> np.ndarray:
    """Every |P*(tau)| a threshold can give for one frame's SNR map (Nr, W): brute force over all
    thresholds (each distinct SNR value, and below the minimum)."""
    u = np.unique(snr)
    masks = snr[None] > u[:, None, None]                                # (U, Nr, W)
    counts = _np_dilate(masks, n).reshape(len(u), -1).sum(1)
    return np.unique(np.append(counts, snr.size))


def _closest(reachable: np.ndarray, m: int) -> int:
    """The reachable count closest to m, the smaller one on a tie."""
    d = np.abs(reachable - m)
    return int(reachable[d == d.min()].min())


@pytest.fixture(scope="module")
def sim_frames():
    """Six realistic RADIAL_S frames (road scenes: vehicles, clutter, noise) and their CFAR SNR."""
    ds = SimulatedRADIal(RADIAL_S, 3, 2, seed=3, split="all")
    rd = torch.stack([ds[i][0] for i in range(len(ds))])                # (6, 128, 64, 16)
    snr = SpectralPointCloud(RADIAL_S, ds.calibration).detect(rd)[1].snr   # (6, 128, 16)
    return rd, ds.calibration, snr


@pytest.mark.parametrize("n", [3, 5])
def test_neighbourhood_mask_equals_numpy_dilation(n):
    g = torch.Generator().manual_seed(n)
    snr = torch.rand(3, TINY.n_range, TINY.slot_width, generator=g, dtype=torch.float64) * 4
    snr[0, 0, 0] = snr[1, -1, -1] = snr[2, 0, -1] = 100.0               # peaks on the corners
    for tau in (1.0, 3.9, 50.0):
        peaks = snr > tau
        ref = _np_dilate(peaks.numpy(), n)
        np.testing.assert_array_equal(neighbourhood_mask(peaks, n).numpy(), ref)
        # P*(tau) is the threshold of the max-filtered SNR: {D > tau}
        np.testing.assert_array_equal((neighbourhood_snr(snr, n) > tau).numpy(), ref)
    assert int(neighbourhood_mask(snr > 50.0, n).sum()) == 3 * (n // 2 + 1) ** 2   # truncated corners
    with pytest.raises(ValueError, match="real floating-point"):
        neighbourhood_snr(snr.to(torch.complex128), n)
    with pytest.raises(ValueError, match="bool mask"):
        neighbourhood_mask(snr, n)
    with pytest.raises(ValueError, match=r"\(B, Nr, W\)"):
        neighbourhood_mask(snr[0] > 1, n)


def test_enriched_controller_hand_worked_ties():
    cfg = TINY                                          # 64 x 8 consolidated cells, |S| = 2 |P| of 2048
    snr = torch.zeros(1, cfg.n_range, cfg.slot_width, dtype=torch.float64)
    snr[0, 0, 0] = 5.0                                  # corner peak: 2 x 2 truncated neighbourhood
    snr[0, 10, 4] = 3.0                                 # interior peak: 3 x 3
    # reachable |P*| = 0, 4, 4 + 9 = 13 and 512 (tau below 0); the closest wins, a tie the smaller
    for m, want in [(2, 0), (3, 4), (4, 4), (8, 4), (9, 13), (13, 13), (200, 13), (300, 512)]:
        target = m * cfg.n_tx / (cfg.n_range * cfg.n_doppler)
        for mode in DENSITY_MODES:
            tau = tau_for_density(snr, cfg, target, mode=mode, neighbourhood=3)
            got = int(neighbourhood_mask(snr > tau.reshape(-1, 1, 1), 3).sum())
            assert got == want, (m, mode, float(tau))
    # above the largest reachable density (every consolidated cell): a clear error, as without rdN
    with pytest.raises(ValueError, match="unreachable"):
        tau_for_density(snr, cfg, 0.6, neighbourhood=3)
    for bad in (1, 4, True, 3.0):
        with pytest.raises(ValueError, match="odd integer >= 3"):
            tau_for_density(snr, cfg, 0.1, neighbourhood=bad)


@pytest.mark.parametrize("n", [3, 5])
def test_enriched_per_frame_controller_hits_target(sim_frames, n):
    rd, calib, snr = sim_frames
    cfg, target = RADIAL_S, 0.2
    spc = SpectralPointCloud(cfg, calib, density=target, enrich=(f"rd{n}",), beamforming="exact")
    clouds = spc(rd)
    # the target applies to the encoded set S*(tau): within 10 % on every frame
    assert np.all(np.abs(clouds.density.numpy() / target - 1) < 0.10), clouds.density
    assert np.all(clouds.peak_density.numpy() < clouds.density.numpy())
    m = round(target * cfg.n_range * cfg.n_doppler / cfg.n_tx)
    for b in range(len(clouds)):
        c = clouds.frame(b)
        # the points are exactly the numpy dilation of {snr > tau}, and S = the non-neighbour points
        ref = _np_dilate(snr[b].numpy() > float(c.tau[0]), n)
        got = np.zeros_like(ref)
        got[c.range_bin.numpy(), c.doppler_bin.numpy()] = True
        np.testing.assert_array_equal(got, ref)
        assert int(ref.sum()) == c.num_points
        assert float(c.density[0]) == pytest.approx(cfg.n_tx * ref.sum() / (cfg.n_range * cfg.n_doppler))
        assert float(c.peak_density[0]) == pytest.approx(
            cfg.n_tx * int((~c.is_neighbour).sum()) / (cfg.n_range * cfg.n_doppler))
        # exact: no threshold gives a count closer to the target
        assert c.num_points == _closest(_reachable_counts(snr[b].numpy(), n), m)


@pytest.mark.parametrize("n", [3, 5])
def test_enriched_per_dataset_controller_hits_mean_target(sim_frames, n):
    rd, calib, snr = sim_frames
    cfg, target = RADIAL_S, 0.057
    spc = SpectralPointCloud(cfg, calib, density=target, density_mode="per-dataset", enrich=(f"rd{n}", "sector8"))
    clouds = spc(rd)
    assert torch.unique(clouds.tau).numel() == 1
    assert abs(float(clouds.density.mean()) / target - 1) < 0.10, clouds.density
    # pooled count against the pooled brute force
    m = round(target * len(rd) * cfg.n_range * cfg.n_doppler / cfg.n_tx)
    u = np.unique(snr.numpy())
    pooled = _np_dilate(snr.numpy()[None] > u[:, None, None, None], n).reshape(len(u), -1).sum(1)
    reachable = np.unique(np.append(pooled, snr.numel()))
    assert clouds.num_points == _closest(reachable, m)
    # calibrate on a "training split" (in two batches), reuse the single tau as a fixed threshold
    tau = spc.calibrate_tau([rd[:2], rd[2:]])
    assert tau == pytest.approx(float(clouds.tau[0]))
    fixed = SpectralPointCloud(cfg, calib, tau=tau, enrich=(f"rd{n}", "sector8"))(rd)
    torch.testing.assert_close(fixed.density, clouds.density)
    # without rdN the same target applies to S(tau): a lower tau, more CFAR peaks
    plain = SpectralPointCloud(cfg, calib, density=target, density_mode="per-dataset", beamforming="exact")(rd)
    assert float(plain.tau[0]) < tau and abs(float(plain.density.mean()) / target - 1) < 0.10


@pytest.mark.parametrize("n", [3, 5])
def test_enriched_density_monotone_in_tau(sim_frames, n):
    rd, calib, snr = sim_frames
    taus = (0.5, 1.0, 1.585, 3.0, 10.0, 100.0, 1e4)
    dens = np.stack([SpectralPointCloud(RADIAL_S, calib, tau=t, enrich=(f"rd{n}",), beamforming="exact")(rd[:2])
                     .density.numpy() for t in taus])                # (n_tau, 2)
    assert np.all(np.diff(dens, axis=0) <= 0) and dens[0].min() > dens[-1].max()
    # the same on a fine sweep through the independent dilation
    grid = np.quantile(snr.numpy(), np.linspace(0, 1, 200))
    counts = _np_dilate(snr.numpy()[None] > grid[:, None, None, None], n).reshape(len(grid), len(snr), -1).sum(2)
    assert np.all(np.diff(counts, axis=0) <= 0)
    # and the controller's tau falls as the target density rises
    t = [float(tau_for_density(snr, RADIAL_S, d, mode="per-dataset", neighbourhood=n)) for d in (0.02, 0.057, 0.2, 0.5)]
    assert np.all(np.diff(t) < 0)


def test_peak_density_without_enrichment_is_density(sim_frames):
    rd, calib, _ = sim_frames
    c = SpectralPointCloud(RADIAL_S, calib, density=0.057, enrich=("sector8",))(rd[:2])
    torch.testing.assert_close(c.peak_density, c.density)


# ---- the fast paths against direct references: borders, ties, tiny grids -------------------------
@pytest.mark.parametrize("n", [3, 5, 7])
@pytest.mark.parametrize("shape", [(2, 64, 8), (1, 3, 2), (2, 1, 5)])
def test_neighbourhood_maps_equal_max_pool(n, shape):
    import torch.nn.functional as F
    g = torch.Generator().manual_seed(n)
    snr = (torch.rand(shape, generator=g, dtype=torch.float64) * 4).floor()      # many ties
    ref = F.max_pool2d(snr.unsqueeze(1), n, stride=1, padding=n // 2).squeeze(1)   # -inf padding
    assert torch.equal(neighbourhood_snr(snr, n), ref)
    peaks = snr > 2
    ref_mask = F.max_pool2d(peaks.unsqueeze(1).float(), n, stride=1, padding=n // 2).squeeze(1) > 0
    got = neighbourhood_mask(peaks, n)
    assert got.dtype == torch.bool and torch.equal(got, ref_mask)
    if n // 2 < min(shape[1:]):
        np.testing.assert_array_equal(got.numpy(), _np_dilate(peaks.numpy(), n))
    snr[0, 0, 0] = float("nan")                                           # NaN spreads like max_pool's
    ref = F.max_pool2d(snr.unsqueeze(1), n, stride=1, padding=n // 2).squeeze(1)
    torch.testing.assert_close(neighbourhood_snr(snr, n), ref, rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("kind", ["random", "ties"])
def test_per_frame_tau_is_the_sorted_midpoint(kind):
    cfg = TINY
    g = torch.Generator().manual_seed(11)
    snr = torch.rand(3, cfg.n_range, cfg.slot_width, generator=g) * 10
    if kind == "ties":
        snr = snr.floor()
    for target in (1e-4, 0.01, 0.1, 0.3, 0.5):
        n = round(target * cfg.n_range * cfg.n_doppler / cfg.n_tx)
        tau = tau_for_density(snr, cfg, target)
        for b in range(3):
            s = torch.sort(snr[b].flatten(), descending=True).values
            if n == 0:
                want = s[0]                                                # nothing passes
            elif n >= s.numel():                                           # every cell passes
                want = 0.5 * s[-1] if s[-1] > 0 else torch.tensor(-1.0)
            else:
                hi, lo = s[n - 1], s[n]
                want = 0.5 * (hi + lo) if 0.5 * (hi + lo) < hi else lo
            assert tau[b].item() == want.item(), (target, b)
            count = int((snr[b] > tau[b]).sum())
            assert count == n or (kind == "ties" and count <= n)


@pytest.mark.parametrize("mode", DENSITY_MODES)
def test_enriched_controller_closest_count_with_ties(mode):
    # integer SNRs: D has large plateaus, so |P*| jumps; the count is still the closest reachable one
    cfg = TINY
    g = torch.Generator().manual_seed(4)
    snr = (torch.rand(2, cfg.n_range, cfg.slot_width, generator=g) ** 4 * 8).floor().double()
    for target in (0.005, 0.02, 0.1, 0.4):
        tau = tau_for_density(snr, cfg, target, mode=mode, neighbourhood=3)
        got = neighbourhood_mask(snr > tau.reshape(-1, 1, 1), 3)
        if mode == "per-frame":
            m = round(target * cfg.n_range * cfg.n_doppler / cfg.n_tx)
            for b in range(2):
                assert int(got[b].sum()) == _closest(_reachable_counts(snr[b].numpy(), 3), m)
        else:
            m = round(target * 2 * cfg.n_range * cfg.n_doppler / cfg.n_tx)
            u = np.unique(snr.numpy())
            pooled = _np_dilate(snr.numpy()[None] > u[:, None, None, None], 3).reshape(len(u), -1).sum(1)
            assert int(got.sum()) == _closest(np.unique(np.append(pooled, snr.numel())), m)


@pytest.mark.parametrize("neighbourhood", [None, 3])
def test_nan_snr_is_rejected(neighbourhood):
    snr = torch.ones(2, TINY.n_range, TINY.slot_width)
    snr[1, 5, 3] = float("nan")
    for mode in DENSITY_MODES:
        with pytest.raises(ValueError, match="without NaN"):
            tau_for_density(snr, TINY, 0.1, mode=mode, neighbourhood=neighbourhood)
