"""False alarms by RADIal's rule, and their causes from hand-placed scatterers."""
import pytest
import torch

from radarpc.boxes import Detections
from radarpc.eval.detection import DetectionMetrics
from radarpc.eval.false_alarms import FALSE_ALARM_CAUSES, false_alarm_causes, false_alarm_mask


def _cause(name: str) -> int:
    return FALSE_ALARM_CAUSES.index(name)


def test_false_alarms_by_hand():
    labels = torch.tensor([[20.0, 0.0], [50.0, 10.0], [120.0, 0.0]])      # the last is outside the gate
    score = torch.tensor([0.9, 0.9, 0.2, 0.25, 0.9, 0.9], dtype=torch.float64)
    range_m = torch.tensor([20.0, 20.0, 40.0, 40.0, 101.0, 120.0])
    azimuth = torch.tensor([0.0, 5.7, 0.0, 0.0, 0.0, 0.0])
    # on the label; 2 m sideways (x = 20 sin 5.7 deg = 1.99 m > 1.8 m, no overlap); at the threshold
    # (not above it); above it, no label; near edge beyond 100 m; on the label outside the gate
    fa = false_alarm_mask(score, range_m, azimuth, labels, threshold=0.2)
    assert fa.tolist() == [False, True, False, True, False, False]
    # a float32 0.2 is 0.2000000030 > 0.2, as the metric counts it
    fa = false_alarm_mask(score.float(), range_m, azimuth, labels, threshold=0.2)
    assert fa.tolist() == [False, True, True, True, False, False]


def test_false_alarms_are_the_false_positives_of_the_metric():
    g = torch.Generator().manual_seed(0)
    metrics = DetectionMetrics()
    n_fa = 0
    for _ in range(20):
        k, m = int(torch.randint(0, 12, (1,), generator=g)), int(torch.randint(0, 4, (1,), generator=g))
        labels = torch.stack([torch.rand(m, generator=g) * 110, torch.rand(m, generator=g) * 60 - 30], 1)
        # detections scattered around the labels and elsewhere, so that both kinds occur
        near = labels[torch.randint(0, max(m, 1), (k,), generator=g)] if m else torch.zeros(k, 2)
        jitter = torch.randn(k, 2, generator=g) * torch.tensor([1.5, 1.0])
        ra = torch.where(torch.rand(k, 1, generator=g) < 0.6, near + jitter,
                         torch.stack([torch.rand(k, generator=g) * 110, torch.rand(k, generator=g) * 60 - 30], 1))
        score = torch.rand(k, generator=g)
        score[:2] = 0.2                                                  # float32 0.2, just above 0.2
        dets = Detections(score, ra[:, 0], ra[:, 1], torch.tensor([k]))
        metrics.update(dets, labels, torch.tensor([m]))
        n_fa += int(false_alarm_mask(score, ra[:, 0], ra[:, 1], labels).sum())
    report = metrics.compute()
    assert n_fa == report.fp[report.thresholds.index(0.2)] and n_fa > 0


def test_causes_by_hand():
    # five false-alarm boxes (near-edge centres); the box spans x +- 0.9 m, y .. y + 4 m, grown by 1 m
    boxes = torch.tensor([[0.0, 20.0], [10.0, 50.0], [-5.0, 30.0], [5.0, 10.0], [0.0, 70.0], [-10.0, 40.0]])
    xy = torch.tensor([
        [0.3, 21.0], [0.0, 23.5],      # box 0: a labelled vehicle's scatterer beats static clutter
        [10.0, 49.5], [10.5, 52.0],    # box 1: the ghost is stronger than the unlabelled vehicle
        [-5.0, 29.0],                  # box 2: moving, unowned, on the grown edge (dy = -1): a cyclist
        [6.85, 12.0],                  # box 3: static, at dx = 1.85 (inside the grown edge)
        [1.91, 72.0], [0.0, 75.01],    # box 4: just outside the grown box on both sides: nothing
        [-10.0, 41.0],                 # box 5: an unlabelled vehicle alone
    ])
    power = torch.tensor([1.0, 0.5, 2.0, 1.0, 1.0, 1.0, 9.0, 9.0, 1.0])
    owner = torch.tensor([3, -1, -2, 4, -1, -1, 3, 3, 4])          # the ghost belongs to no vehicle
    labelled = torch.tensor([True, False, False, False, False, False, True, True, False])
    moving = torch.tensor([True, False, True, True, True, False, True, True, True])
    ghost = torch.tensor([False, False, True, False, False, False, False, False, False])
    cause = false_alarm_causes(boxes, xy, power, owner, labelled, moving, ghost)
    assert [FALSE_ALARM_CAUSES[c] for c in cause] == [
        "labelled vehicle, box off", "mirror ghost", "moving person or cyclist", "static clutter", "nothing",
        "vehicle without a label"]
    # without the margin, the edge scatterers of boxes 2 and 3 fall outside
    cause = false_alarm_causes(boxes, xy, power, owner, labelled, moving, ghost, margin_m=0.0)
    assert cause[2] == cause[3] == _cause("nothing")
    # a frame without scatterers
    empty = torch.zeros(0)
    cause = false_alarm_causes(boxes, torch.zeros(0, 2), empty, empty.long(), empty.bool(), empty.bool(),
                               empty.bool())
    assert (cause == _cause("nothing")).all()


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match=r"power must be \(2,\) like scatterer_xy's rows, got \(3,\)"):
        false_alarm_causes(torch.zeros(1, 2), torch.zeros(2, 2), torch.zeros(3), torch.zeros(2).long(),
                           torch.zeros(2).bool(), torch.zeros(2).bool(), torch.zeros(2).bool())
    with pytest.raises(ValueError, match=r"ghost must be \(2,\) like scatterer_xy's rows, got \(1,\)"):
        false_alarm_causes(torch.zeros(1, 2), torch.zeros(2, 2), torch.zeros(2), torch.zeros(2).long(),
                           torch.zeros(2).bool(), torch.zeros(2).bool(), torch.zeros(1).bool())
    with pytest.raises(ValueError, match=r"labels must be \(M, >= 2\)"):
        false_alarm_mask(torch.zeros(2), torch.zeros(2), torch.zeros(2), torch.zeros(3))
