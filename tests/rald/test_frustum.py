"""Frustum occupancy: coordinates, voxelization, lookup, query sampling."""
import math

import numpy as np
import pytest
import torch

from radarpc.data.coloradar import frustum_mask
from radarpc.rald.frustum import (
    RALD_CELL,
    RALD_GRID,
    FrustumGrid,
    OccupancyGrid,
    cartesian_to_polar,
    cell_indices,
    occupancy_to_points,
    occupancy_to_polar,
    denormalize,
    in_frustum,
    normalize,
    occupancy,
    polar_to_cartesian,
    sample_queries,
    sample_queries_batch,
    voxelize,
    voxelize_batch,
)
from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV

SMALL = FrustumGrid(range_m=(0.0, 2.0), azimuth_deg=(-30.0, 30.0), elevation_deg=(-10.0, 10.0),
                    cell=(0.25, 5.0, 4.0))   # 8 x 12 x 5 cells


def _cloud_in(grid: FrustumGrid, n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(grid.lo, dtype=torch.float64)
    hi = torch.tensor(grid.hi, dtype=torch.float64)
    rae = lo + torch.rand((n, 3), generator=g, dtype=torch.float64) * (hi - lo)
    rae[:, 0] = rae[:, 0].clamp_min(0.05)
    return polar_to_cartesian(rae)


def test_default_grid_is_ralds():
    # RaLD's cells (0.05 m, 0.25 deg, 0.5 deg) over the AWR1843 FOV: ceil(15.863 / 0.05) = 318 range cells
    assert RALD_CELL == (0.05, 0.25, 0.5) and RALD_GRID.cell == RALD_CELL
    assert RALD_GRID == FrustumGrid.from_fov(AWR1843_FOV, RALD_CELL)
    assert RALD_GRID.shape == (318, 720, 80)
    assert RALD_GRID.lo == (0.0, -90.0, -20.0) and RALD_GRID.hi == (15.9, 90.0, 20.0)
    assert SMALL.shape == (8, 12, 5)


def test_from_fov_covers_the_fov_with_whole_cells():
    # hand-worked: 1.01 m at 0.25 m -> 5 cells to 1.25 m; 60 deg at 5 deg -> 12; 20 deg at 4 deg -> 5
    fov = RadarFOV(max_range_m=1.01, azimuth_deg=(-30.0, 30.0), elevation_deg=(-10.0, 10.0))
    g = FrustumGrid.from_fov(fov, (0.25, 5.0, 4.0))
    assert g.shape == (5, 12, 5) and g.lo == (0.0, -30.0, -10.0) and g.hi == (1.25, 30.0, 10.0)
    # a span that is a whole number of cells up to rounding keeps that number (15.8 / 0.05 = 316)
    assert FrustumGrid.from_fov(RadarFOV(max_range_m=15.8), RALD_CELL).shape == (316, 720, 80)
    # a non-zero minimum range starts the grid there
    g = FrustumGrid.from_fov(RadarFOV(max_range_m=2.0, min_range_m=0.5), (0.4, 0.25, 0.5))
    assert g.range_m == (0.5, 0.5 + 4 * 0.4)
    for bad in ((0.05, 0.25), (0.05, 0.0, 0.5), (0.05, float("nan"), 0.5)):
        with pytest.raises(ValueError, match="cell"):
            FrustumGrid.from_fov(AWR1843_FOV, bad)


def test_grid_contains_every_lidar_point_the_fov_crop_keeps():
    fov = AWR1843_FOV
    # the grid's extent covers the FOV, by less than one cell on each axis
    lo, hi, cell = np.array(RALD_GRID.lo), np.array(RALD_GRID.hi), np.array(RALD_GRID.cell)
    f_lo = np.array([fov.min_range_m, fov.azimuth_deg[0], fov.elevation_deg[0]])
    f_hi = np.array([fov.max_range_m, fov.azimuth_deg[1], fov.elevation_deg[1]])
    assert np.all(lo == f_lo) and np.all(hi >= f_hi) and np.all(hi - f_hi < cell)
    # LiDAR-like float32 clouds around the sensor, with points between RaLD's 15.8 m and the FOV's 15.863 m
    rng = np.random.default_rng(0)
    pts = rng.uniform(-16.5, 16.5, (400_000, 3)).astype(np.float32)
    u = rng.normal(size=(20_000, 3))
    shell = (u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(15.8, 15.87, (20_000, 1))).astype(np.float32)
    pts = np.concatenate([pts, shell])
    kept = pts[frustum_mask(pts, fov)]
    assert len(kept) > 10_000 and (np.linalg.norm(kept.astype(np.float64), axis=1) > 15.8).sum() > 1000
    assert bool(in_frustum(RALD_GRID, torch.from_numpy(kept)).all())
    occ = voxelize(RALD_GRID, kept)
    assert occ.n_outside == 0 and occ.n_points == len(kept)
    assert int(occ.ijk()[:, 0].max()) == 317       # the cell holding 15.85..15.9 m, past RaLD's 316 cells
    # float64 points exactly on the FOV's edges (corners, range bound, angular bounds)
    r = [1e-3, 1.0, 15.8, fov.max_range_m]
    rae = torch.tensor([(a, b, c) for a in r for b in (*fov.azimuth_deg, 0.0) for c in (*fov.elevation_deg, 0.0)],
                       dtype=torch.float64)
    edge = polar_to_cartesian(rae)
    keep = torch.as_tensor(frustum_mask(edge, fov))
    assert int(keep.sum()) > len(edge) // 2
    assert bool(in_frustum(RALD_GRID, edge[keep]).all())
    # in float32 an edge point can round to opposite sides of an angular bound in the crop's
    # asin(z / r) and the grid's atan2(z, hypot(x, y)); it is then outside by no more than the
    # angles' float32 rounding: a few ulps (sqrt, division, asin/atan2 each <= 1 ulp, plus the
    # bound's own rounding), bounded here by 4 eps * 90 deg
    e32 = edge.float()
    kept32 = e32[torch.as_tensor(frustum_mask(e32, fov))]
    p = cartesian_to_polar(kept32.double())
    excess = torch.maximum(torch.tensor(RALD_GRID.lo, dtype=torch.float64) - p,
                           p - torch.tensor(RALD_GRID.hi, dtype=torch.float64)).clamp_min(0)
    assert float(excess.max()) <= 4 * torch.finfo(torch.float32).eps * 90.0


def test_polar_convention_hand_worked():
    xyz = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, -3.0, 0.0], [1.0, 0.0, 1.0]], dtype=torch.float64)
    rae = cartesian_to_polar(xyz)
    expected = torch.tensor([[1, 0, 0], [2, 90, 0], [3, -90, 0], [math.sqrt(2), 0, 45]], dtype=torch.float64)
    torch.testing.assert_close(rae, expected)   # azimuth left (+y) positive, elevation up positive


