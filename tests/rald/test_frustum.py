"""Frustum occupancy: coordinates, voxelization, lookup, query sampling."""
import math

import numpy as np
import pytest
import torch

from radarpc.rald.frustum import (
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
    assert RALD_GRID.shape == (316, 720, 80)
    assert RALD_GRID.lo == (0.0, -90.0, -20.0) and RALD_GRID.hi == (15.8, 90.0, 20.0)
    assert SMALL.shape == (8, 12, 5)


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
    corners = torch.tensor([RALD_GRID.lo, RALD_GRID.hi, [7.9, 0.0, 0.0]], dtype=torch.float64)
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
                        [20.0, 0.0, 0.0],     # beyond 15.8 m
                        [1.0, 0.0, 1.0],      # elevation 45 deg
                        [15.8, 0.0, 0.0]])    # on the upper range edge: last cell
    occ = voxelize(RALD_GRID, xyz)
    assert occ.n_points == 2 and occ.n_outside == 3
    assert in_frustum(RALD_GRID, xyz).tolist() == [True, False, False, False, True]
    ijk = occ.ijk()
    assert ijk[:, 0].tolist() == [20, 315]
    assert ijk[:, 1].tolist() == [360, 360] and ijk[:, 2].tolist() == [40, 40]


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
        FrustumGrid(cell=(0.03, 0.25, 0.5))
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
