"""Operating points against an F1 target on hand-worked counts, and the focal loss's implied
positive rate against scipy's minimiser of the expected loss."""
import json

import numpy as np
import pytest

from radarpc.eval.operating_points import (
    allowed_false_alarms,
    focal_implied_probability,
    operating_points,
    read_operating_points,
)


def test_allowed_false_alarms_on_hand_worked_counts():
    # 100 labels, 80 found: F1 = 160 / (160 + FP + 20) >= 0.8 holds up to FP = 20
    assert allowed_false_alarms(80, 20, 0.8) == 20
    # bounds that are whole numbers count in full: 1220 / (1220 + 68 + 237) = 0.8 exactly, and
    # 12 / (12 + 2 + 1) = 0.8
    assert allowed_false_alarms(610, 237, 0.8) == 68 and allowed_false_alarms(6, 1, 0.8) == 2
    # recall 2/3 reaches F1 0.8 only without false alarms; 0.6 not at all
    assert allowed_false_alarms(200, 100, 0.8) == 0 and allowed_false_alarms(60, 40, 0.8) == -1
    # full recall: FP <= TP (2 / t - 2)
    assert allowed_false_alarms(50, 0, 0.5) == 100
    with pytest.raises(ValueError, match="target F1"):
        allowed_false_alarms(5, 5, 1.2)
    with pytest.raises(ValueError, match="counts"):
        allowed_false_alarms(-1, 5, 0.8)


# 10 labels on 4 frames; at 0.5: 8 found, 2 false alarms -> F1 16 / 20 = 0.8, exactly the allowance
EVALUATION = {"split": "test", "metrics": {"thresholds": [0.2, 0.5], "tp": [9, 8], "fp": [6, 2], "fn": [1, 2],
                                           "n_labels": 10, "n_frames": 4}}


def test_operating_points_on_hand_worked_counts():
    res = operating_points(EVALUATION, 0.8)
    assert res["split"] == "test" and res["n_frames"] == 4 and res["thresholds"] == [0.2, 0.5]
    assert res["recall"] == pytest.approx([0.9, 0.8])
    assert res["false_alarms_per_label"] == pytest.approx([0.6, 0.2])
    assert res["false_alarms_per_frame"] == pytest.approx([1.5, 0.5])
    assert res["f1"] == pytest.approx([18 / 25, 0.8]) and res["false_alarms"] == [6, 2]
    # at 0.2: FP <= 18 x 0.25 - 1 = 3.5 -> 3; at 0.5: 16 x 0.25 - 2 = 2
    assert res["allowed_false_alarms"] == [3, 2]
    # scores in (0.2, 0.5]: 5 detections (1 true, 4 false); above 0.5: 10 (8 true)
    assert res["band_detections"] == [5, 10] and res["band_precision"] == pytest.approx([0.2, 0.8])
    assert res["focal_gamma"] is None and res["implied_probability"] is None
    # cross-entropy's minimiser is the positive rate itself
    assert operating_points(EVALUATION, 0.8, 0.0)["implied_probability"] == pytest.approx([0.2, 0.5])
    # an empty band gives None, not a division by zero
    flat = {"split": "val", "metrics": {**EVALUATION["metrics"], "tp": [8, 8], "fp": [2, 2]}}
    assert operating_points(flat, 0.8)["band_precision"] == [None, 0.8]
    for bad, match in (({"thresholds": [0.5, 0.2]}, "ascend"), ({"tp": [9]}, "one length"),
                       ({"fp": [2, 6]}, "must not rise")):
        with pytest.raises(ValueError, match=match):
            operating_points({"split": "test", "metrics": {**EVALUATION["metrics"], **bad}}, 0.8)


def test_operating_points_from_an_evaluation_file(tmp_path):
    path = tmp_path / "eval_test.json"
    path.write_text(json.dumps(EVALUATION))
    res = read_operating_points(path)
    assert res["file"] == str(path) and res["target_f1"] == 0.8
    assert res["recall"] == pytest.approx([0.9, 0.8]) and res["f1"] == pytest.approx([18 / 25, 0.8])
    assert res["allowed_false_alarms"] == [3, 2] and res["band_precision"] == pytest.approx([0.2, 0.8])
    assert res["implied_probability"] is None  # no run.json beside the file
    # a run folder's focal exponent is read from its run.json
    (tmp_path / "run.json").write_text(json.dumps({"experiment": {"loss": {"focal_gamma": 0.0}}}))
    got = read_operating_points(str(path))
    assert got["focal_gamma"] == 0.0 and got["implied_probability"] == pytest.approx([0.2, 0.5])
    (tmp_path / "run.json").write_text(json.dumps({"experiment": {}}))
    with pytest.raises(ValueError, match="run.json.*focal_gamma"):
        read_operating_points(path)
    (tmp_path / "run.json").unlink()
    for bad in ({"thresholds": [0.5, 0.2]}, {"tp": [9]}, {"fp": [2, 6]}):
        path.write_text(json.dumps({"split": "test", "metrics": {**EVALUATION["metrics"], **bad}}))
        with pytest.raises(ValueError, match="eval_test.json.*expected an evaluation JSON"):
            read_operating_points(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="eval_test.json.*expected an evaluation JSON"):
        read_operating_points(path)
    with pytest.raises(ValueError, match="eval_missing.json.*expected an evaluation JSON"):
        read_operating_points(tmp_path / "eval_missing.json")
    with pytest.raises(ValueError, match="target F1"):
        read_operating_points(path, 0.0)


def test_focal_implied_probability_inverts_the_focal_minimiser():
    from scipy.optimize import minimize_scalar
    for gamma in (0.0, 0.5, 1.0, 2.0):
        for q in (0.003, 0.03, 0.2, 0.5, 0.8):
            def expected_loss(p):
                return q * (1 - p) ** gamma * -np.log(p) + (1 - q) * p ** gamma * -np.log1p(-p)
            p_star = minimize_scalar(expected_loss, bounds=(1e-9, 1 - 1e-9), method="bounded",
                                     options={"xatol": 1e-12}).x
            # the inverse is smooth with slope below 3 here, so p* to 1e-8 gives q to ~1e-7
            assert focal_implied_probability(p_star, gamma) == pytest.approx(q, abs=1e-6)
    with pytest.raises(ValueError, match="scores"):
        focal_implied_probability(np.array([0.0, 0.5]), 2.0)
    with pytest.raises(ValueError, match="gamma"):
        focal_implied_probability(0.5, -1.0)
