"""The occupancy baseline's task: the target against hand-worked cells, the loss and the metrics by
hand, and a tiny network that overfits one frame of a simulated hallway in a few seconds."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radarpc.data.coloradar import ColoRadar, rald_intensity
from radarpc.eval.pointsets import chamfer_distance
from radarpc.experiments.rpdnet.task import occupancy_metrics, occupancy_target, weighted_bce
from radarpc.models import build_model
from radarpc.pipelines.occupancy_clouds import occupancy_points
from radarpc.rald.frustum import FrustumGrid
from radarpc.rald.oscfar_baseline import CubeAxes, OSCFARConfig, detect_points
from radarpc.sensors.coloradar import AWR1843_FOV

CELL = (1.0, 22.5, 10.0)               # AWR1843's field of view in 16 x 8 x 4 cells


def _xyz(r: float, az: float, el: float) -> list[float]:
    a, e = math.radians(az), math.radians(el)
    return [r * math.cos(e) * math.cos(a), r * math.cos(e) * math.sin(a), r * math.sin(e)]


def test_target_occupancy_by_hand():
    """Cells ``i = floor(r / 1 m)``, ``j = floor((az + 90) / 22.5)``, ``k = floor((el + 20) / 10)``:
    (2.5 m, 30 deg, 5 deg) -> (2, 5, 2), twice (one cell); (0.4 m, -89 deg, -19 deg) -> (0, 0, 0);
    (15.5 m, 89 deg, 19 deg) -> (15, 7, 3); beyond the range (17 m) or the elevation (30 deg): none."""
    grid = FrustumGrid.from_fov(AWR1843_FOV, CELL)
    assert grid.shape == (16, 8, 4)
    pts = np.array([_xyz(2.5, 30, 5), _xyz(2.6, 31, 6), _xyz(0.4, -89, -19), _xyz(15.5, 89, 19),
                    _xyz(17.0, 0, 0), _xyz(5.0, 0, 30)], dtype=np.float32)
    occ = occupancy_target(grid, pts)
    want = torch.zeros(16, 8, 4)
    for ijk in ((2, 5, 2), (0, 0, 0), (15, 7, 3)):
        want[ijk] = 1.0
    assert occ.dtype == torch.float32 and torch.equal(occ, want)
    # and back to points at the cells' centres: (2.5 m, -90 + 5.5 x 22.5 = 33.75 deg, -20 + 2.5 x 10 = 5 deg), ...
    centres = occupancy_points(grid, occ, 0.5)
    torch.testing.assert_close(centres, torch.tensor([_xyz(0.5, -78.75, -15), _xyz(2.5, 33.75, 5),
                                                      _xyz(15.5, 78.75, 15)]), rtol=0, atol=1e-5)


def test_weighted_bce_by_hand():
    """Logits (0, 2, -1) with truth (1, 0, 1) and w = 4:
    ``[4 log 2 + log(1 + e^2) + 4 log(1 + e)] / 3``."""
    got = weighted_bce(torch.tensor([0.0, 2.0, -1.0]), torch.tensor([1.0, 0.0, 1.0]), 4.0)
    want = (4 * math.log(2) + math.log(1 + math.e ** 2) + 4 * math.log(1 + math.e)) / 3
    assert float(got) == pytest.approx(want, rel=1e-6)


def test_metrics_by_hand():
    """Predicted (logit > 0) cells {0, 1, 2}, true {1, 2, 3, 4}: |P & O| = 2, |P | O| = 5, so IoU 2/5,
    precision 2/3, recall 2/4, F1 4/7; a frame with nothing predicted nor occupied scores 1."""
    logits = torch.tensor([[1.0, 1.0, 1.0, -1.0, -1.0, -1.0], [-1.0] * 6])
    truth = torch.tensor([[0.0, 1.0, 1.0, 1.0, 1.0, 0.0], [0.0] * 6])
    m = occupancy_metrics(logits, truth)
    for k, v in {"iou": 2 / 5, "precision": 2 / 3, "recall": 2 / 4, "f1": 4 / 7}.items():
        torch.testing.assert_close(m[k], torch.tensor([v, 1.0]))      # float32 (MPS has no float64)


def test_a_tiny_network_overfits_one_frame(colo_hallway_root):
    """120 AdamW steps on one hallway frame: the loss falls below a fifth of its start and the cloud
    of the cells above 0.5 comes within well under OS-CFAR's Chamfer distance of the LiDAR truth
    (OS-CFAR with its default parameters on the same cube; the truth's own cells, in the message, are
    what the grid can reach)."""
    ds = ColoRadar(colo_hallway_root, "train", cube_size=None)
    cube, truth = ds.cube(0), ds.lidar_points(0)
    axes = CubeAxes.from_radians(cube.range_m, cube.azimuth_rad, cube.elevation_rad)
    cd_oscfar = chamfer_distance(detect_points(cube.intensity_db, axes, OSCFARConfig()).cpu().numpy(), truth)
    torch.manual_seed(0)
    model = build_model("rpdnet-tiny")
    grid = FrustumGrid.from_fov(ds.fov, (0.5, 11.25, 5.0))
    assert grid.shape == model.cfg.out_shape
    x = rald_intensity(cube, model.cfg.radar_shape)[None]                  # (1, 32, 16, 8)
    y = occupancy_target(grid, truth)[None]                                 # (1, 32, 16, 8)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.0)
    losses = []
    for _ in range(120):
        loss = weighted_bce(model(x), y, 4.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    with torch.no_grad():
        cloud = occupancy_points(grid, torch.sigmoid(model(x)[0])).numpy()
    cd = chamfer_distance(cloud, truth)
    floor = chamfer_distance(occupancy_points(grid, y[0]).numpy(), truth)
    assert losses[-1] < 0.2 * losses[0]
    assert cd < 0.6 * cd_oscfar, (floor, cd, cd_oscfar)
