"""OS-CFAR baseline: a point reflector is detected at its cell; tuning; config files."""
import math

import numpy as np
import pytest
import torch

from radarpc.io import DataFileError
from radarpc.rald.oscfar_baseline import (
    CubeAxes,
    OSCFARConfig,
    TuningGrid,
    detect_cells,
    detect_points,
    load_config,
    save_config,
    tune_oscfar,
    upsample_angles,
)

R, A, E = 64, 8, 2
AXES = CubeAxes(range_m=tuple(0.125 * np.arange(R)),
                azimuth_deg=tuple(np.rad2deg(np.arcsin(np.linspace(0.875, -0.875, A)))),   # descending, sin-spaced
                elevation_deg=(-10.0, 10.0))


def _noise_cube(seed: int, batch: tuple[int, ...] = ()) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    power = -torch.log(torch.rand((*batch, R, A, E), generator=g, dtype=torch.float64))   # exponential, mean 1
    return 10.0 * torch.log10(power)


def _xyz(r, az_deg, el_deg):
    a, e = math.radians(az_deg), math.radians(el_deg)
    return np.array([r * math.cos(e) * math.cos(a), r * math.cos(e) * math.sin(a), r * math.sin(e)])


def test_point_reflector_detected_at_its_cell():
    cube = _noise_cube(0)
    cube[30, 5, 1] = 35.0                      # 35 dB above the noise at (3.75 m, az bin 5, +10 deg)
    cfg = OSCFARConfig(tau_db=20.0, refine=False, elevation_deg=None)   # bin-centre elevations
    mask, _, _ = detect_cells(cube, AXES, cfg)
    assert mask.nonzero().tolist() == [[30, 5, 1]]
    pts = detect_points(cube, AXES, cfg)
    assert pts.shape == (1, 3) and pts.dtype == torch.float32
    np.testing.assert_allclose(pts[0].numpy(), _xyz(3.75, AXES.azimuth_deg[5], 10.0), atol=1e-5)
    # default: the elevation axis is collapsed, the point lies in the horizontal plane
    flat = detect_points(cube, AXES, OSCFARConfig(tau_db=20.0, refine=False))
    np.testing.assert_allclose(flat[0].numpy(), _xyz(3.75, AXES.azimuth_deg[5], 0.0), atol=1e-5)


def test_default_elevation_merges_the_elevation_bins():
    # one target seen in both elevation bins of a (range, azimuth) cell: one point at 0 deg, not two
    cube = _noise_cube(5)
    cube[30, 5, :] = 35.0
    cube[44, 2, 0] = 35.0
    pts = detect_points(cube, AXES, OSCFARConfig(tau_db=20.0, refine=False))
    assert pts.shape == (2, 3)
    np.testing.assert_allclose(pts.numpy(), [_xyz(3.75, AXES.azimuth_deg[5], 0.0),
                                             _xyz(5.5, AXES.azimuth_deg[2], 0.0)], atol=1e-5)
    pts = detect_points(cube, AXES, OSCFARConfig(tau_db=20.0, refine=False, elevation_deg=5.0))
    np.testing.assert_allclose(np.degrees(np.arcsin(pts[:, 2].numpy() / np.linalg.norm(pts.numpy(), axis=1))),
                               [5.0, 5.0], atol=1e-4)
    with pytest.raises(ValueError, match="elevation_deg"):
        OSCFARConfig(elevation_deg=120.0)

def test_refinement_moves_a_straddling_target_between_bins():
    cube = torch.full((R, A, E), -50.0, dtype=torch.float64)
    cube[20, 3, 0] = 20.0
    cube[21, 3, 0] = 20.0 - 1e-9               # a target halfway between range bins 20 and 21
    cube[19, 3, 0] = cube[22, 3, 0] = 10.0
    cfg = OSCFARConfig(tau_db=20.0, min_points=1)
    mask, _, _ = detect_cells(cube, AXES, cfg)
    assert mask[20, 3, 0] and mask[21, 3, 0]
    pts = detect_points(cube, AXES, cfg)
    r = np.linalg.norm(pts.numpy(), axis=1)
    # bin 20 refines towards 21 (+0.5 bin), bin 21 is not a strict peak along range: stays
    assert np.any(np.isclose(r, 0.125 * 20.5, atol=1e-4))


def test_min_range_and_min_points_fallback():
    cube = _noise_cube(1)
    cube[1, 4, 0] = 40.0                       # leakage at 0.125 m, inside min_range_m
    cfg = OSCFARConfig(tau_db=60.0, min_range_m=0.3, min_points=3, refine=False)
    mask, _, _ = detect_cells(cube, AXES, cfg)
    assert int(mask.sum()) == 3 and not mask[:3].any()   # nothing passes 60 dB: the 3 best cells beyond 0.3 m


def test_batch_equals_single_frames():
    cubes = _noise_cube(2, (3,))
    cubes[1, 40, 2, 0] = 30.0
    cfg = OSCFARConfig(tau_db=12.0, angle_bins=(16, 4))
    batch = detect_points(cubes, AXES, cfg)
    assert len(batch) == 3
    for b in range(3):
        torch.testing.assert_close(batch[b], detect_points(cubes[b], AXES, cfg))


