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
    chamfer_distance_batch,
    earth_movers_distance,
    earth_movers_distance_batch,
    earth_movers_distance_equal,
    emd_resample,
    emd_subset,
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
    pred_to_gt, gt_to_pred = ChamferTarget([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]).directions([[0.0, 1.0, 0.0]])
    assert pred_to_gt == pytest.approx(1.0)
    assert gt_to_pred == pytest.approx(0.5 * (1 + np.sqrt(5)))


@pytest.mark.parametrize("n,m", [(7, 30), (50, 13)])
def test_chamfer_directions_match_brute_force(n, m):
    rng = np.random.default_rng(n * 7 + m)
    p, g = rng.normal(size=(n, 3)) * 3, rng.normal(size=(m, 3)) * 3
    d = np.linalg.norm(p[:, None, :] - g[None, :, :], axis=-1)      # (n, m)
    pred_to_gt, gt_to_pred = ChamferTarget(g).directions(p)
    assert pred_to_gt == pytest.approx(d.min(1).mean(), rel=1e-12)
    assert gt_to_pred == pytest.approx(d.min(0).mean(), rel=1e-12)
    with pytest.raises(ValueError, match="pred"):
        ChamferTarget(g).directions(np.zeros((0, 3)))


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


def _box_surface(n, rng):
    # points on the surface of an 8 m x 6 m x 4 m box: a LiDAR-like 2-D distribution
    u = rng.uniform(-1, 1, (n, 3))
    ax = rng.integers(0, 3, n)
    u[np.arange(n), ax] = np.sign(u[np.arange(n), ax])
    return u * [4.0, 3.0, 2.0]


