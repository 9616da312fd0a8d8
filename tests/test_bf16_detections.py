"""``benchmarks/bf16_detections.py``'s pairing of two precisions' detections, on hand-worked frames
(the script itself runs on a trained tiny run in tests/training/test_radial_experiment.py)."""
import importlib.util
from pathlib import Path

import torch

from radarpc.models.targets import Detections

_spec = importlib.util.spec_from_file_location(
    "bf16_detections", Path(__file__).parents[1] / "benchmarks" / "bf16_detections.py")
bf16_detections = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bf16_detections)


def _dets(rows):
    t = torch.tensor(rows, dtype=torch.float32).reshape(-1, 2)
    return Detections(torch.linspace(0.9, 0.1, len(t)), t[:, 0], t[:, 1], torch.tensor([len(t)]))


def test_pairs_within_half_a_cell_and_reports_the_rest():
    a = _dets([(10.0, 0.0), (20.0, 5.0), (30.0, -3.0)])
    b = _dets([(10.3, 0.1), (20.0, 5.5), (29.9, -3.0), (50.0, 0.0)])
    pairs, lone_a, lone_b = bf16_detections.pair_detections(a, b)
    # (20, 5) and (20, 5.5) are 0.5 deg apart, more than half a 0.8-deg cell
    assert sorted(pairs) == [(0, 0), (2, 2)] and lone_a == [1] and lone_b == [1, 3]


def test_pairs_nearest_first_and_one_to_one():
    pairs, lone_a, lone_b = bf16_detections.pair_detections(_dets([(10.0, 0.0), (10.3, 0.0)]),
                                                            _dets([(10.25, 0.0)]))
    assert pairs == [(1, 0)] and lone_a == [0] and lone_b == []
    pairs, lone_a, lone_b = bf16_detections.pair_detections(_dets([]), _dets([(10.0, 0.0)]))
    assert pairs == [] and lone_a == [] and lone_b == [0]
