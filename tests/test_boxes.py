"""The detection contract: RADIal's fixed evaluation boxes and the offset-batched detection type."""
from __future__ import annotations

import math

import pytest
import torch

from radarpc.boxes import Detections, box_iou, ra_to_box_xy


def test_box_iou_hand_values():
    xy = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
    other = torch.tensor([[0.0, 0.0], [0.6, 0.0], [0.0, 2.0], [1.8, 0.0], [0.0, -4.0], [0.9, 1.0]], dtype=torch.float64)
    # (1.8 - dx)(4 - dy) / (14.4 - that)
    want = [1.0, 4.8 / 9.6, 3.6 / 10.8, 0.0, 0.0, 0.9 * 3 / (14.4 - 2.7)]
    assert box_iou(xy, other)[0].tolist() == pytest.approx(want, abs=1e-12)
    # x = R sin A, y = R cos A
    assert ra_to_box_xy(torch.tensor(10.0, dtype=torch.float64), torch.tensor(30.0, dtype=torch.float64)).tolist() == \
        pytest.approx([5.0, 10 * math.sqrt(3) / 2])


def test_ra_to_box_xy_numpy_and_torch_paths_agree():
    # on the CPU the boxes come from numpy in float64, elsewhere (and under autograd) from torch:
    # the same x = R sin A, y = R cos A, in the inputs' dtype and broadcast shape
    g = torch.Generator().manual_seed(0)
    r = torch.rand(5000, generator=g) * 100                                    # m
    a = torch.rand(5000, generator=g) * 180 - 90                               # deg
    xy = ra_to_box_xy(r, a)
    assert xy.dtype == torch.float32 and xy.shape == (5000, 2)
    exact = torch.tensor([[R * math.sin(math.radians(A)), R * math.cos(math.radians(A))]
                          for R, A in zip(r.tolist(), a.tolist())], dtype=torch.float64)  # libm, per element
    # float64 (a few of its ulps) then one rounding to float32 (half an ulp of |x|, |y| <= R)
    tol = (0.5 * torch.finfo(torch.float32).eps + 8 * torch.finfo(torch.float64).eps) * r.double()[:, None]
    assert ((xy.double() - exact).abs() <= tol).all()
    # broadcasting (one range, many azimuths) and float64 kept
    xy64 = ra_to_box_xy(torch.tensor(10.0, dtype=torch.float64), torch.tensor([0.0, 90.0], dtype=torch.float64))
    assert xy64.dtype == torch.float64 and xy64.flatten().tolist() == pytest.approx([0.0, 10.0, 10.0, 0.0], abs=1e-14)
    # integer inputs give the default float dtype, as the torch path does
    xyi = ra_to_box_xy(torch.tensor([10]), torch.tensor([90]))
    assert xyi.dtype == torch.get_default_dtype() and xyi.flatten().tolist() == pytest.approx([10.0, 0.0], abs=1e-6)
    # the autograd path (torch) gives the same boxes and a gradient: d x / d R = sin A
    rg = r[:3].double().requires_grad_()
    xg = ra_to_box_xy(rg, a[:3].double())
    assert torch.allclose(xg, exact[:3], rtol=0, atol=1e-12)
    xg[:, 0].sum().backward()
    assert rg.grad.tolist() == pytest.approx([math.sin(math.radians(A)) for A in a[:3].tolist()], abs=1e-15)


def test_detections_from_frames_sorts_and_batches():
    det = Detections.from_frames([torch.tensor([[0.2, 10.0, 1.0], [0.9, 20.0, 2.0]]), torch.zeros(0, 3),
                                  torch.tensor([[0.5, 30.0, 3.0]])])
    assert len(det) == 3 and det.offset.tolist() == [2, 2, 3]
    assert det.score.tolist() == pytest.approx([0.9, 0.2, 0.5])
    assert det.frame(1).num_detections == 0 and det.frame(-1).range_m.tolist() == [30.0]
    with pytest.raises(ValueError, match=r"frame 0: expected a \(K, 3\)"):
        Detections.from_frames([torch.zeros(2, 2)])