def _brute_w1(p, g):
    # exact transport between uniform masses by linear_sum_assignment on replicated points:
    # with |p| = a, |g| = b, replicate p b/gcd times and g a/gcd times -> equal sizes, same optimum
    import math
    l = math.lcm(len(p), len(g))
    pp, gg = np.repeat(p, l // len(p), 0), np.repeat(g, l // len(g), 0)
    return _brute_emd(pp, gg)


def test_emd_unequal_sizes_hand_worked_and_brute_force():
    # 1 point vs 2 points: half the mass travels 1 m, half 3 m -> 2 m (a 1:1 matching would say 1 m)
    assert earth_movers_distance([[0.0, 0, 0]], [[1.0, 0, 0], [3.0, 0, 0]]) == pytest.approx(2.0)
    # 2 points vs 3 points on a line, p = {0, 3}, g = {0, 1, 2}: integrating |F_p^-1 - F_g^-1| over
    # the quantile u gives 1/3 * |0-0| + 1/6 * |0-1| + 1/6 * |3-1| + 1/3 * |3-2| = 5/6 (scipy's 1-D W1 agrees)
    p, g = np.array([[0.0, 0, 0], [3.0, 0, 0]]), np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    from scipy.stats import wasserstein_distance
    ref = wasserstein_distance(p[:, 0], g[:, 0])
    assert ref == pytest.approx(5 / 6)
    assert earth_movers_distance(p, g) == pytest.approx(ref, abs=1e-12)
    assert earth_movers_distance(p, g) == pytest.approx(_brute_w1(p, g), abs=1e-12)
    rng = np.random.default_rng(4)
    for n, m in [(4, 6), (9, 6), (5, 7)]:
        p, g = rng.normal(size=(n, 3)), rng.normal(size=(m, 3))
        assert earth_movers_distance(p, g) == pytest.approx(_brute_w1(p, g), rel=1e-9)
        assert earth_movers_distance(g, p) == pytest.approx(_brute_w1(p, g), rel=1e-9)


def test_emd_of_a_cloud_to_itself_is_zero_beyond_the_subset_size():
    g = _box_surface(3000, np.random.default_rng(0))
    perm = np.random.default_rng(1).permutation(3000)
    assert earth_movers_distance(g, g, n=512) == 0.0
    assert earth_movers_distance(g[perm], g, n=512) == 0.0          # any point order


def test_emd_gt_draw_does_not_depend_on_the_prediction():
    rng = np.random.default_rng(3)
    g = _box_surface(5000, rng)
    sub = emd_subset(g, 1024, seed=7)
    assert sub.shape == (1024, 3)
    np.testing.assert_array_equal(sub, emd_subset(g[::-1].copy(), 1024, seed=7))
    assert not np.array_equal(sub, emd_subset(g, 1024, seed=8))
    # every point of the subset is a point of g, no point twice
    assert len(np.unique(sub, axis=0)) == 1024
    assert set(map(tuple, sub)) <= set(map(tuple, g))
    # the perfect prediction -- exactly the ground-truth subset -- scores 0 whatever else exists
    assert earth_movers_distance(sub, g, n=1024, seed=7) == 0.0
    # predictions of different sizes are all scored against that same subset
    for m in (300, 2000):
        p = rng.normal(size=(m, 3))
        want = _w1_ref(emd_subset(p, 1024, seed=7), sub)
        assert earth_movers_distance(p, g, n=1024, seed=7) == pytest.approx(want, rel=1e-9)
    # a cloud no larger than n is used whole
    np.testing.assert_array_equal(np.sort(emd_subset(g[:100], 1024), 0), np.sort(g[:100], 0))


def _w1_ref(p, g):
    import ot
    return ot.emd2([], [], np.linalg.norm(p[:, None] - g[None], axis=-1), numItermax=10**8)


def test_emd_of_ground_truth_points_does_not_depend_on_prediction_size():
    # A prediction made of ground-truth points must score about the same at 1000 points as at
    # 6000: the old equal-size scheme drew k = min(n, |pred|, |gt|) points from *both* clouds,
    # so the score of a sparse prediction was dominated by the sampling noise of its ground truth.
    rng = np.random.default_rng(0)
    g = _box_surface(8000, rng)
    means = {m: np.mean([earth_movers_distance(g[rng.choice(8000, m, replace=False)], g, n=2048)
                         for _ in range(2)]) for m in (1000, 2500, 6000)}
    hi, lo = max(means.values()), min(means.values())
    assert hi / lo < 1.35, means
    # and the floor is the one of two independent 2048-point draws of the cloud (~0.27 m here)
    assert 0.15 < lo < 0.4


def test_emd_subsets_are_seeded():
    rng = np.random.default_rng(3)
    p, g = rng.normal(size=(500, 3)), rng.normal(size=(300, 3))
    a = earth_movers_distance(p, g, n=100, seed=7)
    assert a == earth_movers_distance(p, g, n=100, seed=7)
    assert a == pytest.approx(_w1_ref(emd_subset(p, 100, 7), emd_subset(g, 100, 7)), rel=1e-9)
    # n larger than both clouds: the exact EMD of the full clouds
    assert earth_movers_distance(p, g, n=10_000) == pytest.approx(_w1_ref(p, g), rel=1e-9)


def test_batched_metrics_equal_per_pair_results():
    rng = np.random.default_rng(9)
    preds = [rng.normal(size=(n, 3)) for n in (5, 40, 300)]
    gts = [rng.normal(size=(m, 3)) + 0.5 for m in (70, 8, 250)]
    cd = chamfer_distance_batch(preds, gts, workers=2)
    emd = earth_movers_distance_batch(preds, gts, n=64, workers=2)
    for b in range(3):
        assert cd[b] == pytest.approx(chamfer_distance(preds[b], gts[b]), rel=1e-12)
        assert emd[b] == pytest.approx(earth_movers_distance(preds[b], gts[b], n=64), rel=1e-12)
    # concatenated clouds with Pointcept offsets
    offs = (np.cumsum([len(p) for p in preds]), torch.tensor(np.cumsum([len(g) for g in gts])))
    np.testing.assert_allclose(chamfer_distance_batch(np.concatenate(preds), np.concatenate(gts), offsets=offs,
                                                      workers=1), cd, rtol=1e-12)
    np.testing.assert_allclose(earth_movers_distance_batch(np.concatenate(preds), np.concatenate(gts),
                                                           offsets=offs, n=64), emd, rtol=1e-12)
    # the chunked torch.cdist path (used for CUDA tensors) agrees, here on the CPU
    from radarpc.eval.pointsets import _chamfer_torch
    for b in range(3):
        got = _chamfer_torch(torch.from_numpy(preds[b]), torch.from_numpy(gts[b]), chunk=16)
        assert got == pytest.approx(cd[b], rel=1e-9)
    with pytest.raises(ValueError, match="pair 1: gt cloud is empty"):
        chamfer_distance_batch(preds[:2], [gts[0], np.zeros((0, 3))])
    with pytest.raises(ValueError, match="2 predicted clouds but 3"):
        earth_movers_distance_batch(preds[:2], gts)
    with pytest.raises(ValueError, match="offsets end at"):
        chamfer_distance_batch(np.concatenate(preds), np.concatenate(gts), offsets=([5, 45], [70, 78]))


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
    assert "| hall | 2 |" in md and "**all**" in md and "gt 40, pred 40" in md and "Wasserstein-1" in md
    assert d["frames"][0]["emd_gt_k"] == 40 and d["frames"][0]["emd_pred_k"] == 40
    with pytest.raises(ValueError, match=r"run 'lab_0' frame 0: pred cloud must have shape \(N, 3\)"):
        evaluate_clouds([CloudPair("lab_0", 0, np.zeros((4, 2)), gt)], {"lab_0": "lab"})
    with pytest.raises(ValueError, match="no scene"):
        evaluate_clouds(pairs, {"hall_1": "hall"})
    with pytest.raises(ValueError, match="no frames"):
        evaluate_clouds([], {})


# ---- the equal-size EMD ---------------------------------------------------------------------------

def test_emd_resample_sizes_and_draws():
    rng = np.random.default_rng(3)
    big, small = rng.normal(size=(50, 3)), rng.normal(size=(7, 3))
    # more than n: n distinct points of the cloud, without replacement, the subset of emd_subset
    r = emd_resample(big, 20, 5)
    assert r.shape == (20, 3) and len(np.unique(r, axis=0)) == 20
    np.testing.assert_array_equal(r, emd_subset(big, 20, 5))
    # fewer than n: every point at least once, exactly n rows, the rest repeats of its points
    r = emd_resample(small, 30, 5)
    assert r.shape == (30, 3)
    rows = {tuple(x) for x in r}
    assert rows == {tuple(x) for x in small}
    # exactly n: the cloud itself; the draw is keyed by the point set, not its order, and seeded
    np.testing.assert_array_equal(emd_resample(small, 7), emd_subset(small, 7))
    np.testing.assert_array_equal(emd_resample(small[::-1].copy(), 30, 5), r)
    assert not np.array_equal(emd_resample(small, 30, 6), r)


def test_emd_equal_hand_worked_on_a_line():
    # 3 vs 3 points on the x axis, n = 3: no resampling; on a line the optimal one-to-one
    # assignment matches sorted orders: |0 - 0.5| + |1 - 2| + |5 - 4| = 2.5, mean 2.5 / 3
    p = [[0.0, 0, 0], [5.0, 0, 0], [1.0, 0, 0]]
    g = [[4.0, 0, 0], [0.5, 0, 0], [2.0, 0, 0]]
    assert earth_movers_distance_equal(p, g, n=3) == pytest.approx(2.5 / 3, rel=1e-12)
    # one predicted point resampled to n copies: the mean distance to the n truth points
    assert earth_movers_distance_equal([[0.0, 0, 0]], [[1.0, 0, 0], [3.0, 0, 0]], n=2) == pytest.approx(2.0)
    # {0, 10} resampled to 4 against {0, 1, 2, 3}: sorted matching of whatever the draw repeated
    p2 = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    g2 = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    xs = np.sort(emd_resample(p2, 4, 0, name="pred")[:, 0])
    assert set(xs[:1]) == {0.0} and xs[-1] == 10.0                        # both points present
    expected = np.abs(xs - np.array([0.0, 1.0, 2.0, 3.0])).mean()
    assert earth_movers_distance_equal(p2, g2, n=4, seed=0) == pytest.approx(expected, rel=1e-12)
    # the unequal-size EMD of the same pair: half the mass at 0 takes {0, 1}, half at 10 {2, 3}
    assert earth_movers_distance(p2, g2, n=4) == pytest.approx((0 + 1 + 8 + 7) / 4)


@pytest.mark.parametrize("sizes", [(5, 40), (40, 5), (12, 12), (60, 80)])
def test_emd_equal_is_the_assignment_of_the_resampled_clouds(sizes):
    rng = np.random.default_rng(sum(sizes))
    p, g = rng.normal(size=(sizes[0], 3)), rng.normal(size=(sizes[1], 3)) + 0.7
    n = 32
    got = earth_movers_distance_equal(p, g, n=n, seed=4)
    ref = _brute_emd(emd_resample(p, n, 4, name="pred"), emd_resample(g, n, 4))   # scipy's assignment
    assert got == pytest.approx(ref, rel=1e-9)
    if min(sizes) >= n:                                                 # both drawn without replacement
        assert got == earth_movers_distance(p, g, n=n, seed=4)
    emd = earth_movers_distance_batch([p, g], [g, p], n=n, seed=4, equal_size=True)
    assert emd[0] == got and emd[1] == pytest.approx(earth_movers_distance_equal(g, p, n=n, seed=4))


@pytest.mark.parametrize("size", [1, 9, 32, 100])
def test_emd_equal_of_a_cloud_to_itself_is_zero(size):
    # <= n points: both resampled to the same multiset; more: the same keyed subset
    c = np.random.default_rng(size).uniform(-3, 3, (size, 3))
    assert earth_movers_distance_equal(c, c[::-1].copy(), n=32) == pytest.approx(0.0, abs=1e-12)


def test_emd_equal_refuses_bad_input():
    with pytest.raises(ValueError, match="pred cloud is empty"):
        earth_movers_distance_equal(np.zeros((0, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="resample size"):
        earth_movers_distance_equal(np.ones((2, 3)), np.ones((2, 3)), n=0)


# ---- empty predictions: counted, not scored --------------------------------------------------------

def test_evaluate_clouds_counts_empty_predictions(tmp_path):
    rng = np.random.default_rng(1)
    gt = rng.uniform(0, 5, (30, 3))
    pairs = [CloudPair("hall_1", 0, gt + [0.2, 0, 0], gt), CloudPair("hall_1", 1, np.zeros((0, 3)), gt),
             CloudPair("lab_0", 0, np.zeros((0, 3), np.float32), gt), CloudPair("hall_1", 2, gt[:10], gt)]
    rep = evaluate_clouds(pairs, {"hall_1": "hall", "lab_0": "lab"}, emd_points=16, batch_size=3)
    assert [f.empty for f in rep.frames] == [False, True, True, False]
    assert rep.frames[1].chamfer is None and rep.frames[1].emd is None and rep.frames[1].emd_equal is None
    assert rep.frames[3].emd_equal == pytest.approx(earth_movers_distance_equal(gt[:10], gt, n=16))
    assert rep.frames[3].emd == pytest.approx(earth_movers_distance(gt[:10], gt, n=16))
    hall, lab = rep.scenes
    assert (hall.n_frames, hall.empty, hall.n_scored) == (3, 1, 2)
    cds = [chamfer_distance(gt + [0.2, 0, 0], gt), chamfer_distance(gt[:10], gt)]
    assert hall.chamfer_mean == pytest.approx(np.mean(cds)) and hall.chamfer_median == pytest.approx(np.median(cds))
    assert (lab.n_frames, lab.empty, lab.chamfer_mean, lab.emd_equal_mean) == (1, 1, None, None)
    assert (rep.overall.n_frames, rep.overall.empty) == (4, 2)
    assert rep.scored_keys == {("hall_1", 0), ("hall_1", 2)}
    rep.write(tmp_path / "m.json", tmp_path / "m.md")
    d = json.loads((tmp_path / "m.json").read_text())
    assert d["overall"]["empty"] == 2 and d["frames"][1]["empty"] and d["frames"][1]["chamfer"] is None
    md = (tmp_path / "m.md").read_text()
    assert "| lab | 1 | 1 | - | - | - | - | - | - |" in md and "| hall | 3 | 1 |" in md and "EMD_equal" in md
    # a subset recomputes the summaries
    sub = rep.subset({("hall_1", 0), ("lab_0", 0)})
    assert sub.overall.n_frames == 2 and sub.overall.empty == 1 and sub.overall.chamfer_mean == pytest.approx(cds[0])
    # an empty ground truth is still an error naming run and frame, with an empty prediction too
    for pred in (gt, np.zeros((0, 3))):
        with pytest.raises(ValueError, match="run 'lab_0' frame 4: gt cloud is empty"):
            evaluate_clouds([CloudPair("lab_0", 4, pred, np.zeros((0, 3)))], {"lab_0": "lab"})
