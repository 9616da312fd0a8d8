"""Spectral point clouds: isolated simulated targets, enrichments against direct per-point numpy,
batching, bad input."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from radarpc.dsp.beamform import dictionary_tables, stack_real
from radarpc.dsp.pointcloud import SpectralPointCloud, SpectralPointCloudConfig
from radarpc.points import PointCloudBatch, offset2batch
from radarpc.sensors.radial import RADIAL_S, TINY
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.rd import Scatterers, synthesize_rd

# (range in bins, off-grid; true Doppler bin; azimuth deg) of isolated targets per sensor
TARGETS = {
    "tiny": [(12.3, 3, -30.0), (30.3, 17, 0.0), (48.3, 26, 24.0)],
    "radial-s": [(15.3, 2, -40.3), (40.3, 21, 0.0), (70.3, 38, 12.6), (100.3, 55, 33.0)],
}


def _scene(cfg, targets, rcs=30.0):
    half = cfg.n_doppler // 2
    r = torch.tensor([t[0] * cfg.range_res_m for t in targets])
    v = torch.tensor([float(((t[1] + half) % cfg.n_doppler - half) * cfg.velocity_res_mps) for t in targets])
    az = torch.tensor([t[2] for t in targets])
    n = len(targets)
    rcs_t = torch.as_tensor(rcs, dtype=torch.float32).expand(n).clone()
    return Scatterers(r, az, torch.zeros(n), v, rcs_t)


def _half_resolution_deg(cfg, az_deg):
    h = cfg.virtual_positions[:, 0]
    n_h = h.max() - h.min() + 1                        # horizontal aperture in half wavelengths
    return 0.5 * math.degrees(2.0 / n_h) / math.cos(math.radians(az_deg))


@pytest.mark.parametrize("beamforming", ["exact", "screened"])
@pytest.mark.parametrize("cfg", [TINY, RADIAL_S], ids=lambda c: c.name)
def test_isolated_targets_are_recovered(cfg, beamforming):
    g = torch.Generator().manual_seed(0)
    targets = TARGETS[cfg.name]
    rd = synthesize_rd(cfg, [_scene(cfg, targets)] * 2, noise=True, generator=g)
    calib = make_calibration(cfg)
    spc = SpectralPointCloud(cfg, calib, tau=10.0, beamforming=beamforming)
    el_grid = np.unique(np.asarray(calib.elevation_deg, dtype=np.float64))
    half_el_step = 0.5 * float(np.diff(el_grid).min())           # targets are at elevation 0
    az_grid = np.asarray(calib.azimuth_deg, dtype=np.float64)
    clouds = spc(rd)
    assert len(clouds) == 2
    for b in range(2):
        c = clouds.frame(b)
        for rbin, d, az in targets:
            near = (c.range_bin - rbin).abs() <= 3
            assert near.any(), f"target at range bin {rbin} not detected"
            j = torch.nonzero(near).flatten()[c.amplitude[near].argmax()]
            assert abs(int(c.range_bin[j]) - rbin) <= 0.5
            assert int(c.doppler_bin[j]) == d % cfg.slot_width
            assert int(c.doppler_full[j]) == d
            assert abs(float(c.azimuth_deg[j]) - az) <= _half_resolution_deg(cfg, az)
            if np.isclose(az_grid, az).any():
                # on-grid azimuth: elevation 0 within half an elevation grid step (an off-grid
                # azimuth, 12.6 deg on RADIAL_S, couples into the joint (az, el) argmax: -5 deg)
                assert abs(float(c.elevation_deg[j])) <= half_el_step
            assert not bool(c.is_neighbour[j])
            assert float(c.snr[j]) > 10.0
            assert float(c.velocity_mps[j]) == pytest.approx(float(cfg.velocity_of_bin(d)), rel=1e-5, abs=1e-6)
            assert float(c.range_m[j]) == pytest.approx(int(c.range_bin[j]) * cfg.range_res_m, rel=1e-6)


def test_amplitude_tracks_target_power():
    cfg = RADIAL_S
    spc = SpectralPointCloud(cfg, make_calibration(cfg), tau=10.0)
    targets = TARGETS[cfg.name][:1]
    amps = []
    for rcs in (1.0, 4.0, 16.0, 64.0):
        c = spc(synthesize_rd(cfg, _scene(cfg, targets, rcs), noise=False))
        j = c.amplitude.argmax()
        assert int(c.range_bin[j]) == 15 and int(c.doppler_full[j]) == 2
        amps.append(float(c.amplitude[j]))
    # amplitude of the echo ~ sqrt(rcs): Ae doubles when the rcs is multiplied by 4
    np.testing.assert_allclose(np.array(amps[1:]) / np.array(amps[:-1]), 2.0, rtol=1e-4)


# ---- direct per-point reference (numpy, loops) --------------------------------------------------
def _direct_points(rd: np.ndarray, cfg, calib, peaks: np.ndarray, n: int | None, sectors, patch):
    """Independent evaluation of eqs. 4-10 for every kept cell of one frame."""
    w = cfg.slot_width
    a = np.abs(rd.astype(np.complex128)).sum(-1)                              # (Nr, Nd)
    g = cfg.n_empty_slots

    def tx0(r, l):                  # RADIal's rule: the n_empty_slots-slot gap of least mean follows Tx 0
        x = [a[r, l + s * w] for s in range(cfg.n_slots)]
        means = [np.mean([x[(s + 1 + k) % cfg.n_slots] for k in range(g)]) for s in range(cfg.n_slots)]
        return int(np.argmin(means)) * w + l

    # seed eq. 1: envelope = sum over the n_tx replica bins of each consolidated cell
    e = np.array([[sum(a[r, (tx0(r, l) + off) % cfg.n_doppler] for off in cfg.doppler_offsets)
                   for l in range(w)] for r in range(cfg.n_range)])
    kept = set(zip(*np.nonzero(peaks)))
    if n is not None:
        h = n // 2
        for (r, l) in list(kept):
            for dr, dl in itertools.product(range(-h, h + 1), repeat=2):
                if 0 <= r + dr < cfg.n_range and 0 <= l + dl < w:
                    kept.add((r + dr, l + dl))
    bmat = calib.dictionary().numpy().astype(np.complex128)                 # (n_az * n_el, n_virtual)
    n_az, n_el = calib.grid_shape
    out = {}
    for (r, l) in sorted(kept):
        d0 = tx0(r, l)
        v = np.concatenate([rd[r, (d0 + off) % cfg.n_doppler, :] for off in cfg.doppler_offsets])
        spec = np.abs(bmat @ v)
        k = int(np.argmax(spec))
        rec = dict(d0=d0, az=float(calib.azimuth_deg[k // n_el]), el=float(calib.elevation_deg[k % n_el]),
                   amp=spec[k], neighbour=not peaks[r, l])
        if sectors is not None:
            grid = spec.reshape(n_az, n_el)
            na, ne = sectors
            rec["sector"] = [grid[(u * n_az) // na: -(-((u + 1) * n_az) // na),
                                  (q * n_el) // ne: -(-((q + 1) * n_el) // ne)].max()
                             for u in range(na) for q in range(ne)]
        if patch is not None:
            h = patch // 2
            rec["patch"] = [e[r + dr, l + dl] if 0 <= r + dr < cfg.n_range and 0 <= l + dl < w else 0.0
                            for dr in range(-h, h + 1) for dl in range(-h, h + 1)]
        out[(r, l)] = rec
    return out


@pytest.mark.parametrize("enrich,n,sectors,patch", [
    ((), None, None, None),
    (("rd3", "sector8x2"), 3, (8, 2), 3),
    (("rd5", "sector7", "patch3"), 5, (7, 1), 3),
])
def test_points_and_enrichments_match_direct_computation(enrich, n, sectors, patch):
    cfg = TINY
    calib = make_calibration(cfg)
    g = torch.Generator().manual_seed(1)
    rd = synthesize_rd(cfg, [_scene(cfg, TARGETS["tiny"]), _scene(cfg, TARGETS["tiny"][:1], 3.0)],
                       noise=True, generator=g)
    spc = SpectralPointCloud(cfg, calib, tau=4.0, enrich=enrich)
    clouds = spc(rd)
    _, _, mask = spc.detect(rd)
    for b in range(2):
        c = clouds.frame(b)
        ref = _direct_points(rd[b].numpy(), cfg, calib, mask[b].numpy(), n, sectors, patch)
        got = list(zip(c.range_bin.tolist(), c.doppler_bin.tolist()))
        assert got == sorted(ref), "kept cells differ from P (or P*) built by direct loops"
        assert (c.is_neighbour.sum() > 0) == (n is not None)
        for j, key in enumerate(got):
            rr = ref[key]
            assert int(c.doppler_full[j]) == rr["d0"]
            assert float(c.azimuth_deg[j]) == rr["az"] and float(c.elevation_deg[j]) == rr["el"]
            assert float(c.amplitude[j]) == pytest.approx(rr["amp"], rel=1e-4)
            assert bool(c.is_neighbour[j]) == rr["neighbour"]
            if sectors is not None:
                np.testing.assert_allclose(c.sector[j].numpy(), rr["sector"], rtol=1e-4)
            if patch is not None:
                np.testing.assert_allclose(c.rd_patch[j].numpy(), rr["patch"], rtol=1e-5, atol=1e-6)
        if sectors is None:
            assert c.sector is None
        else:
            assert c.sector.shape == (c.num_points, sectors[0] * sectors[1])
        if patch is None:
            assert c.rd_patch is None
        else:
            assert c.rd_patch.shape == (c.num_points, patch * patch)
        # density on S (or S*): n_tx full-grid cells per kept consolidated cell
        assert float(clouds.density[b]) == pytest.approx(cfg.n_tx * len(ref) / (cfg.n_range * cfg.n_doppler))


def test_cartesian_coordinates():
    cfg = RADIAL_S
    rd = synthesize_rd(cfg, _scene(cfg, TARGETS[cfg.name]), noise=True, generator=torch.Generator().manual_seed(2))
    c = SpectralPointCloud(cfg, make_calibration(cfg), density=0.05)(rd)
    a = np.deg2rad(c.azimuth_deg.double().numpy())
    e = np.deg2rad(c.elevation_deg.double().numpy())
    r = c.range_m.double().numpy()
    np.testing.assert_allclose(c.x.numpy(), r * np.cos(e) * np.cos(a), atol=1e-4)
    np.testing.assert_allclose(c.y.numpy(), r * np.cos(e) * np.sin(a), atol=1e-4)
    np.testing.assert_allclose(c.z.numpy(), r * np.sin(e), atol=1e-4)
    for name in ("range_m", "azimuth_deg", "elevation_deg", "velocity_mps", "amplitude", "snr", "x", "y", "z"):
        assert getattr(c, name).dtype == torch.float32


def test_batch_equals_frames_and_helpers():
    cfg = TINY
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=0.1, enrich="rd3,sector4")
    g = torch.Generator().manual_seed(3)
    rd = torch.randn((3, *cfg.rd_shape), dtype=torch.complex64, generator=g)
    batch = spc(rd)
    assert len(batch) == 3 and batch.offset[-1] == batch.num_points
    np.testing.assert_array_equal(offset2batch(batch.offset).numpy(),
                                  np.repeat(np.arange(3), np.diff(batch.offset.numpy(), prepend=0)))
    for b in range(3):
        single = spc(rd[b])
        part = batch.frame(b)
        assert isinstance(part, PointCloudBatch) and len(part) == 1
        for name in PointCloudBatch._PER_POINT + ("tau", "density", "peak_density", "offset"):
            torch.testing.assert_close(getattr(single, name), getattr(part, name))
    moved = batch.to("cpu")
    torch.testing.assert_close(moved.sector, batch.sector)
    with pytest.raises(IndexError):
        batch.frame(3)


def test_empty_detections_give_valid_empty_cloud():
    cfg = TINY
    spc = SpectralPointCloud(cfg, make_calibration(cfg), tau=1e12, enrich=("rd3", "sector8"))
    c = spc(torch.randn((2, *cfg.rd_shape), dtype=torch.complex64))
    assert c.num_points == 0 and c.offset.tolist() == [0, 0]
    assert c.sector.shape == (0, 8) and c.rd_patch.shape == (0, 9)
    assert c.density.tolist() == [0.0, 0.0] and c.frame(1).num_points == 0
    assert c.peak_density.tolist() == [0.0, 0.0]


def test_complex128_input_gives_same_points():
    cfg = TINY
    spc = SpectralPointCloud(cfg, make_calibration(cfg), tau=3.0)
    rd = synthesize_rd(cfg, _scene(cfg, TARGETS["tiny"]), noise=True, generator=torch.Generator().manual_seed(4))
    a, b = spc(rd), spc(rd.to(torch.complex128))
    assert torch.equal(a.range_bin, b.range_bin) and torch.equal(a.doppler_full, b.doppler_full)
    torch.testing.assert_close(a.amplitude, b.amplitude, rtol=1e-4, atol=0)


def test_config_parsing():
    c = SpectralPointCloudConfig(enrich=("rd5", "sector32x1"))
    assert c.neighbourhood == 5 and c.patch == 5 and c.sectors == (32, 1)
    c = SpectralPointCloudConfig(density=0.057, enrich=("sector32",))
    assert c.tau is None and c.sectors == (32, 1) and c.neighbourhood is None and c.patch is None
    assert c.to_dict()["enrich"] == ["sector32"]
    c = SpectralPointCloudConfig(enrich="rd3, sector32", window=[11, 7], guard=[5, 3])
    assert c.enrich == ("rd3", "sector32") and c.window == (11, 7) and c.guard == (5, 3)


@pytest.mark.parametrize("kwargs,match", [
    (dict(enrich=("foo",)), "unknown enrichment"),
    (dict(enrich=("rd4",)), "odd"),
    (dict(enrich=("rd3", "rd5")), "once"),
    (dict(density=0.0), r"\(0, 1\]"),
    (dict(density=1.5), r"\(0, 1\]"),
    (dict(density=-0.1), r"\(0, 1\]"),
    (dict(density=0.9), "unreachable"),
    (dict(tau=0.0), "tau"),
    (dict(tau=float("nan")), "tau"),
    (dict(window=(8, 9)), "odd"),
    (dict(window=(9, 9, 9), guard=(3, 3, 3)), "2-D"),
    (dict(density=0.05, density_mode="per-epoch"), "density_mode"),
    (dict(enrich=("sector99",)), "exceeds"),
    (dict(beamforming="fp8"), "beamforming"),
])
def test_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SpectralPointCloud(TINY, make_calibration(TINY), **kwargs)


def test_bad_cubes():
    spc = SpectralPointCloud(TINY, make_calibration(TINY))
    with pytest.raises(ValueError, match=r"expected|\(B, 64, 32, 4\)"):
        spc(torch.zeros((64, 32, 5), dtype=torch.complex64))
    with pytest.raises(ValueError, match="complex"):
        spc(torch.zeros(TINY.rd_shape))
    rd = torch.zeros((2, *TINY.rd_shape), dtype=torch.complex64)
    rd[1, 0, 0, 0] = complex(float("nan"), 0)
    with pytest.raises(ValueError, match="NaN"):
        spc(rd)
    with pytest.raises(ValueError, match=r"rd is an empty batch \(shape \(0, 64, 32, 4\)\)"):
        spc(torch.zeros((0, *TINY.rd_shape), dtype=torch.complex64))
    with pytest.raises(ValueError, match="virtual channels"):
        SpectralPointCloud(RADIAL_S, make_calibration(TINY))


def test_angle_spectrum_and_real_gemm_form():
    from radarpc.dsp.beamform import angle_spectrum, beamform_peaks
    cfg = TINY
    calib = make_calibration(cfg)
    rng = np.random.default_rng(6)
    v = (rng.standard_normal((5, cfg.n_virtual)) + 1j * rng.standard_normal((5, cfg.n_virtual))).astype(np.complex64)
    b = calib.dictionary()
    ref = np.abs(b.numpy().astype(np.complex128) @ v.astype(np.complex128).T).T   # (5, n_dir)
    np.testing.assert_allclose(angle_spectrum(torch.from_numpy(v), b).numpy(), ref, rtol=1e-4)
    bt = b.transpose(0, 1).contiguous()
    w = stack_real(bt)
    x = torch.view_as_real(torch.from_numpy(v)).reshape(5, -1)
    y = (x.double() @ w.double()).numpy()
    k = bt.shape[1]
    np.testing.assert_allclose(np.hypot(y[:, :k], y[:, k:]), ref, rtol=1e-5)
    res = beamform_peaks(torch.from_numpy(v), bt, calib.grid_shape)
    np.testing.assert_array_equal(res.index.numpy(), ref.argmax(1))
    np.testing.assert_allclose(res.amplitude.numpy(), ref.max(1), rtol=1e-5)


def test_envelope_option_selects_the_cfar_input():
    cfg = TINY
    calib = make_calibration(cfg)
    rd = synthesize_rd(cfg, [_scene(cfg, TARGETS["tiny"])], noise=True, generator=torch.Generator().manual_seed(4))
    a = np.abs(rd[0].numpy().astype(np.complex128)).sum(-1)                  # (Nr, Nd)
    all_slots = a.reshape(cfg.n_range, cfg.n_slots, cfg.slot_width).sum(1)  # RADIal rpl.py
    e_all, _, _ = SpectralPointCloud(cfg, calib, envelope="all-slots").detect(rd)
    e_rep, _, _ = SpectralPointCloud(cfg, calib).detect(rd)
    np.testing.assert_allclose(e_all[0].numpy(), all_slots, rtol=1e-5)
    # replicas: the all-slot sum minus the (noise-only) empty slots of each cell's DDMA hypothesis
    assert bool((e_rep < e_all).all())
    c = SpectralPointCloud(cfg, calib, tau=10.0, envelope="all-slots", window=(19, 19), guard=(7, 7)).config
    assert c.envelope == "all-slots" and c.to_dict()["envelope"] == "all-slots" and c.window == (19, 19)
    with pytest.raises(ValueError, match="envelope must be one of"):
        SpectralPointCloudConfig(envelope="rpl")


# ---- opt-in bfloat16 beamforming with exact re-ranking ------------------------------------------
def _random_scene(cfg, n, g):
    r = (torch.rand(n, generator=g) * 0.8 + 0.1) * cfg.n_range * cfg.range_res_m
    az = torch.rand(n, generator=g) * 100.0 - 50.0
    el = torch.rand(n, generator=g) * 10.0 - 5.0
    half = cfg.n_doppler // 2
    v = (torch.randint(0, cfg.n_doppler, (n,), generator=g) - half).to(torch.float32) * cfg.velocity_res_mps
    rcs = torch.rand(n, generator=g) * 20.0 + 1.0
    return Scatterers(r, az, el, v, rcs)


def test_screened_beamforming_gives_the_exact_points(selection):
    cfg = RADIAL_S
    g = torch.Generator().manual_seed(7)
    # two frames at density 0.25: a few hundred points (the screen's bfloat16 GEMM takes milliseconds a
    # point on CPUs without native bfloat16)
    rd = synthesize_rd(cfg, [_random_scene(cfg, 40, g) for _ in range(2)], noise=True, generator=g)
    calib = make_calibration(cfg)
    exact = SpectralPointCloud(cfg, calib, density=0.25, beamforming="exact")(rd)
    fast = SpectralPointCloud(cfg, calib, density=0.25, beamforming="screened")(rd)
    assert exact.num_points > 250
    for name in ("offset", "range_bin", "doppler_bin", "doppler_full", "snr", "azimuth_deg", "elevation_deg"):
        assert torch.equal(getattr(exact, name), getattr(fast, name)), name
    torch.testing.assert_close(fast.amplitude, exact.amplitude, rtol=2e-6, atol=0)
    # sector descriptors need the whole spectrum: every mode runs the exact beamformer for them
    kw = dict(density=0.2, enrich=("sector16",))
    a = SpectralPointCloud(cfg, calib, beamforming="exact", **kw)(rd)
    for mode in ("screened", "auto"):
        b = SpectralPointCloud(cfg, calib, beamforming=mode, **kw)(rd)
        assert torch.equal(a.sector, b.sector) and torch.equal(a.azimuth_deg, b.azimuth_deg)


def _bf16_screen(v, bt):
    """|s^| of the screen, computed independently: bf16-rounded inputs, float64 products, bf16 output."""
    x = torch.view_as_real(v).reshape(v.shape[0], -1).to(torch.bfloat16).double()
    w = stack_real(bt).to(torch.bfloat16).double()
    y = (x @ w).to(torch.bfloat16).double()
    k = bt.shape[1]
    return torch.hypot(y[:, :k], y[:, k:])


def test_screen_error_bound_holds_and_screened_is_the_exact_argmax(selection):
    from radarpc.dsp.accel.screened import beamform_peaks_screened, screen_bound
    from radarpc.dsp.beamform import dictionary_tables
    cfg = TINY
    calib = make_calibration(cfg)
    bt = calib.dictionary().transpose(0, 1).contiguous()                # (n_virtual, K)
    g = torch.Generator().manual_seed(3)
    n = bt.shape[0]
    noise = torch.randn(200, n, dtype=torch.complex64, generator=g)
    # strong single targets (steering rows of the dictionary) plus noise at several SNRs, and a
    # huge dynamic range across snapshots
    k_true = torch.randint(0, bt.shape[1], (200,), generator=g)
    gain = 10.0 ** torch.linspace(-3, 6, 200)
    targets = bt.transpose(0, 1)[k_true].conj() * gain[:, None].to(torch.complex64) + noise
    v = torch.cat([noise, targets])
    exact = np.abs(v.numpy().astype(np.complex128) @ bt.numpy().astype(np.complex128))   # (P, K) float64
    tables = dictionary_tables(bt, calib.grid_shape)
    alpha, beta = screen_bound(v, tables.row_norm_max)
    screen = _bf16_screen(v, bt).numpy()
    err = np.abs(screen - exact)
    bound = alpha * screen + beta.double().numpy()[:, None]
    assert (err <= bound).all(), f"bound violated by {float((err - bound).max())}"
    assert float((err / bound).max()) > 0.01          # the bound is not vacuous
    # the bound also holds for this machine's own bfloat16 GEMM (the call the screen makes)
    x16 = torch.view_as_real(v).reshape(v.shape[0], -1).to(torch.bfloat16)
    y = torch.mm(x16, stack_real(bt).to(torch.bfloat16)).double()
    k = bt.shape[1]
    err_gemm = np.abs(torch.hypot(y[:, :k], y[:, k:]).numpy() - exact)
    assert (err_gemm <= alpha * torch.hypot(y[:, :k], y[:, k:]).numpy() + beta.double().numpy()[:, None]).all()
    res = beamform_peaks_screened(v, tables, calib.grid_shape)
    picked = exact[np.arange(len(v)), res.index.numpy()]
    np.testing.assert_allclose(picked, exact.max(1), rtol=1e-6)        # the exact maximum (up to fp32 ties)
    np.testing.assert_allclose(res.amplitude.numpy(), exact.max(1), rtol=1e-5)
    assert (res.index.numpy() == exact.argmax(1)).mean() > 0.99


def test_screened_falls_back_to_the_whole_spectrum_for_flat_spectra(selection):
    from radarpc.dsp.accel.screened import beamform_peaks_screened
    from radarpc.dsp.beamform import beamform_peaks
    cfg = TINY
    calib = make_calibration(cfg)
    bt = calib.dictionary().transpose(0, 1).contiguous()
    g = torch.Generator().manual_seed(5)
    v = torch.randn(40, bt.shape[0], dtype=torch.complex64, generator=g)
    v[::7] = 0                                            # flat (all-zero) spectra: every direction a candidate
    ref = beamform_peaks(v, bt, calib.grid_shape)
    for cap in (1, 2, 16):                                # cap 1: most snapshots take the fallback
        res = beamform_peaks_screened(v, bt, calib.grid_shape, max_candidates=cap)
        assert torch.equal(res.index, ref.index), cap
        torch.testing.assert_close(res.amplitude, ref.amplitude, rtol=2e-6, atol=0)
    assert bool((res.amplitude[::7] == 0).all()) and bool((res.index[::7] == ref.index[::7]).all())
    # a non-finite snapshot leaves no candidate: it takes the exact path too, as do empty inputs
    w = v.clone()
    w[3, 5] = complex(float("nan"), 0.0)
    w[4, 0] = complex(float("inf"), 0.0)
    ref = beamform_peaks(w, bt, calib.grid_shape)
    res = beamform_peaks_screened(w, bt, calib.grid_shape)
    assert torch.equal(res.index, ref.index) and 0 <= int(res.index.min()) and int(res.index.max()) < bt.shape[1]
    assert torch.equal(res.amplitude.isnan(), ref.amplitude.isnan()) and bool(res.amplitude[3].isnan())
    empty = beamform_peaks_screened(v[:0], bt, calib.grid_shape)
    assert empty.index.shape == (0,) and empty.amplitude.shape == (0,)
    with pytest.raises(ValueError, match="max_candidates"):
        beamform_peaks_screened(v, bt, calib.grid_shape, max_candidates=0)
    with pytest.raises(ValueError, match="complex64"):
        beamform_peaks_screened(v.to(torch.complex128), bt.to(torch.complex128), calib.grid_shape)


def test_auto_beamforming_resolves_by_measurement_and_sectors(monkeypatch):
    from radarpc.dsp.accel import screened
    from radarpc.dsp.beamform_modes import resolve_beamforming
    cpu = torch.device("cpu")
    assert resolve_beamforming("exact", cpu, None) == "exact"
    assert resolve_beamforming("screened", cpu, None) == "screened"
    assert resolve_beamforming("subspace", cpu, None) == "subspace"
    assert resolve_beamforming("screened", cpu, (32, 1)) == "exact"
    assert resolve_beamforming("auto", cpu, None) == "exact"                  # nothing to measure on
    assert resolve_beamforming("auto", cpu, (8, 1)) == "exact"
    with pytest.raises(ValueError, match="beamforming must be one of"):
        resolve_beamforming("bf16", cpu, None)
    # "auto" runs what the injected measurement found fastest, measured once per key
    calls = []
    tables = dictionary_tables(make_calibration(TINY).dictionary().transpose(0, 1), make_calibration(TINY).grid_shape)
    monkeypatch.setattr(screened, "_choices", {})
    monkeypatch.setattr(screened, "measure_beamformers",
                        lambda t, d: calls.append(d) or {"exact": 3.0, "subspace": 1.0, "screened": 2.0})
    from radarpc.dsp import accel as _accel
    if _accel.enabled():
        assert resolve_beamforming("auto", cpu, None, tables) == "subspace"
        assert resolve_beamforming("auto", cpu, None, tables) == "subspace" and len(calls) == 1
    else:                  # RADARPC_NO_NATIVE=1: the switch wins, nothing is measured
        assert resolve_beamforming("auto", cpu, None, tables) == "exact" and not calls
    # "auto" is the default everywhere a user can leave it out
    import inspect

    from radarpc.pipelines.pointclouds import ConvertSettings, convert_dataset
    calib = make_calibration(TINY)
    assert SpectralPointCloud(TINY, calib).config.beamforming == "auto"
    assert SpectralPointCloudConfig().beamforming == "auto"
    assert ConvertSettings(tau=1.585).beamforming == "auto"
    assert "settings" in inspect.signature(convert_dataset).parameters
    # the one switch turns the accelerated paths off: "auto" is then the core's exact beamformer
    from radarpc.dsp import accel
    with accel.disabled():
        assert resolve_beamforming("auto", cpu, None, tables) == "exact"
        assert resolve_beamforming("screened", cpu, None) == "screened"     # asked for explicitly


@pytest.mark.parametrize("grid,sectors", [((181, 5), (32, 1)), ((181, 5), (7, 2)), ((13, 1), (13, 1)),
                                          ((13, 3), (5, 1)), ((40, 2), (1, 1)), ((9, 4), (4, 3))])
def test_elevation_major_sector_pooling_equals_adaptive_pooling(grid, sectors):
    from radarpc.dsp.beamform import _sector_pool_elevation_major, column_to_direction, sector_pool
    n_az, n_el = grid
    g = torch.Generator().manual_seed(n_az * 10 + n_el)
    spec = torch.rand(11, n_az * n_el, generator=g)                   # direction-major (k = az n_el + el)
    em = spec[:, column_to_direction(torch.arange(n_az * n_el), grid)]   # elevation-major columns
    assert torch.equal(_sector_pool_elevation_major(em, grid, sectors), sector_pool(spec, grid, sectors))
    # and against a hand computation of the sector bounds for the 181 -> 32 case
    if grid == (181, 5) and sectors == (32, 1):
        best = spec.reshape(11, 181, 5).amax(-1)
        ref = torch.stack([best[:, (u * 181) // 32: -(-((u + 1) * 181) // 32)].amax(1) for u in range(32)], 1)
        assert torch.equal(sector_pool(spec, grid, sectors), ref)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (requirement: CPU and CUDA agree)")
@pytest.mark.parametrize("beamforming,enrich", [("exact", ("rd3", "sector16")), ("screened", ())])
def test_cuda_gives_the_cpu_points(beamforming, enrich):
    cfg = RADIAL_S
    g = torch.Generator().manual_seed(11)
    rd = synthesize_rd(cfg, [_random_scene(cfg, 30, g) for _ in range(3)], noise=True, generator=g)
    calib = make_calibration(cfg)
    kw = dict(density=0.1, enrich=enrich, beamforming=beamforming)
    cpu = SpectralPointCloud(cfg, calib, **kw)(rd)
    gpu = SpectralPointCloud(cfg, calib, **kw).to("cuda")(rd.to("cuda")).to("cpu")
    # detection (sums of float32 values in another order) may flip a cell exactly at tau: require
    # nearly all cells to be shared, and compare every shared cell's point
    def by_cell(c):
        key = zip(c.batch_index().tolist(), c.range_bin.tolist(), c.doppler_bin.tolist())
        return {k: i for i, k in enumerate(key)}

    a, b = by_cell(cpu), by_cell(gpu)
    shared = sorted(set(a) & set(b))
    assert len(shared) >= 0.99 * max(len(a), len(b)) and len(shared) > 100
    ia, ib = torch.tensor([a[k] for k in shared]), torch.tensor([b[k] for k in shared])
    assert torch.equal(cpu.doppler_full[ia], gpu.doppler_full[ib])
    assert float((cpu.azimuth_deg[ia] == gpu.azimuth_deg[ib]).double().mean()) > 0.999
    torch.testing.assert_close(gpu.amplitude[ib], cpu.amplitude[ia], rtol=1e-4, atol=0)
    if cpu.sector is not None:
        torch.testing.assert_close(gpu.sector[ib], cpu.sector[ia], rtol=1e-4, atol=1e-6)


def test_frame_span_of_offsets():
    from radarpc.points import frame_span

    offset = torch.tensor([2, 2, 5])                      # frames of 2, 0 and 3 rows
    assert frame_span(offset, 0) == (0, 0, 2)
    assert frame_span(offset, 1) == (1, 2, 2)            # an empty frame
    assert frame_span(offset, -1) == (2, 2, 5)
    with pytest.raises(IndexError, match="frame 3 out of range for a batch of 3 frames"):
        frame_span(offset, 3)