def test_upsample_angles_keeps_bin_values_and_axes():
    cube = _noise_cube(3)
    up, ax = upsample_angles(cube, AXES, (15, 3))           # (8-1)*2+1 and (2-1)*2+1: old bins kept
    assert up.shape == (R, 15, 3)
    torch.testing.assert_close(up[:, ::2, ::2], cube)
    assert ax.azimuth_deg[::2] == pytest.approx(AXES.azimuth_deg)
    assert ax.elevation_deg == pytest.approx((-10.0, 0.0, 10.0))


def test_tuning_prefers_the_threshold_that_isolates_the_reflectors():
    frames = []
    for s in range(3):
        cube = _noise_cube(10 + s)
        cube[25 + s, 2, 0] = 30.0
        cube[50, 6, 1] = 30.0
        lidar = np.stack([_xyz(0.125 * (25 + s), AXES.azimuth_deg[2], -10.0),
                          _xyz(0.125 * 50, AXES.azimuth_deg[6], 10.0)])
        frames.append((cube, lidar))
    grid = TuningGrid(windows=((9, 3, 3),), guards=((3, 1, 1),), ranks=(0.75,), taus_db=(3.0, 20.0),
                      angle_bins=(None,), base=OSCFARConfig(refine=False, elevation_deg=None))
    res = tune_oscfar(frames, AXES, grid)
    assert len(res.table) == 2 and res.n_frames == 3
    assert res.best.tau_db == 20.0
    assert res.best_chamfer == pytest.approx(0.0, abs=1e-5)     # exactly the two reflector cells
    low = [row for row in res.table if row[0].tau_db == 3.0][0]
    assert low[1] > res.best_chamfer and low[2] > 2


def test_config_yaml_round_trip_and_errors(tmp_path):
    cfg = OSCFARConfig(window=(13, 5, 3), guard=(5, 3, 1), rank=0.6, tau_db=9.5, angle_bins=(32, 8))
    save_config(tmp_path / "config.yaml", cfg, split="val", chamfer_m=0.8)
    assert load_config(tmp_path / "config.yaml") == cfg
    assert "!!python" not in (tmp_path / "config.yaml").read_text()
    with pytest.raises(DataFileError, match="missing"):
        load_config(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("oscfar: {window: [9, 3, 3], colour: red}\n")
    with pytest.raises(DataFileError, match="bad.yaml.*unknown OS-CFAR config keys"):
        load_config(tmp_path / "bad.yaml")


def test_bad_parameters_and_cubes():
    with pytest.raises(ValueError, match="odd"):
        OSCFARConfig(window=(8, 3, 3))
    with pytest.raises(ValueError, match="smaller than window"):
        OSCFARConfig(window=(9, 3, 3), guard=(3, 3, 1))
    with pytest.raises(ValueError, match="quantile"):
        OSCFARConfig(rank=1.5)
    with pytest.raises(ValueError, match="does not match its axes"):
        detect_points(torch.zeros(R, A, 3), AXES)
    with pytest.raises(ValueError, match="NaN"):
        detect_points(torch.full((R, A, E), float("nan")), AXES)
    with pytest.raises(ValueError, match="complex"):
        detect_points(torch.zeros(R, A, E, dtype=torch.complex64), AXES)
    with pytest.raises(ValueError, match="monotonic"):
        CubeAxes((0.0, 1.0, 1.0), (0.0,), (0.0,))
    with pytest.raises(ValueError, match="LiDAR cloud is empty"):
        tune_oscfar([(_noise_cube(0), np.zeros((0, 3)))], AXES)


def test_angles_outside_the_frustum_are_clipped_and_radian_axes():
    # the AWR1843's 2-bin elevation FFT: bins at asin(-0.5 / d) ~ -80 deg and 0 deg
    axes = CubeAxes.from_radians(torch.arange(R) * 0.125, torch.linspace(-1.2, 1.2, A),
                                 torch.tensor([-1.396, 0.0]))
    assert axes.elevation_deg[0] == pytest.approx(-79.99, abs=0.01)
    cube = _noise_cube(4)
    cube[40, 0, 0] = 40.0
    pts = detect_points(cube, axes, OSCFARConfig(tau_db=20.0, refine=False, elevation_deg=None))
    assert pts.shape == (1, 3)
    np.testing.assert_allclose(pts[0].numpy(), _xyz(5.0, -np.rad2deg(1.2), -20.0), atol=1e-5)
    # the default places the difference-channel (-80 deg bin) detection at 0 deg, not on the -20 deg floor
    pts0 = detect_points(cube, axes, OSCFARConfig(tau_db=20.0, refine=False))
    np.testing.assert_allclose(pts0[0].numpy(), _xyz(5.0, -np.rad2deg(1.2), 0.0), atol=1e-5)
    free = detect_points(cube, axes, OSCFARConfig(tau_db=20.0, refine=False, clip_angles_deg=None,
                                                  elevation_deg=None))
    np.testing.assert_allclose(free[0].numpy(), _xyz(5.0, -np.rad2deg(1.2), -np.rad2deg(1.396)), atol=1e-5)
