"""The occupancy partitioning choice: Cartesian voxels against hand-worked cells, and both kinds of
grid through the same query sampling."""
from __future__ import annotations

import math

import pytest
import torch

from radarpc.rald.frustum import RALD_GRID, FrustumGrid, occupancy, sample_queries
from radarpc.rald.voxels import (CartesianGrid, cartesian_points, cell_centres, grid_coords, model_coords,
                                 partition_grid, voxelize_points)
from radarpc.sensors.coloradar import AWR1843_FOV


def test_voxel_grid_covering_the_fov_by_hand():
    # AWR1843: r <= 15.863 m, +-90 deg azimuth, +-20 deg elevation -> x in [0, 15.863], y in +-15.863,
    # z in +-15.863 sin 20 deg = +-5.4255; in 0.05 m voxels from the origin: 0..15.9, +-15.9, +-5.45
    g = partition_grid("cartesian")
    assert isinstance(g, CartesianGrid)
    assert g.x_m == pytest.approx((0.0, 15.9)) and g.y_m == pytest.approx((-15.9, 15.9))
    assert g.z_m == pytest.approx((-5.45, 5.45))
    assert g.shape == (318, 636, 218)
    assert partition_grid("frustum") == RALD_GRID
    with pytest.raises(ValueError, match="partition"):
        partition_grid("spherical")


def test_voxelize_and_query_labels_by_hand():
    g = CartesianGrid((0.0, 2.0), (-1.0, 1.0), (-0.5, 0.5), (0.5, 0.5, 0.5))       # 4 x 4 x 2 voxels
    pts = torch.tensor([[0.1, -0.9, -0.4], [0.2, -0.8, -0.3], [1.7, 0.6, 0.2], [3.0, 0.0, 0.0]])
    occ = voxelize_points(g, pts)
    # (0, 0, 0) -> 0 twice, (3, 3, 1) -> (3 * 4 + 3) * 2 + 1 = 31; (3, 0, 0) is outside
    assert occ.cells.tolist() == [0, 31] and occ.n_points == 3 and occ.n_outside == 1
    torch.testing.assert_close(cell_centres(occ), torch.tensor([[0.25, -0.75, -0.25], [1.75, 0.75, 0.25]]))
    u = model_coords(g, pts[:3])
    torch.testing.assert_close(u[0], torch.tensor([0.1 / 1.0 - 1.0, -0.9, -0.8]))
    torch.testing.assert_close(cartesian_points(g, u), pts[:3])
    q, labels = sample_queries(occ, 64, 0.25, generator=torch.Generator().manual_seed(0))
    assert labels.sum() == 16 and q.abs().max() <= 1
    assert torch.equal(occupancy(occ, q), labels)               # each positive lies in an occupied voxel


def test_frustum_partition_through_the_same_functions():
    g = FrustumGrid((0.0, 8.0), (-60.0, 60.0), (-20.0, 20.0), (0.5, 7.5, 5.0))
    p = torch.tensor([[4.0, 1.0, 0.5]], dtype=torch.float64)
    rae = grid_coords(g, p)[0]
    assert rae[0].item() == pytest.approx(math.sqrt(17.25))
    assert rae[1].item() == pytest.approx(math.degrees(math.atan2(1, 4)))
    torch.testing.assert_close(cartesian_points(g, model_coords(g, p)), p)
    occ = voxelize_points(g, p)
    # the centre of the cell holding p lies within half a cell of p in every polar coordinate
    centre = grid_coords(g, cell_centres(occ, dtype=torch.float64))[0]
    assert ((centre - rae).abs() <= torch.tensor(g.cell, dtype=torch.float64) / 2).all()
    with pytest.raises(ValueError, match="FrustumGrid or a CartesianGrid"):
        model_coords(AWR1843_FOV, p)
