"""RADIal detection and freespace metrics on hand-worked cases."""
from __future__ import annotations

import math

import pytest
import torch

from radarpc.boxes import Detections
from radarpc.eval.detection import (
    THRESHOLDS,
    DetectionMetrics,
    FreespaceMetrics,
    evaluate_detections,
    freespace_iou,
    lateral_tolerance_m,
)

ALL = len(THRESHOLDS)


def _det(*frames):
    """Detections from per-frame lists of (score, range, azimuth)."""
    return Detections.from_frames([torch.tensor(f, dtype=torch.float32).reshape(-1, 3) for f in frames])


def _lab(*frames):
    """Offset-batched labels from per-frame lists of (range, azimuth)."""
    rows = [torch.tensor(f, dtype=torch.float32).reshape(-1, 2) for f in frames]
    return torch.cat(rows), torch.cumsum(torch.tensor([len(r) for r in rows]), 0)


def _eval(det, lab):
    return evaluate_detections(det, *lab)


def test_perfect():
    rep = _eval(_det([(0.95, 20.0, 5.0), (0.97, 50.0, -30.0)], [(0.99, 70.0, 0.0)]),
                _lab([(20.0, 5.0), (50.0, -30.0)], [(70.0, 0.0)]))
    assert rep.tp == (3,) * ALL and rep.fp == (0,) * ALL and rep.fn == (0,) * ALL
    assert rep.n_labels == 3
    assert (rep.ap, rep.ar, rep.f1, rep.f1_fixed) == (1.0, 1.0, 1.0, 1.0)
    assert rep.range_error_m == pytest.approx(0, abs=1e-5) and rep.azimuth_error_deg == pytest.approx(0, abs=1e-5)
    assert rep.n_frames == 2


def test_empty_predictions():
    rep = _eval(_det([], []), _lab([(20.0, 5.0)], [(30.0, 1.0), (40.0, 2.0)]))
    assert rep.fn == (3,) * ALL and rep.tp == (0,) * ALL
    assert (rep.ap, rep.ar, rep.f1, rep.f1_fixed) == (0.0, 0.0, 0.0, 0.0)
    assert math.isnan(rep.range_error_m) and math.isnan(rep.azimuth_error_deg)   # no 0/0 error


def test_empty_labels():
    rep = _eval(_det([(0.96, 20.0, 5.0)]), _lab([]))
    assert rep.fp == (1,) * ALL and rep.fn == (0,) * ALL
    assert (rep.ap, rep.ar, rep.f1) == (0.0, 0.0, 0.0)


def test_one_miss():
    rep = _eval(_det([(0.95, 20.0, 5.0)]), _lab([(20.0, 5.0), (60.0, -10.0)]))
    assert rep.precision == (1.0,) * ALL and rep.recall == (0.5,) * ALL
    assert rep.f1 == pytest.approx(2 * 0.5 / 1.5) and rep.f1_fixed == pytest.approx(2 / 3)


def test_one_false_alarm():
    rep = _eval(_det([(0.95, 20.0, 5.0), (0.95, 40.0, 30.0)]), _lab([(20.0, 5.0)]))
    assert rep.precision == (0.5,) * ALL and rep.recall == (1.0,) * ALL
    assert rep.f1 == pytest.approx(2 / 3)


def test_duplicates_are_both_true_positives():
    # RADIal's rule: a detection is a TP if it reaches any label, even one already reached
    rep = _eval(_det([(0.95, 20.0, 5.0), (0.96, 20.2, 5.0)]), _lab([(20.0, 5.0)]))
    assert rep.tp == (2,) * ALL and rep.fp == (0,) * ALL and rep.fn == (0,) * ALL
    assert rep.range_error_m == pytest.approx(0.1, abs=1e-5)   # pairs (0, 0.2): mean 0.1


def test_iou_boundary():
    # azimuth 0: boxes share x; forward shift dy gives IoU = 1.8 (4 - dy) / (14.4 - 1.8 (4 - dy)),
    # which is 0.5 at dy = 4/3. 1e-4 m is far above float32 rounding at 20 m (1.9e-6).
    dy = 4 / 3
    at = _eval(_det([(0.95, 20.0 + dy - 1e-4, 0.0)]), _lab([(20.0, 0.0)]))
    below = _eval(_det([(0.95, 20.0 + dy + 1e-4, 0.0)]), _lab([(20.0, 0.0)]))
    assert at.tp == (1,) * ALL and at.fn == (0,) * ALL
    assert below.tp == (0,) * ALL and below.fp == (1,) * ALL and below.fn == (1,) * ALL


def test_lateral_tolerance_is_where_the_box_iou_crosses_the_threshold():
    from radarpc.boxes import box_iou
    label = torch.tensor([[0.0, 50.0]], dtype=torch.float64)
    for t in (0.3, 0.5, 0.7):
        tol = lateral_tolerance_m(t)
        iou = box_iou(torch.tensor([[tol - 1e-9, 50.0], [-tol - 1e-9, 50.0]], dtype=torch.float64), label)[:, 0]
        assert iou[0] >= t > iou[1]
    assert lateral_tolerance_m() == pytest.approx(0.6, abs=1e-12)
    with pytest.raises(ValueError, match="iou_threshold"):
        lateral_tolerance_m(1.0)