def test_polar_cartesian_round_trip():
    xyz = torch.randn(500, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 5
    torch.testing.assert_close(polar_to_cartesian(cartesian_to_polar(xyz)), xyz)
    rae = cartesian_to_polar(xyz)
    torch.testing.assert_close(cartesian_to_polar(polar_to_cartesian(rae)), rae)


def test_normalize_maps_grid_to_unit_cube_and_back():
    corners = torch.tensor([RALD_GRID.lo, RALD_GRID.hi, [7.95, 0.0, 0.0]], dtype=torch.float64)
    u = normalize(RALD_GRID, corners)
    torch.testing.assert_close(u, torch.tensor([[-1.0, -1, -1], [1, 1, 1], [0, 0, 0]], dtype=torch.float64))
    torch.testing.assert_close(denormalize(RALD_GRID, u), corners)


def test_voxelize_then_occupancy_to_points_within_half_a_cell():
    xyz = _cloud_in(RALD_GRID, 3000, seed=1)
    occ = voxelize(RALD_GRID, xyz)
    assert occ.n_points == 3000 and occ.n_outside == 0
    assert torch.all(occ.cells[1:] > occ.cells[:-1])            # sorted, unique
    centres = occupancy_to_polar(occ, dtype=torch.float64)          # (M, 3)
    rae = cartesian_to_polar(xyz)
    cell = torch.tensor(RALD_GRID.cell, dtype=torch.float64)
    # every point is within half a cell (per polar axis) of the centre of an occupied cell: its own
    lin, _ = cell_indices(RALD_GRID, xyz)
    own = centres[torch.searchsorted(occ.cells, lin)]
    assert torch.all((rae - own).abs() / cell <= 0.5 + 1e-9)
    # and every occupied cell is the cell of some point (so holds a point within half a cell)
    assert torch.equal(torch.unique(lin), occ.cells)
    # the decoded Cartesian points re-voxelize to the same cells
    assert torch.equal(voxelize(RALD_GRID, occupancy_to_points(occ)).cells, occ.cells)


def test_voxelize_drops_points_outside_and_keeps_upper_edge():
    xyz = torch.tensor([[1.0, 0.0, 0.0],      # inside
                        [-1.0, 0.0, 0.0],     # behind: azimuth 180
                        [20.0, 0.0, 0.0],     # beyond 15.9 m
                        [1.0, 0.0, 1.0],      # elevation 45 deg
                        [15.83, 0.0, 0.0],    # past RaLD's public 15.8 m, inside the FOV: cell 316
                        [15.9, 0.0, 0.0]])    # on the upper range edge: last cell
    occ = voxelize(RALD_GRID, xyz)
    assert occ.n_points == 3 and occ.n_outside == 3
    assert in_frustum(RALD_GRID, xyz).tolist() == [True, False, False, False, True, True]
    ijk = occ.ijk()
    assert ijk[:, 0].tolist() == [20, 316, 317]
    assert ijk[:, 1].tolist() == [360] * 3 and ijk[:, 2].tolist() == [40] * 3


def test_occupancy_lookup_matches_dense_brute_force():
    xyz = _cloud_in(SMALL, 40, seed=2)
    occ = voxelize(SMALL, xyz)
    dense = np.zeros(SMALL.shape, dtype=bool)
    lo, cell = np.array(SMALL.lo), np.array(SMALL.cell)
    for p in cartesian_to_polar(xyz).numpy():
        i, j, k = np.minimum(np.floor((p - lo) / cell).astype(int), np.array(SMALL.shape) - 1)
        dense[i, j, k] = True
    assert np.array_equal(occ.dense().numpy(), dense)
    # arbitrary queries, some outside the frustum, in all three coordinate systems
    u = torch.rand(5000, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 2.4 - 1.2
    rae = denormalize(SMALL, u).numpy()
    inside = np.all((rae >= SMALL.lo) & (rae <= SMALL.hi), axis=1)
    idx = np.minimum(np.floor((rae - lo) / cell).astype(int), np.array(SMALL.shape) - 1).clip(0)
    want = inside & dense[idx[:, 0], idx[:, 1], idx[:, 2]]
    assert want.sum() > 0
    assert np.array_equal(occupancy(occ, u).numpy(), want)
    assert np.array_equal(occupancy(occ, torch.from_numpy(rae), coords="polar").numpy(), want)
    assert np.array_equal(occupancy(occ, u.view(50, 100, 3)).numpy(), want.reshape(50, 100))
    ok = rae[:, 0] > 0.01
    xyz_q = polar_to_cartesian(torch.from_numpy(rae[ok]))
    assert np.array_equal(occupancy(occ, xyz_q, coords="cartesian").numpy(), want[ok])


def test_sample_queries_exact_ratio_and_labels_agree_with_lookup():
    occ = voxelize(RALD_GRID, _cloud_in(RALD_GRID, 2000, seed=4))
    gen = torch.Generator().manual_seed(5)
    q, lab = sample_queries(occ, n=10_000, positive_ratio=0.0625, generator=gen)
    assert q.shape == (10_000, 3) and q.dtype == torch.float32 and lab.dtype == torch.bool
    assert int(lab.sum()) == 625 and lab[:625].all() and not lab[625:].any()
    assert q.abs().max() <= 1.0
    assert torch.equal(occupancy(occ, q), lab)       # positives inside occupied cells, negatives in empty
    # reproducible with the same generator seed
    q2, _ = sample_queries(occ, n=10_000, generator=torch.Generator().manual_seed(5))
    assert torch.equal(q, q2)
    qs, ls = sample_queries(occ, n=10_000, generator=torch.Generator().manual_seed(6), shuffle=True)
    assert int(ls.sum()) == 625 and not ls[:625].all() and torch.equal(occupancy(occ, qs), ls)
    # jitter covers the cell: positives are not all at cell centres
    rae = denormalize(RALD_GRID, q[:625].double())
    frac = (rae - torch.tensor(RALD_GRID.lo, dtype=torch.float64)) / torch.tensor(RALD_GRID.cell, dtype=torch.float64)
    frac = frac - frac.floor()
    assert frac.min() < 0.1 and frac.max() > 0.9


def test_sample_queries_on_nearly_full_small_grid():
    # 480 cells, 470 occupied: rejection sampling must still find the 10 empty ones
    lin = torch.arange(SMALL.n_cells)
    keep = torch.ones_like(lin, dtype=torch.bool)
    keep[torch.arange(0, 480, 48)] = False
    occ = OccupancyGrid(SMALL, lin[keep])
    q, lab = sample_queries(occ, n=300, positive_ratio=0.5, generator=torch.Generator().manual_seed(0))
    assert int(lab.sum()) == 150
    assert torch.equal(occupancy(occ, q), lab)
    qb, lb = sample_queries_batch([occ, occ], n=64, positive_ratio=0.25)
    assert qb.shape == (2, 64, 3) and lb.sum(1).tolist() == [16, 16]


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="shape"):
        voxelize(RALD_GRID, torch.zeros(10, 2))
    with pytest.raises(ValueError, match="NaN"):
        voxelize(RALD_GRID, torch.tensor([[1.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="complex"):
        cartesian_to_polar(torch.zeros(3, 3, dtype=torch.complex64))
    with pytest.raises(ValueError, match="empty"):
        sample_queries(voxelize(RALD_GRID, torch.zeros(0, 3)), n=100)
    occ = voxelize(RALD_GRID, torch.tensor([[1.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="positive_ratio"):
        sample_queries(occ, positive_ratio=1.5)
    with pytest.raises(ValueError, match="positive integer"):
        sample_queries(occ, n=0)
    with pytest.raises(ValueError, match="coords"):
        occupancy(occ, torch.zeros(1, 3), coords="spherical")
    with pytest.raises(ValueError, match="whole number of cells"):
        FrustumGrid((0.0, 15.8), (-90.0, 90.0), (-20.0, 20.0), cell=(0.03, 0.25, 0.5))
    with pytest.raises(ValueError, match="every cell"):
        sample_queries(OccupancyGrid(SMALL, torch.arange(SMALL.n_cells)), n=10)


def test_voxelize_batch_equals_per_cloud():
    clouds = [_cloud_in(RALD_GRID, 500, seed=6), torch.zeros(0, 3, dtype=torch.float64),
              torch.cat([_cloud_in(RALD_GRID, 300, seed=7), torch.tensor([[-3.0, 0.0, 0.0]], dtype=torch.float64)])]
    offset = torch.cumsum(torch.tensor([len(c) for c in clouds]), 0)
    occs = voxelize_batch(RALD_GRID, torch.cat(clouds), offset)
    assert len(occs) == 3
    for o, c in zip(occs, clouds):
        ref = voxelize(RALD_GRID, c)
        assert torch.equal(o.cells, ref.cells) and (o.n_points, o.n_outside) == (ref.n_points, ref.n_outside)
    assert occs[2].n_outside == 1 and occs[1].n_occupied == 0
    with pytest.raises(ValueError, match="offset"):
        voxelize_batch(RALD_GRID, torch.cat(clouds), torch.tensor([500, 400, 801]))
    with pytest.raises(ValueError, match="sorted unique"):
        OccupancyGrid(SMALL, torch.tensor([3, 3]))
