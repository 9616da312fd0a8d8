"""Occupancy probabilities as clouds: the cells above the threshold at their centres by hand, the
jitter inside its cell and reproducible from its seed."""
from __future__ import annotations

import math

import pytest
import torch

from radarpc.pipelines.occupancy_clouds import CloudConfig, occupancy_points
from radarpc.rald.frustum import FrustumGrid, cartesian_to_polar

GRID = FrustumGrid((0.0, 4.0), (-90.0, 90.0), (-20.0, 20.0), (1.0, 45.0, 20.0))     # 4 x 4 x 2 cells


def test_cells_above_the_threshold_at_their_centres_by_hand():
    """Probabilities 0.9 at (1, 2, 1), exactly 0.5 at (3, 0, 0) (not above), 0.51 at (0, 3, 0):
    centres (1.5 m, 22.5 deg, 10 deg) and (0.5 m, 67.5 deg, -10 deg), in linear-index order."""
    prob = torch.zeros(GRID.shape)
    prob[1, 2, 1], prob[3, 0, 0], prob[0, 3, 0] = 0.9, 0.5, 0.51
    pts = occupancy_points(GRID, prob, 0.5)

    def xyz(r, az, el):
        a, e = math.radians(az), math.radians(el)
        return [r * math.cos(e) * math.cos(a), r * math.cos(e) * math.sin(a), r * math.sin(e)]

    torch.testing.assert_close(pts, torch.tensor([xyz(0.5, 67.5, -10), xyz(1.5, 22.5, 10)]), rtol=0, atol=1e-6)
    assert occupancy_points(GRID, prob, 0.95).shape == (0, 3)


def test_jitter_stays_in_its_cell_and_follows_its_seed():
    prob = torch.rand(GRID.shape, generator=torch.Generator().manual_seed(1))
    above = prob > 0.5
    a = occupancy_points(GRID, prob, 0.5, jitter=True, generator=torch.Generator().manual_seed(7))
    b = occupancy_points(GRID, prob, 0.5, jitter=True, generator=torch.Generator().manual_seed(7))
    c = occupancy_points(GRID, prob, 0.5, jitter=True, generator=torch.Generator().manual_seed(8))
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.allclose(a, c)
    rae = cartesian_to_polar(a.double())
    ijk = ((rae - torch.tensor(GRID.lo, dtype=torch.float64)) / torch.tensor(GRID.cell, dtype=torch.float64)).floor()
    want = torch.nonzero(above).double()                                    # the same cells, in the same order
    torch.testing.assert_close(ijk, want, rtol=0, atol=0)


@pytest.mark.parametrize("kw, message", [({"threshold": 1.0}, "threshold must be a probability in [0, 1)"),
                                         ({"jitter": 1}, "jitter must be true or false"),
                                         ({"seed": -1}, "seed must be an integer >= 0")])
def test_cloud_config_refuses_bad_values(kw, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace(")", r"\)")):
        CloudConfig(**kw)
