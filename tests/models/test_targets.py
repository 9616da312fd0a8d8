"""RADIal range-azimuth targets: encoding, decoding and NMS (the boxes: tests/test_boxes.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radarpc.models.targets import (
    AZIMUTH_CELL_DEG,
    RADIAL_REG_MEAN,
    RADIAL_REG_STD,
    RANGE_CELL_M,
    TargetConfig,
    decode_detections,
    encode_batch,
    encode_targets,
    nms,
)

CFG = TargetConfig()
# decoded = i c + float32(t) sd + mu in float32: a few ulps of values below 104 (ulp 7.6e-6)
TOL = 16 * 7.6e-6


def _labels(ra):
    return torch.tensor(ra, dtype=torch.float32).reshape(-1, 2)


def test_radial_statistics_are_the_moments_of_a_uniform_3x3_patch():
    # mean c/2, std c sqrt(1/12 + 2/3): the docstring's claim, within RADIal's sampling noise
    for k, c in enumerate((RANGE_CELL_M, AZIMUTH_CELL_DEG)):
        assert RADIAL_REG_MEAN[k] == pytest.approx(c / 2, rel=0.02)
        assert RADIAL_REG_STD[k] == pytest.approx(c * math.sqrt(1 / 12 + 2 / 3), rel=0.005)


def test_encode_paints_the_patch_and_offsets_from_each_cell_corner():
    r, a = 20.5, -3.3
    m = encode_targets(_labels([r, a]))
    assert m.shape == (3, 128, 224) and m.dtype == torch.float32
    i0, j0 = math.floor(r / RANGE_CELL_M), math.floor(a / AZIMUTH_CELL_DEG) + 112
    pos = torch.nonzero(m[0]).tolist()
    assert sorted(pos) == [[i, j] for i in range(i0 - 1, i0 + 2) for j in range(j0 - 1, j0 + 2)]
    for i, j in pos:
        assert m[1, i, j].item() == pytest.approx((r - i * RANGE_CELL_M - RADIAL_REG_MEAN[0]) / RADIAL_REG_STD[0], abs=1e-6)
        assert m[2, i, j].item() == pytest.approx((a - (j - 112) * AZIMUTH_CELL_DEG - RADIAL_REG_MEAN[1]) / RADIAL_REG_STD[1],
                                                  abs=1e-6)
    assert int((m[1:] != 0).sum()) <= 18        # nothing painted off the patch


def test_encode_then_decode_gives_back_every_label():
    rng = np.random.default_rng(0)
    # labels on a coarse grid (patches never touch), jittered inside their cells
    ii = np.arange(2, 126, 5)
    jj = np.arange(2, 222, 7)
    gi, gj = np.meshgrid(ii, jj, indexing="ij")
    r = (gi.ravel() + rng.uniform(0, 1, gi.size)) * RANGE_CELL_M
    a = (gj.ravel() - 112 + rng.uniform(0, 1, gi.size)) * AZIMUTH_CELL_DEG
    lab = _labels(np.stack([r, a], 1))
    m = encode_targets(lab)
    det = decode_detections(m[None], threshold=0.5, nms_iou=None)
    assert det.num_detections == 9 * len(r)           # every patch cell decodes its label
    got = det.rows()[:, 1:].double()
    d = (got[:, None, :] - lab.double()[None]).abs()    # (9n, n, 2)
    near = d.amax(-1).min(1)
    assert float(near.values.max()) < TOL             # far inside half a cell
    assert torch.bincount(near.indices, minlength=len(r)).eq(9).all()


def test_nms_keeps_one_detection_per_separated_vehicle():
    lab = _labels([[10.2, 0.3], [30.7, -20.1], [55.0, 45.5], [80.3, -60.0]])
    det = decode_detections(encode_targets(lab)[None])
    assert det.num_detections == 4
    got = det.rows()[:, 1:]
    for r, a in lab.tolist():
        assert float((got - torch.tensor([r, a])).abs().amax(1).min()) < TOL


def test_edges_are_clipped_and_outside_labels_skipped():
    m = encode_targets(_labels([[0.3, 0.0], [50.0, 89.5], [50.0, -89.5], [110.0, 0.0], [50.0, 90.0], [-1.0, 0.0]]))
    assert int(m[0].sum()) == 6 + 6 + 6     # 2 x 3 at range 0, 3 x 2 at each azimuth edge
    assert m[0, 0:2, 111:114].all() and m[0, 61:64, 222:224].all() and m[0, 61:64, 0:2].all()


def test_overlapping_patches_regress_the_nearer_vehicle():
    c_r = RANGE_CELL_M
    # rows 10 and 12 hold the vehicles; row 11 is in both patches and 0.7 cell from the second
    lab = _labels([[10.5 * c_r, 0.4], [12.2 * c_r, 0.4]])
    for order in (lab, lab.flip(0)):                    # whatever the label order
        m = encode_targets(order)
        det = decode_detections(m[None], threshold=0.5, nms_iou=None)
        assert det.num_detections == 15
        row11 = decode_detections(m[None] * (torch.arange(128) == 11)[:, None], threshold=0.5, nms_iou=None)
        assert row11.num_detections == 3
        assert row11.range_m.tolist() == pytest.approx([12.2 * c_r] * 3, abs=TOL)


def test_encode_batch_follows_label_offsets():
    lab = _labels([[20.0, 1.0], [40.0, -5.0], [60.0, 10.0]])
    maps = encode_batch(lab, torch.tensor([1, 1, 3]))
    assert maps.shape == (3, 3, 128, 224)
    assert [int(m[0].sum()) for m in maps] == [9, 0, 18]
    det = decode_detections(maps)
    assert det.offset.tolist() == [1, 1, 3]
    assert sorted(det.frame(2).range_m.tolist()) == pytest.approx([40.0, 60.0], abs=TOL)


def test_decode_rejects_a_wrong_shape():
    with pytest.raises(ValueError, match=r"maps must be \(B, 3, 128, 224\)"):
        decode_detections(torch.zeros(1, 3, 64, 224))
    with pytest.raises(ValueError, match="labels must be"):
        encode_targets(torch.zeros(3))
    with pytest.raises(ValueError, match="patch must be an odd"):
        TargetConfig(patch=2)


def test_nms_hand_case():
    # A suppresses B (same place); D overlaps only B, which was suppressed, so D stays; C is far.
    xy = torch.tensor([[0.0, 20.0], [0.0, 20.5], [0.0, 30.0], [0.0, 24.0], [0.3, 20.2]])
    score = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.9])
    assert nms(score, xy, 0.05).tolist() == [0, 2, 3]      # tie 0 / 4: the first listed wins
    # suppression at IoU >= threshold (float64 boxes: IoU of 0 and 1 is 6.3 / 8.1 within 1e-15)
    iou01 = 3.5 * 1.8 / (14.4 - 3.5 * 1.8)
    xy64 = xy[:2].double()
    assert nms(score[:2], xy64, iou01 - 1e-9).tolist() == [0]
    assert nms(score[:2], xy64, iou01 + 1e-9).tolist() == [0, 1]
    assert nms(torch.zeros(0), torch.zeros(0, 2), 0.05).numel() == 0


def _greedy_reference(score, boxes, thr):
    """Textbook greedy NMS on explicit rectangles (x0, y0, x1, y1), float64, O(K^2)."""
    order = sorted(range(len(score)), key=lambda k: -score[k])          # sorted() is stable
    keep = []
    for i in order:
        ok = True
        for j in keep:
            w = min(boxes[i][2], boxes[j][2]) - max(boxes[i][0], boxes[j][0])
            h = min(boxes[i][3], boxes[j][3]) - max(boxes[i][1], boxes[j][1])
            inter = max(w, 0.0) * max(h, 0.0)
            area = lambda b: (b[2] - b[0]) * (b[3] - b[1])
            if inter / (area(boxes[i]) + area(boxes[j]) - inter) >= thr:
                ok = False
                break
        if ok:
            keep.append(i)
    return keep


@pytest.mark.parametrize("thr", [0.05, 0.3])
def test_nms_matches_a_textbook_greedy_nms(thr):
    rng = np.random.default_rng(4)
    xy = np.c_[rng.uniform(-6, 6, 400), rng.uniform(5, 25, 400)]        # dense: many overlaps
    score = rng.choice(np.linspace(0.05, 1, 40), 400)                   # with ties
    boxes = [(x - 0.9, y, x + 0.9, y + 4.0) for x, y in xy]
    got = nms(torch.from_numpy(score), torch.from_numpy(xy), thr).tolist()
    assert got == _greedy_reference(score.tolist(), boxes, thr)
    with pytest.raises(ValueError, match="iou_threshold must be > 0"):
        nms(torch.from_numpy(score), torch.from_numpy(xy), 0.0)
