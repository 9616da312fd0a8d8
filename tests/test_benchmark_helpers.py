"""Helpers of the benchmark scripts on hand-worked cases: ``bf16_detections.py``'s pairing of two
precisions' detections (the script itself runs on a trained tiny run in
tests/training/test_radial_experiment.py), ``fftradnet_official.py``'s MAC count and
``operating_points.py``'s F1 allowance, ``box_offsets.py``'s failing axis,
``detection_ceiling.py``'s placement of boxes from points, ``vehicle_glint.py``'s beamformer,
``training_gradients.py``'s gradient comparison and ``vml_first_call.py`` (run whole)."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from radarpc.boxes import Detections


def _script(name):
    spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


bf16_detections = _script("bf16_detections")


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


def test_conv_gmac_counts_convolutions_and_transposed_convolutions():
    conv_gmac = _script("fftradnet_official")._conv_gmac

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = torch.nn.Conv2d(4, 6, 3, padding=1, groups=2)          # 4 x 6 outputs of 6 channels
            self.up = torch.nn.ConvTranspose2d(6, 5, 3, stride=(2, 1), padding=1, output_padding=(1, 0))
            self.act = torch.nn.ReLU()

        def forward_channels(self, x):
            return self.up(self.act(self.conv(x)))

    # conv: 6 x 4 x 6 outputs, each 3 x 3 x (4 / 2) MACs = 144 x 18; transposed: each of its
    # 6 x 4 x 6 inputs feeds 3 x 3 x 5 outputs = 144 x 45
    assert conv_gmac(Net(), torch.randn(1, 4, 4, 6)) == pytest.approx((144 * 18 + 144 * 45) / 1e9, rel=1e-12)


def test_allowed_false_alarms_on_hand_worked_counts():
    allowed = _script("operating_points").allowed_false_alarms
    # 100 labels, 80 found: F1 = 160 / (160 + FP + 20) >= 0.8 holds up to FP = 20
    assert allowed(80, 20, 0.8) == 20
    # bounds that are whole numbers count in full: 1220 / (1220 + 68 + 237) = 0.8 exactly, and
    # 12 / (12 + 2 + 1) = 0.8
    assert allowed(610, 237, 0.8) == 68 and allowed(6, 1, 0.8) == 2
    # recall 2/3 reaches F1 0.8 only without false alarms; 0.6 not at all
    assert allowed(200, 100, 0.8) == 0 and allowed(60, 40, 0.8) == -1
    # full recall: FP <= TP (2 / t - 2)
    assert allowed(50, 0, 0.5) == 100
    with pytest.raises(ValueError, match="target F1"):
        allowed(5, 5, 1.2)
    with pytest.raises(ValueError, match="counts"):
        allowed(-1, 5, 0.8)


def test_operating_points_from_an_evaluation_file(tmp_path, capsys):
    mod = _script("operating_points")
    # 10 labels on 4 frames; at 0.5: 8 found, 2 false alarms -> F1 16 / 20 = 0.8, exactly the allowance
    ev = {"split": "test", "metrics": {"thresholds": [0.2, 0.5], "tp": [9, 8], "fp": [6, 2], "fn": [1, 2],
                                        "n_labels": 10, "n_frames": 4}}
    path = tmp_path / "eval_test.json"
    path.write_text(json.dumps(ev))
    mod.main([str(path), "--figure", str(tmp_path / "op.png")])
    res = json.loads(capsys.readouterr().out)
    assert res["recall"] == pytest.approx([0.9, 0.8])
    assert res["false_alarms_per_label"] == pytest.approx([0.6, 0.2])
    assert res["false_alarms_per_frame"] == pytest.approx([1.5, 0.5])
    assert res["f1"] == pytest.approx([18 / 25, 0.8])
    # at 0.2: FP <= 18 x 0.25 - 1 = 3.5 -> 3; at 0.5: 16 x 0.25 - 2 = 2
    assert res["allowed_false_alarms"] == [3, 2]
    # scores in (0.2, 0.5]: 5 detections (1 true, 4 false); above 0.5: 10 (8 true)
    assert res["band_detections"] == [5, 10] and res["band_precision"] == pytest.approx([0.2, 0.8])
    assert res["implied_probability"] is None  # no run.json beside the file
    assert (tmp_path / "op.png").stat().st_size > 0
    # a run folder's focal exponent is read from its run.json
    (tmp_path / "run.json").write_text(json.dumps({"experiment": {"loss": {"focal_gamma": 0.0}}}))
    mod.main([str(path)])
    assert json.loads(capsys.readouterr().out)["implied_probability"] == pytest.approx([0.2, 0.5])
    (tmp_path / "run.json").write_text(json.dumps({"experiment": {}}))
    with pytest.raises(SystemExit, match="run.json.*focal_gamma"):
        mod.main([str(path)])
    (tmp_path / "run.json").unlink()
    for bad in ({"thresholds": [0.5, 0.2]}, {"tp": [9]}, {"fp": [2, 6]}):
        path.write_text(json.dumps({"split": "test", "metrics": {**ev["metrics"], **bad}}))
        with pytest.raises(SystemExit, match="eval_test.json.*expected an evaluation JSON"):
            mod.main([str(path)])


def test_focal_implied_probability_inverts_the_focal_minimiser():
    from scipy.optimize import minimize_scalar
    implied = _script("operating_points").focal_implied_probability
    for gamma in (0.0, 0.5, 1.0, 2.0):
        for q in (0.003, 0.03, 0.2, 0.5, 0.8):
            def expected_loss(p):
                return q * (1 - p) ** gamma * -np.log(p) + (1 - q) * p ** gamma * -np.log1p(-p)
            p_star = minimize_scalar(expected_loss, bounds=(1e-9, 1 - 1e-9), method="bounded",
                                     options={"xatol": 1e-12}).x
            # the inverse is smooth with slope below 3 here, so p* to 1e-8 gives q to ~1e-7
            assert implied(p_star, gamma) == pytest.approx(q, abs=1e-6)
    with pytest.raises(ValueError, match="scores"):
        implied(np.array([0.0, 0.5]), 2.0)
    with pytest.raises(ValueError, match="gamma"):
        implied(0.5, -1.0)


def test_failing_axis_on_hand_worked_offsets_and_against_box_iou():
    from radarpc.boxes import box_iou
    failing_axis = _script("box_offsets").failing_axis
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
    assert {"match", "x", "y", "x+y", "x,y"} <= set(axis.tolist())
    with pytest.raises(ValueError, match="iou_threshold"):
        failing_axis(0.0, 0.0, 1.0)


def test_lateral_placement_on_a_hand_worked_frame():
    ceiling = _script("detection_ceiling")
    assert ceiling.LATERAL_TOLERANCE_M == pytest.approx(0.6, abs=1e-12)
    labels = torch.tensor([[0.0, 50.0], [10.0, 20.0]], dtype=torch.float64)
    # label 0's box grown by 0.6 m: |dx| <= 1.5, -0.6 <= dy <= 4.6; the last two points lie outside it
    points = torch.tensor([[-0.9, 51.0], [0.9, 53.0], [0.3, 49.5], [1.6, 51.0], [0.0, 54.7]], dtype=torch.float64)
    amp = torch.tensor([2.0, 1.0, 1.0, 9.0, 9.0])
    got = ceiling.lateral_placement(labels, points, amp)
    # extent centre (-0.9 + 0.9) / 2 = 0; strongest -0.9; power centroid (-0.9 * 4 + 0.9 + 0.3) / 6 = -0.4
    assert got[0].tolist() == pytest.approx([3, 0.0, -0.9, -0.4], abs=1e-12)
    assert got[1, 0] == 0 and torch.isnan(got[1, 1:]).all()
    assert torch.isnan(ceiling.lateral_placement(labels, torch.zeros(0, 2), torch.zeros(0))[:, 1:]).all()
    with pytest.raises(ValueError, match="amplitude"):
        ceiling.lateral_placement(labels, points, amp[:2])
    # a label without a point counts as not placed; shares by label range
    rows = np.array([[3, 0.0, -0.9, -0.4], [0, np.nan, np.nan, np.nan], [1, 0.7, 0.7, 0.7]])
    s = ceiling.placement_summary(np.array([50.0, 20.0, 70.0]), rows)
    assert s["all"]["labels"] == 3 and s["all"]["share_without_a_point"] == pytest.approx(1 / 3)
    assert s["all"]["share_placed_within_tolerance"] == pytest.approx(
        {"extent_centre": 1 / 3, "strongest_point": 0.0, "power_centroid": 1 / 3})
    assert s["30-60"]["share_placed_within_tolerance"]["extent_centre"] == 1.0
    assert s["0-30"]["labels"] == 1 and s[">=60"]["share_placed_within_tolerance"]["extent_centre"] == 0.0
    # bins are [lo, hi): 30 m and 60 m open the next bin; |dx| equal to the tolerance is placed;
    # an empty bin gives None, not NaN (strict JSON)
    edge = ceiling.placement_summary(np.array([30.0, 60.0]), np.array([[1, 0.6, 0.6, 0.6], [1, -0.6, 0.7, 0.0]]))
    assert edge["0-30"] == {"labels": 0, "median_points_in_grown_box": None, "share_without_a_point": None,
                            "share_placed_within_tolerance": dict.fromkeys(ceiling.PLACEMENT_RULES)}
    assert edge["30-60"]["labels"] == 1 and edge[">=60"]["labels"] == 1
    assert edge["all"]["share_placed_within_tolerance"] == {"extent_centre": 1.0, "strongest_point": 0.5,
                                                            "power_centroid": 1.0}
    json.dumps(edge, allow_nan=False)
    # all inside amplitudes 0: the strongest is still an inside point, the centroid undefined
    z = ceiling.lateral_placement(labels[:1], torch.tensor([[3.0, 50.0], [0.5, 51.0]], dtype=torch.float64),
                                  torch.tensor([5.0, 0.0]))
    assert z[0, :3].tolist() == [1, 0.5, 0.5] and torch.isnan(z[0, 3])


def test_beamwidth_against_the_ideal_array_factor():
    from radarpc.sensors.radial import radial_sensor, steering_vectors
    glint = _script("vehicle_glint")
    cfg = radial_sensor("radial")
    az_t, el_t = cfg.azimuth_table_deg, cfg.elevation_table_deg
    step = float(az_t[1] - az_t[0])
    # the ideal dictionary (unit-modulus steering, Hamming taper over the horizontal positions):
    # on the elevation-0 cut its spectrum of an ideal target is the tapered array factor
    p = cfg.virtual_positions[:, 0]
    w = 0.54 - 0.46 * np.cos(2 * np.pi * (p - p.min()) / (p.max() - p.min()))
    ideal = np.conj(steering_vectors(cfg, az_t[:, None], el_t[None, :], hardware=False)).reshape(-1, cfg.n_virtual)
    b = torch.as_tensor(ideal * w, dtype=torch.complex64)
    for a0 in (0.0, 30.0):
        az = np.arange(a0 - 4, a0 + 4, 1e-4)
        af = np.abs((w * np.exp(1j * np.pi * p * (np.sin(np.radians(az)) - np.sin(np.radians(a0)))[:, None])).sum(1))
        main = np.flatnonzero(af >= af.max() / np.sqrt(2))
        # linear interpolation between grid samples misplaces a crossing by at most
        # (h^2 / 8) max|f''| / |f'| (h the grid step), f' and f'' of the array factor near it
        d1, d2 = np.gradient(af, az), np.gradient(np.gradient(af, az), az)
        near = int(step / 1e-4)
        bound = sum(step ** 2 / 8 * np.abs(d2[k - near:k + near]).max() / abs(d1[k]) for k in (main[0], main[-1]))
        got = glint.beamwidth_deg(cfg, a0, b, hardware=False)
        assert abs(got - (az[main[-1]] - az[main[0]])) <= bound + 2e-4
        assert bound < step / 4                          # the check is tighter than the grid
    with pytest.raises(ValueError, match="end of the calibration grid"):
        glint.beamwidth_deg(cfg, 74.9, b, hardware=False)


def test_vehicle_glint_paths_peaks_and_faces():
    from radarpc.sensors.radial import radial_sensor
    from radarpc.sim.radial_calibration import make_calibration
    from radarpc.sim.road import RoadSceneConfig, _vehicle_template
    glint = _script("vehicle_glint")
    cfg = radial_sensor("radial")
    b = make_calibration(cfg).dictionary()
    step = float(cfg.azimuth_table_deg[1] - cfg.azimuth_table_deg[0])
    # one path: the maximum is the grid azimuth nearest to it; two equal in-phase paths inside one
    # beamwidth, symmetric about 10 deg: at 10 deg; two resolved ones (6 deg apart): the stronger
    one = glint.beamformed_azimuth(cfg, np.array([[40.0]]), np.array([[3.05]]), np.zeros((1, 1)), np.ones((1, 1)), b)
    assert abs(one[0] - 3.05) <= step / 2 + 1e-6
    r = np.full((2, 2), 40.0)
    peaks = glint.beamformed_azimuth(cfg, r, np.array([[9.7, 10.3], [-3.0, 3.0]]), np.zeros((2, 2)),
                                     np.array([[1.0, 1.0], [1.0, 4.0]]), b)
    assert abs(peaks[0] - 10.0) <= step / 2 + 1e-6 and abs(peaks[1] - 3.0) <= step / 2 + 1e-6
    with pytest.raises(ValueError, match="dictionary"):
        glint.beamformed_azimuth(cfg, r, r, r, r, b[:10])
    # the rear face: the template's rear-facing points (3 bumper, 2 lights, 2 corners at 45 deg),
    # RCS times sqrt(cos): 1 for the five facing back, 2^-1/4 for the corners
    lateral_z, rcs = glint.rear_face(np.random.default_rng(3))
    body = _vehicle_template(np.random.default_rng(3), *glint.CAR_LWH_M, truck=False, speed=10.0,
                             under_rcs=RoadSceneConfig.underbody_rcs_m2)
    back = (body.normal[:, 0] < 0) & ~body.under
    assert np.sort(rcs / body.rcs[back]).tolist() == pytest.approx([2 ** -0.25] * 2 + [1.0] * 5)
    assert np.abs(lateral_z[:, 0]).max() == pytest.approx(0.9)
    # the paths of one point 0.5 m above the road, 50 m ahead, radar 0.8 m up: direct, ground
    # bistatic (half the direct and image ranges, 4 |Gamma|^2) and ground double (|Gamma|^4)
    r, az, el, rc = glint.face_paths(np.array([[0.3, 0.5]]), np.array([2.0]), 50.0, 0.0, 0.0, 0.8, -6.0)
    g2 = 10 ** -0.6
    direct, image = np.sqrt(50 ** 2 + 0.3 ** 2 + 0.3 ** 2), np.sqrt(50 ** 2 + 0.3 ** 2 + 1.3 ** 2)
    assert r.tolist() == pytest.approx([direct, (direct + image) / 2, image], rel=1e-12)
    assert rc.tolist() == pytest.approx([2.0, 8.0 * g2, 2.0 * g2 ** 2], rel=1e-12)
    assert az == pytest.approx(np.degrees(np.arctan2(0.3, 50.0)), rel=1e-9) and el[2] < el[1] < el[0] < 0
    # draws: scored by the metric's boxes; at 10 m the corners are resolved, so many cells sit
    # on a corner, far outside the tolerance
    matched, dx = glint.glint_draws(cfg, 10.0, 16, np.random.default_rng(0), dictionary=b)
    assert matched.shape == dx.shape == (16,)
    # level boxes match within 0.6 m across; here dy = R (cos A - 1) is at most 0.02 m, which
    # still lets |dx| <= 0.59 pass ((1.8 - 0.59)(4 - 0.02) >= 4.8)
    assert not (matched & (np.abs(dx) > 0.6)).any() and (matched | (np.abs(dx) > 0.59)).all()
    assert (np.abs(dx) > 0.8).any()
    with pytest.raises(ValueError, match="draws"):
        glint.glint_draws(cfg, 80.0, 0, np.random.default_rng(0), dictionary=b)


def test_vehicle_glint_script(tmp_path, capsys):
    glint = _script("vehicle_glint")
    glint.main(["--sensor", "radial", "--ranges", "20", "80", "--draws", "4", "--figure", str(tmp_path / "g.png")])
    out = json.loads(capsys.readouterr().out)
    assert out["lateral_tolerance_m"] == pytest.approx(0.6) and 1.5 < out["beamwidth_3db_deg"] < 2.5
    assert [r["range_m"] for r in out["by_range"]] == [20, 80] and (tmp_path / "g.png").stat().st_size > 0


def test_vml_first_call_script():
    # benchmarks/vml_first_call.py in fresh processes (where torch's first VML call can be inexact:
    # 20 of 40 processes in docs/results/vml_first_call.md): ra_to_box_xy's boxes agree in each
    res = subprocess.run([sys.executable, str(Path(__file__).parents[1] / "benchmarks" / "vml_first_call.py"),
                          "--processes", "2"], capture_output=True, text=True, check=True)
    cases = {c["first_call"] + str(c["env"]): c for c in json.loads(res.stdout)["cases"]}
    assert list(cases) == ["sqrt{}", "sqrt{'MKL_NUM_THREADS': '1'}", "boxes_torch{}", "boxes{}"]
    assert all(c["processes"] == 2 and 0 <= c["inaccurate"] <= 2 for c in cases.values())
    assert cases["sqrt{'MKL_NUM_THREADS': '1'}"]["torch_threads"] == [1]
    assert cases["boxes{}"]["inaccurate"] == 0 and cases["boxes{}"]["max_rel_error"] == 0.0


def test_training_gradients_compares_weight_tensors_only():
    training_gradients = _script("training_gradients")
    ref = {"conv.weight": torch.tensor([[3.0, 4.0]]), "conv.bias": torch.tensor([1.0]),
           "other.weight": torch.tensor([[1.0, 0.0]]), "frozen.weight": torch.zeros(1, 2)}
    g = {"conv.weight": torch.tensor([[6.0, 8.0]]),      # twice the reference: cosine 1, error 1
         "conv.bias": torch.tensor([-5.0]),             # 1-D: left out
         "other.weight": torch.tensor([[0.0, 1.0]]),    # orthogonal: cosine 0, error sqrt(2)
         "frozen.weight": torch.ones(1, 2)}             # zero reference: left out
    out = training_gradients.compare(g, ref)
    assert out["weights_compared"] == 2
    assert out["median_relative_error"] == pytest.approx((1 + 2 ** 0.5) / 2)
    assert [r["parameter"] for r in out["lowest_cosines"]] == ["other.weight", "conv.weight"]
    low, high = out["lowest_cosines"]
    assert low["cosine"] == pytest.approx(0.0, abs=1e-7) and low["relative_error"] == pytest.approx(2 ** 0.5)
    assert high["cosine"] == pytest.approx(1.0) and high["norm_ratio"] == pytest.approx(2.0)
