"""Near misses and the data-side ceiling on hand-worked frames, against the metric's own box IoU
and its ``fn`` / ``fn_near`` counts."""
import json
import math

import numpy as np
import pytest
import torch

from radarpc.eval.detection import evaluate_detections, match_frame
from radarpc.eval.localisation import (
    FAILING_AXES,
    LATERAL_TOLERANCE_M,
    PLACEMENT_RULES,
    failing_axis,
    lateral_placement,
    near_miss_summary,
    near_misses,
    nearest_detection_offsets,
    placement_summary,
    point_reach,
    range_bins,
)
from radarpc.boxes import Detections, box_iou


def test_range_bins_are_half_open():
    got = range_bins(np.array([0.0, 29.99, 30.0, 59.9, 60.0, 150.0]))
    assert list(got) == ["0-30", "30-60", ">=60"]
    assert got["0-30"].tolist() == [True, True, False, False, False, False]
    assert got["30-60"].tolist() == [False, False, True, True, False, False]
    assert got[">=60"].tolist() == [False, False, False, False, True, True]
    assert list(range_bins(np.array([5.0]), (10.0,))) == ["0-10", ">=10"]
    with pytest.raises(ValueError, match="edges_m"):
        range_bins(np.array([5.0]), (60.0, 30.0))