def test_threshold_without_true_positive():
    # score 0.35: counted at 0.1, 0.2, 0.3 only; the other six thresholds have no TP (P = R = 0)
    rep = _eval(_det([(0.35, 30.0, 2.0)]), _lab([(30.3, 2.2)]))
    assert rep.tp == (1, 1, 1, 0, 0, 0, 0, 0, 0)
    assert rep.precision == (1.0, 1.0, 1.0) + (0.0,) * 6 and rep.ap == pytest.approx(3 / 9)
    assert rep.ar == pytest.approx(3 / 9) and rep.f1 == pytest.approx(3 / 9)
    assert rep.f1_fixed == 1.0
    # errors: the mean over the thresholds that have pairs, not divided by zero
    assert rep.range_error_m == pytest.approx(0.3, abs=1e-5)
    assert rep.azimuth_error_deg == pytest.approx(0.2, abs=1e-5)


def test_score_equal_to_threshold_is_not_kept():
    rep = _eval(_det([(0.5, 30.0, 2.0)]), _lab([(30.0, 2.0)]))
    assert rep.tp == (1, 1, 1, 1, 0, 0, 0, 0, 0)


def test_misses_with_a_detection_within_3_m_are_counted_as_localisation_misses():
    # label A (50 m, 0 deg); detection at (50 m, 1 deg): 0.873 m sideways, 0.008 m nearer, so
    # IoU = (1.8 - 0.873) (4 - 0.008) / (14.4 - that) = 0.346 < 0.5: a miss, 0.87 m off.
    # label B (30 m, 10 deg); the only other detection is at (30 m, -10 deg), 10.4 m away.
    rep = _eval(_det([(0.55, 50.0, 1.0), (0.95, 30.0, -10.0)]), _lab([(50.0, 0.0), (30.0, 10.0)]))
    assert rep.tp == (0,) * ALL and rep.fn == (2,) * ALL
    # the near detection is above thresholds 0.1 .. 0.5 only (scores are kept when > t)
    assert rep.fn_near == (1, 1, 1, 1, 1, 0, 0, 0, 0)
    assert (rep.fn_fixed, rep.fn_near_fixed, rep.n_labels) == (2, 1, 2)
    # with no detection at all nothing is near
    rep = _eval(_det([]), _lab([(50.0, 0.0)]))
    assert rep.fn_near == (0,) * ALL and (rep.fn_fixed, rep.fn_near_fixed) == (1, 0)


def test_range_and_azimuth_errors_are_true_errors():
    # two frames, one matched pair each: |dR| = 0.3, 0.1; |dA| = 0.2, 0.4 (degrees, not metres)
    rep = _eval(_det([(0.95, 30.3, 10.2)], [(0.95, 59.9, -20.4)]), _lab([(30.0, 10.0)], [(60.0, -20.0)]))
    assert rep.tp == (2,) * ALL
    assert rep.range_error_m == pytest.approx(0.2, abs=1e-5)
    assert rep.azimuth_error_deg == pytest.approx(0.3, abs=1e-5)
    assert rep.range_error_fixed_m == pytest.approx(0.2, abs=1e-5)


def test_range_gate():
    # labels gated on R in [5, 100]; detections on their near-edge y = R cos A in [5, 100]
    labels = _lab([(4.9, 0.0), (5.0, 0.0), (100.0, 0.0), (100.2, 0.0)])
    dets = _det([(0.96, 4.9, 0.0), (0.96, 5.0, 0.0), (0.96, 100.0, 0.0), (0.96, 100.2, 0.0)])
    rep = _eval(dets, labels)
    assert rep.tp == (2,) * ALL and rep.fp == (0,) * ALL and rep.fn == (0,) * ALL
    assert rep.n_labels == 2                                  # the two outside the gate are not scored
    # a detection at R = 6 m, 40 deg has y = 4.6 m: dropped, so its label (R = 6 m, kept) is missed
    rep = _eval(_det([(0.96, 6.0, 40.0)]), _lab([(6.0, 40.0)]))
    assert rep.tp == (0,) * ALL and rep.fp == (0,) * ALL and rep.fn == (1,) * ALL


def test_accumulates_over_batches_like_one_batch():
    d1, l1 = _det([(0.95, 20.0, 5.0)]), _lab([(20.0, 5.0), (60.0, -10.0)])
    d2, l2 = _det([(0.45, 40.0, 1.0), (0.8, 80.0, 0.0)]), _lab([(40.0, 1.0)])
    m = DetectionMetrics()
    m.update(d1, *l1)
    m.update(d2, *l2)
    both = _eval(_det([(0.95, 20.0, 5.0)], [(0.45, 40.0, 1.0), (0.8, 80.0, 0.0)]),
                 _lab([(20.0, 5.0), (60.0, -10.0)], [(40.0, 1.0)]))
    assert m.compute() == both


def test_mismatched_frames_rejected():
    with pytest.raises(ValueError, match="detections hold 2 frames but label_offset 1"):
        _eval(_det([], []), _lab([]))


def test_freespace_iou_hand_case():
    prob = torch.zeros(2, 1, 256, 224)
    target = torch.zeros(2, 256, 224, dtype=torch.bool)
    prob[0, 0, 0, 0:3] = torch.tensor([0.5, 0.9, 0.7])      # 0.5 counts as free
    target[0, 0, 1:5] = True                                # inter 2 (cols 1, 2), union 5
    prob[0, 0, 124:, :] = 1.0                               # rows >= 124 (beyond 50 m) are not scored
    # frame 1: both empty -> no IoU
    iou = freespace_iou(prob, target)
    assert iou[0].item() == pytest.approx(2 / 5) and math.isnan(iou[1].item())
    m = FreespaceMetrics()
    m.update(prob, target)
    m.update(prob[:1], target[:1] | True)
    # second update: target all free in rows 0..123, prediction free on 3 cells -> 3 / (124 * 224)
    assert m.compute() == pytest.approx((2 / 5 + 3 / (124 * 224)) / 2)
    with pytest.raises(ValueError, match="prob and target"):
        freespace_iou(prob, target[:, :10])
