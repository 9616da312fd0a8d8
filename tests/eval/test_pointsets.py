"""Chamfer distance and EMD against brute force; per-scene reports."""
import json

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from radarpc.eval.pointsets import (
    ChamferTarget,
    CloudPair,
    chamfer_distance,
    earth_movers_distance,
    evaluate_clouds,
)


def _brute_chamfer(p, g):
    d = np.linalg.norm(p[:, None, :] - g[None, :, :], axis=-1)   # (N, M)
    return 0.5 * d.min(0).mean() + 0.5 * d.min(1).mean()


def _brute_emd(p, g):
    d = np.linalg.norm(p[:, None, :] - g[None, :, :], axis=-1)
    r, c = linear_sum_assignment(d)
    return d[r, c].mean()


@pytest.mark.parametrize("n,m", [(1, 1), (7, 30), (50, 13)])
def test_chamfer_matches_brute_force_and_is_symmetric(n, m):
    rng = np.random.default_rng(n * 100 + m)
    p, g = rng.normal(size=(n, 3)) * 3, rng.normal(size=(m, 3)) * 3
    cd = chamfer_distance(p, g)
    assert cd == pytest.approx(_brute_chamfer(p, g), rel=1e-12)
    assert chamfer_distance(g, p) == pytest.approx(cd, rel=1e-12)
    assert chamfer_distance(torch.from_numpy(p).float(), g) == pytest.approx(cd, rel=1e-5)
    assert ChamferTarget(g)(p) == cd


def test_chamfer_hand_worked_two_points():
    # gt at (0,0,0) and (2,0,0), prediction one point at (0,1,0):
    # gt->pred distances 1 and sqrt(5); pred->gt distance 1  =>  0.5 (1 + sqrt 5)/2 + 0.5 * 1
    cd = chamfer_distance([[0.0, 1.0, 0.0]], [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    assert cd == pytest.approx(0.25 * (1 + np.sqrt(5)) + 0.5)


def test_zero_for_identical_clouds():
    p = np.random.default_rng(0).uniform(-5, 5, (200, 3))
    assert chamfer_distance(p, p) == 0.0
    assert earth_movers_distance(p, p[::-1].copy(), n=200) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("k", [1, 5, 40])
def test_emd_full_sets_matches_linear_sum_assignment(k):
    rng = np.random.default_rng(k)
    p, g = rng.normal(size=(k, 3)), rng.normal(size=(k, 3)) + 1.0
    emd = earth_movers_distance(p, g, n=k)
    assert emd == pytest.approx(_brute_emd(p, g), rel=1e-12)
    assert earth_movers_distance(g, p, n=k) == pytest.approx(emd, rel=1e-12)


def test_emd_hand_worked_two_points():
    # pred {(0,0,0), (1,0,0)}, gt {(1,0,0), (2,0,0)}: crossing matches cost (0 + 2), parallel (1 + 1)
    # both total 2, mean matched distance 1
    emd = earth_movers_distance([[0.0, 0, 0], [1.0, 0, 0]], [[1.0, 0, 0], [2.0, 0, 0]])
    assert emd == pytest.approx(1.0)
    # a pure translation by t of an identical cloud costs exactly |t|
    p = np.random.default_rng(1).uniform(0, 0.1, (64, 3))
    assert earth_movers_distance(p, p + [3.0, 4.0, 0.0], n=64) == pytest.approx(5.0, abs=0.05)


def test_emd_subsets_are_seeded_and_sized():
    rng = np.random.default_rng(3)
    p, g = rng.normal(size=(500, 3)), rng.normal(size=(300, 3))
    a = earth_movers_distance(p, g, n=100, seed=7)
    assert a == earth_movers_distance(p, g, n=100, seed=7)
    # the subsets are those of default_rng(seed): pred first, then gt
    r = np.random.default_rng(7)
    ps, gs = p[r.choice(500, 100, replace=False)], g[r.choice(300, 100, replace=False)]
    assert a == pytest.approx(_brute_emd(ps, gs), rel=1e-12)
    # n larger than a cloud: k = min(n, N, M) = 300 points
    r = np.random.default_rng(0)
    assert earth_movers_distance(p, g, n=10_000, seed=0) == pytest.approx(
        _brute_emd(p[r.choice(500, 300, replace=False)], g), rel=1e-12)


def test_empty_and_bad_clouds_raise_naming_the_cloud():
    ok = np.zeros((3, 3))
    with pytest.raises(ValueError, match="pred cloud is empty"):
        chamfer_distance(np.zeros((0, 3)), ok)
    with pytest.raises(ValueError, match="gt cloud is empty"):
        earth_movers_distance(ok, np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"gt cloud must have shape \(N, 3\)"):
        chamfer_distance(ok, np.zeros((3, 4)))
    with pytest.raises(ValueError, match="pred cloud contains NaN"):
        chamfer_distance(np.array([[0.0, np.nan, 0.0]]), ok)
    with pytest.raises(ValueError, match="real"):
        chamfer_distance(ok.astype(complex), ok)
    with pytest.raises(ValueError, match="subset size"):
        earth_movers_distance(ok, ok, n=0)


def test_evaluate_clouds_per_scene_tables(tmp_path):
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 5, (40, 3))
    pairs = [CloudPair("hall_1", 0, gt + [0.1, 0, 0], gt), CloudPair("hall_1", 1, gt + [0.3, 0, 0], gt),
             CloudPair("lab_0", 0, gt, gt)]
    rep = evaluate_clouds(pairs, {"hall_1": "hall", "lab_0": "lab"}, emd_points=40)
    assert [s.scene for s in rep.scenes] == ["hall", "lab"]
    hall = rep.scenes[0]
    assert hall.n_frames == 2
    cds = [chamfer_distance(p.pred, p.gt) for p in pairs]
    assert hall.chamfer_mean == pytest.approx((cds[0] + cds[1]) / 2)
    assert hall.emd_mean == pytest.approx(0.2, abs=1e-9)      # pure shifts 0.1 and 0.3 are matched 1:1
    assert rep.scenes[1].chamfer_mean == 0.0
    assert rep.overall.n_frames == 3 and rep.overall.chamfer_median == pytest.approx(cds[0])
    rep.write(tmp_path / "m.json", tmp_path / "m.md")
    d = json.loads((tmp_path / "m.json").read_text())
    assert d["emd_points"] == 40 and len(d["frames"]) == 3 and d["scenes"][0]["scene"] == "hall"
    md = (tmp_path / "m.md").read_text()
    assert "| hall | 2 |" in md and "**all**" in md and "mean subset size 40" in md
    assert d["frames"][0]["emd_k"] == 40
    with pytest.raises(ValueError, match="run 'lab_0' frame 0: pred cloud is empty"):
        evaluate_clouds([CloudPair("lab_0", 0, np.zeros((0, 3)), gt)], {"lab_0": "lab"})
    with pytest.raises(ValueError, match="no scene"):
        evaluate_clouds(pairs, {"hall_1": "hall"})
    with pytest.raises(ValueError, match="no frames"):
        evaluate_clouds([], {})
