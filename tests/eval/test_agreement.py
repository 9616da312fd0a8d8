"""Pairing two inference paths' detections of one frame, on hand-worked frames."""
import pytest
import torch

from radarpc.eval.agreement import HALF_CELL, pair_detections
from radarpc.boxes import Detections


def _dets(rows):
    t = torch.tensor(rows, dtype=torch.float32).reshape(-1, 2)
    return Detections(torch.linspace(0.9, 0.1, len(t)), t[:, 0], t[:, 1], torch.tensor([len(t)]))


def test_pairs_within_half_a_cell_and_reports_the_rest():
    assert HALF_CELL == (0.4, 0.4)
    a = _dets([(10.0, 0.0), (20.0, 5.0), (30.0, -3.0)])
    b = _dets([(10.3, 0.1), (20.0, 5.5), (29.9, -3.0), (50.0, 0.0)])
    pairs, lone_a, lone_b = pair_detections(a, b)
    # (20, 5) and (20, 5.5) are 0.5 deg apart, more than half a 0.8-deg cell
    assert sorted(pairs) == [(0, 0), (2, 2)] and lone_a == [1] and lone_b == [1, 3]
    # a wider window pairs them too
    pairs, lone_a, lone_b = pair_detections(a, b, half_cell=(0.4, 0.6))
    assert sorted(pairs) == [(0, 0), (1, 1), (2, 2)] and lone_a == [] and lone_b == [3]


def test_pairs_nearest_first_and_one_to_one():
    # 10.25 lies 0.05 m from 10.3 and 0.25 m from 10.0: the nearer takes it, the other stays alone
    pairs, lone_a, lone_b = pair_detections(_dets([(10.0, 0.0), (10.3, 0.0)]), _dets([(10.25, 0.0)]))
    assert pairs == [(1, 0)] and lone_a == [0] and lone_b == []
    pairs, lone_a, lone_b = pair_detections(_dets([]), _dets([(10.0, 0.0)]))
    assert pairs == [] and lone_a == [] and lone_b == [0]
    # the cost weighs range and azimuth by their half cells: 0.2 m + 0.0 deg (0.5) beats
    # 0.0 m + 0.3 deg (0.75); pairs come out in the order they are taken
    pairs, _, _ = pair_detections(_dets([(10.0, 0.0), (12.0, 0.0)]), _dets([(12.0, 0.3), (10.2, 0.0)]))
    assert pairs == [(0, 1), (1, 0)]
    with pytest.raises(ValueError, match="half_cell"):
        pair_detections(_dets([]), _dets([]), half_cell=(0.0, 0.4))


def _greedy_by_argmin(a, b, half_cell=HALF_CELL):
    """The definition, step by step: the cheapest pair left over the whole matrix (argmin, so the
    first in row-major order among equal costs), then its row and column are taken out."""
    import math
    dr = (a.range_m[:, None] - b.range_m[None, :]).abs()
    da = (a.azimuth_deg[:, None] - b.azimuth_deg[None, :]).abs()
    ok = (dr <= half_cell[0]) & (da <= half_cell[1])
    cost = torch.where(ok, dr / half_cell[0] + da / half_cell[1], torch.full_like(dr, math.inf))
    pairs = []
    while cost.numel() and bool(torch.isfinite(cost).any()):
        i, j = divmod(int(torch.argmin(cost)), cost.shape[1])
        pairs.append((i, j))
        cost[i, :] = math.inf
        cost[:, j] = math.inf
    return pairs


def test_pairs_equal_the_step_by_step_definition_on_crowded_frames_with_ties():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        # positions on a 0.1 grid: many candidates per detection and many equal costs
        a = _dets((torch.randint(0, 12, (40, 2), generator=g) * 0.1 + torch.tensor([10.0, 0.0])).tolist())
        b = _dets((torch.randint(0, 12, (35, 2), generator=g) * 0.1 + torch.tensor([10.0, 0.0])).tolist())
        pairs, lone_a, lone_b = pair_detections(a, b)
        want = _greedy_by_argmin(a, b)
        assert pairs == want and len(pairs) > 10
        assert lone_a == sorted(set(range(40)) - {i for i, _ in want})
        assert lone_b == sorted(set(range(35)) - {j for _, j in want})