def test_failing_axis_on_hand_worked_offsets_and_against_box_iou():
    # 1.8 m x 4 m boxes match while (1.8 - |dx|)(4 - |dy|) >= 4.8: alone |dx| <= 0.6, |dy| <= 4 / 3
    got = failing_axis(np.array([0.59, 0.61, 0.0, 0.0, 0.5, 0.7, -0.3]), np.array([0.0, 0.0, 1.3, -1.4, 1.0, 1.5, 0.5]))
    assert got.tolist() == ["match", "x", "match", "y", "x+y", "x,y", "match"]
    # against the metric's own IoU on random offsets (closed-form boxes, an independent formula)
    g = torch.Generator().manual_seed(0)
    d = (torch.rand(2000, 2, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([3.0, 6.0], dtype=torch.float64)
    zero = torch.zeros(1, 2, dtype=torch.float64)

    def iou(off):
        return box_iou(off, zero)[:, 0].numpy()

    full, x_only, y_only = iou(d), iou(d * torch.tensor([1.0, 0.0])), iou(d * torch.tensor([0.0, 1.0]))
    # keep clear of the boundary, where the two formulas may round differently
    clear = (np.abs(full - 0.5) > 1e-9) & (np.abs(x_only - 0.5) > 1e-9) & (np.abs(y_only - 0.5) > 1e-9)
    axis = failing_axis(d[:, 0].numpy(), d[:, 1].numpy())[clear]
    full, x_ok, y_ok = full[clear] >= 0.5, x_only[clear] >= 0.5, y_only[clear] >= 0.5
    assert ((axis == "match") == full).all()
    assert ((axis == "x") == (~full & ~x_ok & y_ok)).all() and ((axis == "y") == (~full & x_ok & ~y_ok)).all()
    assert ((axis == "x+y") == (~full & x_ok & y_ok)).all() and ((axis == "x,y") == (~x_ok & ~y_ok)).all()
    assert {"match", *FAILING_AXES} <= set(axis.tolist())
    with pytest.raises(ValueError, match="iou_threshold"):
        failing_axis(0.0, 0.0, 1.0)


def _frame():
    """Three gated labels straight ahead at 20, 50 and 80 m (and one at 3 m, outside the gate);
    a detection 0.5 m beyond the first, one level with the second but 0.9 m across, and one on the
    third scored below 0.2."""
    a1 = math.degrees(math.asin(0.9 / 50))
    labels = torch.tensor([[20.0, 0.0], [50.0, 0.0], [80.0, 0.0], [3.0, 0.0]], dtype=torch.float64)
    score = torch.tensor([0.9, 0.6, 0.1])
    range_m = torch.tensor([20.5, 50.0, 80.0], dtype=torch.float64)
    azimuth = torch.tensor([0.0, a1, 0.0], dtype=torch.float64)
    return score, range_m, azimuth, labels, a1


def test_nearest_detection_offsets_on_a_hand_worked_frame():
    score, range_m, azimuth, labels, a1 = _frame()
    rows = nearest_detection_offsets(match_frame(score, range_m, azimuth, labels), 0.2).numpy()
    dy1 = 50 * math.cos(math.radians(a1)) - 50                    # the 0.9 m-across detection's y
    assert rows.shape == (3, 6)                                    # the 3 m label is gated out
    assert rows[0].tolist() == pytest.approx([20.0, 1.0, 0.0, 0.5, 0.5, 0.0], abs=1e-12)
    assert rows[1].tolist() == pytest.approx([50.0, 0.0, 0.9, dy1, 0.0, a1], abs=1e-12)
    # the 80 m label's own detection scores 0.1: the nearest counted one is the 50 m detection
    assert rows[2].tolist() == pytest.approx([80.0, 0.0, 0.9, 50 + dy1 - 80, -30.0, a1], abs=1e-12)
    assert near_misses(rows).tolist() == [False, True, False]
    # nothing counts above 0.95: no detection, NaN offsets, no near miss
    none = nearest_detection_offsets(match_frame(score, range_m, azimuth, labels), 0.95).numpy()
    assert none[:, :2].tolist() == [[20.0, 0.0], [50.0, 0.0], [80.0, 0.0]] and np.isnan(none[:, 2:]).all()
    assert not near_misses(none).any()
    # at 0.05 the 80 m label's detection counts and matches it
    assert nearest_detection_offsets(match_frame(score, range_m, azimuth, labels), 0.05)[:, 1].tolist() == [1, 0, 1]


def test_near_miss_summary_on_a_hand_worked_frame():
    score, range_m, azimuth, labels, a1 = _frame()
    rows = nearest_detection_offsets(match_frame(score, range_m, azimuth, labels), 0.2).numpy()
    s = near_miss_summary(rows, 0.8)
    assert (s["labels"], s["matched"], s["near_miss"], s["far_miss"]) == (3, 1, 1, 1)
    # the near miss is 0.9 m across and 8 mm along: it fails on x alone
    assert s["near_miss_by_axis"] == {"x": 1, "y": 0, "x+y": 0, "x,y": 0}
    med = s["near_miss_median"]
    assert med["abs_dx_m"] == pytest.approx(0.9)
    assert med["abs_dy_m"] == pytest.approx(50 * (1 - math.cos(math.radians(a1))))
    assert med["abs_d_range_m"] == 0.0 and med["abs_d_azimuth_deg"] == pytest.approx(a1)
    assert med["abs_d_azimuth_cells"] == pytest.approx(a1 / 0.8)
    assert s["by_range_m"]["0-30"] == {"labels": 1, "matched": 1, "near_miss": 0, "far_miss": 0,
                                       "near_miss_by_axis": dict.fromkeys(FAILING_AXES, 0)}
    assert (s["by_range_m"]["30-60"]["near_miss"], s["by_range_m"][">=60"]["far_miss"]) == (1, 1)
    json.dumps(s, allow_nan=False)
    # without near misses there are no medians
    assert "near_miss_median" not in near_miss_summary(rows[[0, 2]], 0.8)
    assert near_miss_summary(np.zeros((0, 6)), 0.8)["labels"] == 0


def test_near_miss_summary_counts_the_metrics_misses():
    # random frames: labels, detections jittered around them and false alarms; at each threshold
    # the summary's misses and near misses are the metric's fn and fn_near
    g = np.random.default_rng(1)
    frames, label_rows, offsets = [], [], []
    for _ in range(30):
        lab = np.stack([g.uniform(3, 105, 4), g.uniform(-40, 40, 4)], 1)
        det = [(r + g.normal(0, 1.0), a + g.normal(0, 1.5), g.uniform(0, 1)) for r, a in lab for _ in range(2)]
        det += [(g.uniform(5, 100), g.uniform(-40, 40), g.uniform(0, 1)) for _ in range(3)]
        d = torch.tensor(det, dtype=torch.float64)
        frames.append(d[:, [2, 0, 1]])
        label_rows.append(torch.from_numpy(lab))
    dets = Detections.from_frames(frames)
    labels = torch.cat(label_rows)
    label_offset = torch.cumsum(torch.tensor([len(x) for x in label_rows]), 0)
    for t in (0.2, 0.5, 0.8):
        rep = evaluate_detections(dets, labels, label_offset, thresholds=(t,), fixed_threshold=t)
        offsets = np.concatenate([
            nearest_detection_offsets(match_frame(f[:, 0], f[:, 1], f[:, 2], lab), t).numpy()
            for f, lab in zip(frames, label_rows)])
        s = near_miss_summary(offsets, 0.8)
        assert s["labels"] == rep.n_labels and s["labels"] - s["matched"] == rep.fn_fixed
        assert s["near_miss"] == rep.fn_near_fixed > 0 and sum(s["near_miss_by_axis"].values()) == s["near_miss"]
        assert s["labels"] == s["matched"] + s["near_miss"] + s["far_miss"]
        assert sum(b["labels"] for b in s["by_range_m"].values()) == s["labels"]


def test_point_reach_on_a_hand_worked_frame():
    labels = torch.tensor([[0.0, 20.0], [5.0, 50.0]], dtype=torch.float64)
    # p0 0.3 m across and 0.5 m along from label 0 (IoU 5.25 / 9.15 >= 0.5); p1 exactly 3 m beyond
    # it (not closer than 3 m); p2 far from both
    points = torch.tensor([[0.3, 20.5], [0.0, 23.0], [10.0, 10.0]], dtype=torch.float64)
    r = point_reach(labels, points)
    assert r.nearest_m.tolist() == pytest.approx([math.hypot(0.3, 0.5), math.hypot(5.0, 27.0)], rel=1e-12)
    assert r.matched.tolist() == [True, False] and r.support.tolist() == [1, 0]
    assert r.near_a_label.tolist() == [True, False, False]
    # a wider radius takes p1 in
    assert point_reach(labels, points, 3.5).support.tolist() == [2, 0]
    # the box rule, not the distance: 0.7 m across and level is close but does not match
    assert not point_reach(labels[:1], torch.tensor([[0.7, 20.0]], dtype=torch.float64)).matched.any()
    empty = point_reach(labels, torch.zeros(0, 2))
    assert empty.nearest_m.tolist() == [math.inf] * 2 and not empty.matched.any() and empty.support.tolist() == [0, 0]
    assert empty.near_a_label.shape == (0,)
    assert point_reach(torch.zeros(0, 2), points).near_a_label.tolist() == [False] * 3
    with pytest.raises(ValueError, match="radius_m"):
        point_reach(labels, points, 0.0)
    with pytest.raises(ValueError, match=r"\(L, 2\) and \(N, 2\)"):
        point_reach(labels, points[:, :1])


def test_lateral_placement_on_a_hand_worked_frame():
    assert LATERAL_TOLERANCE_M == pytest.approx(0.6, abs=1e-12)
    labels = torch.tensor([[0.0, 50.0], [10.0, 20.0]], dtype=torch.float64)
    # label 0's box grown by 0.6 m: |dx| <= 1.5, -0.6 <= dy <= 4.6; the last two points lie outside it
    points = torch.tensor([[-0.9, 51.0], [0.9, 53.0], [0.3, 49.5], [1.6, 51.0], [0.0, 54.7]], dtype=torch.float64)
    amp = torch.tensor([2.0, 1.0, 1.0, 9.0, 9.0])
    got = lateral_placement(labels, points, amp)
    # extent centre (-0.9 + 0.9) / 2 = 0; strongest -0.9; power centroid (-0.9 * 4 + 0.9 + 0.3) / 6 = -0.4
    assert got[0].tolist() == pytest.approx([3, 0.0, -0.9, -0.4], abs=1e-12)
    assert got[1, 0] == 0 and torch.isnan(got[1, 1:]).all()
    assert torch.isnan(lateral_placement(labels, torch.zeros(0, 2), torch.zeros(0))[:, 1:]).all()
    with pytest.raises(ValueError, match="amplitude"):
        lateral_placement(labels, points, amp[:2])
    with pytest.raises(ValueError, match="grow_m"):
        lateral_placement(labels, points, amp, grow_m=-0.1)
    # a label without a point counts as not placed; shares by label range
    rows = np.array([[3, 0.0, -0.9, -0.4], [0, np.nan, np.nan, np.nan], [1, 0.7, 0.7, 0.7]])
    s = placement_summary(np.array([50.0, 20.0, 70.0]), rows)
    assert s["all"]["labels"] == 3 and s["all"]["share_without_a_point"] == pytest.approx(1 / 3)
    assert s["all"]["share_placed_within_tolerance"] == pytest.approx(
        {"extent_centre": 1 / 3, "strongest_point": 0.0, "power_centroid": 1 / 3})
    assert s["30-60"]["share_placed_within_tolerance"]["extent_centre"] == 1.0
    assert s["0-30"]["labels"] == 1 and s[">=60"]["share_placed_within_tolerance"]["extent_centre"] == 0.0
    # bins are [lo, hi): 30 m and 60 m open the next bin; |dx| equal to the tolerance is placed;
    # an empty bin gives None, not NaN (strict JSON)
    edge = placement_summary(np.array([30.0, 60.0]), np.array([[1, 0.6, 0.6, 0.6], [1, -0.6, 0.7, 0.0]]))
    assert edge["0-30"] == {"labels": 0, "median_points_in_grown_box": None, "share_without_a_point": None,
                            "share_placed_within_tolerance": dict.fromkeys(PLACEMENT_RULES)}
    assert edge["30-60"]["labels"] == 1 and edge[">=60"]["labels"] == 1
    assert edge["all"]["share_placed_within_tolerance"] == {"extent_centre": 1.0, "strongest_point": 0.5,
                                                            "power_centroid": 1.0}
    json.dumps(edge, allow_nan=False)
    # all inside amplitudes 0: the strongest is still an inside point, the centroid undefined
    z = lateral_placement(labels[:1], torch.tensor([[3.0, 50.0], [0.5, 51.0]], dtype=torch.float64),
                          torch.tensor([5.0, 0.0]))
    assert z[0, :3].tolist() == [1, 0.5, 0.5] and torch.isnan(z[0, 3])
