"""CA-CFAR and OS-CFAR against brute-force loops over cells (borders included)."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from radarpc.dsp.cfar import CFARResult, ca_cfar, os_cfar


def _training_values(p: np.ndarray, cell: tuple[int, ...], window, guard) -> np.ndarray:
    """Powers of the valid training cells of ``cell`` (explicit offsets, explicit bounds)."""
    vals = []
    hw = [w // 2 for w in window]
    hg = [g // 2 for g in guard]
    for off in itertools.product(*[range(-h, h + 1) for h in hw]):
        if all(abs(o) <= h for o, h in zip(off, hg)):
            continue  # guard cell (or the cell under test)
        t = tuple(c + o for c, o in zip(cell, off))
        if all(0 <= ti < n for ti, n in zip(t, p.shape)):
            vals.append(p[t])
    return np.asarray(vals, dtype=np.float64)


def _brute(p: np.ndarray, window, guard, stat) -> tuple[np.ndarray, np.ndarray]:
    noise = np.empty(p.shape)
    for cell in itertools.product(*[range(n) for n in p.shape]):
        vals = _training_values(p, cell, window, guard)
        noise[cell] = stat(vals)
    return noise, p / noise


CASES = [
    ((37,), (9,), (3,)),
    ((5,), (9,), (3,)),                 # array smaller than the window: every cell is a border cell
    ((12, 7), (9, 5), (3, 1)),
    ((20, 16), (9, 9), (3, 3)),
    ((6, 7, 5), (5, 3, 5), (3, 1, 1)),
]


@pytest.mark.parametrize("shape,window,guard", CASES)
def test_ca_cfar_matches_brute_force(shape, window, guard):
    rng = np.random.default_rng(0)
    p = rng.exponential(size=shape)
    p[tuple(n // 2 for n in shape)] = 1e6  # a strong target must not leak through cancellation
    noise_ref, snr_ref = _brute(p, window, guard, np.mean)
    res = ca_cfar(torch.from_numpy(p), window, guard)
    np.testing.assert_allclose(res.noise.numpy(), noise_ref, rtol=1e-12)
    np.testing.assert_allclose(res.snr.numpy(), snr_ref, rtol=1e-12)
    res32 = ca_cfar(torch.from_numpy(p).float(), window, guard)
    np.testing.assert_allclose(res32.noise.numpy(), noise_ref, rtol=1e-5)


def test_ca_cfar_batched_and_numpy_in_numpy_out():
    rng = np.random.default_rng(1)
    p = rng.exponential(size=(3, 2, 14, 10))
    res = ca_cfar(p, (9, 9), (3, 3))
    assert isinstance(res.noise, np.ndarray) and isinstance(res.snr, np.ndarray)
    for b, c in itertools.product(range(3), range(2)):
        noise_ref, _ = _brute(p[b, c], (9, 9), (3, 3), np.mean)
        np.testing.assert_allclose(res.noise[b, c], noise_ref, rtol=1e-12)
    m = res.mask(1.585)
    assert isinstance(m, np.ndarray) and m.dtype == bool
    np.testing.assert_array_equal(m, res.snr > 1.585)


def test_ca_cfar_border_uses_mean_of_valid_cells_hand_worked():
    # 1-D, window 5 (offsets -2..2), guard 1 (only the CUT): cell 0 sees cells 1, 2.
    p = torch.tensor([4.0, 1.0, 3.0, 8.0, 2.0], dtype=torch.float64)
    res = ca_cfar(p, 5, 1)
    expected = torch.tensor([(1 + 3) / 2, (4 + 3 + 8) / 3, (4 + 1 + 8 + 2) / 4, (1 + 3 + 2) / 3, (3 + 8) / 2],
                            dtype=torch.float64)
    torch.testing.assert_close(res.noise, expected)
    torch.testing.assert_close(res.snr, p / expected)


@pytest.mark.parametrize("shape,window,guard", CASES)
@pytest.mark.parametrize("rank", [1, 3, 0.5, 0.75])
def test_os_cfar_matches_brute_force(shape, window, guard, rank):
    rng = np.random.default_rng(2)
    p = rng.exponential(size=shape)

    def stat(vals):
        v = np.sort(vals)
        n = len(v)
        k = min(rank, n) if isinstance(rank, int) else max(1, math.ceil(rank * n))
        return v[k - 1]

    noise_ref, snr_ref = _brute(p, window, guard, stat)
    res = os_cfar(torch.from_numpy(p), window, guard, rank)
    np.testing.assert_array_equal(res.noise.numpy(), noise_ref)
    np.testing.assert_allclose(res.snr.numpy(), snr_ref, rtol=1e-12)


def test_os_cfar_batched():
    rng = np.random.default_rng(3)
    p = rng.exponential(size=(2, 9, 8)).astype(np.float32)
    res = os_cfar(p, (5, 5), (3, 1), 0.5)
    for b in range(2):
        ref, _ = _brute(p[b].astype(np.float64), (5, 5), (3, 1),
                        lambda v: np.sort(v)[max(1, math.ceil(0.5 * len(v))) - 1])
        np.testing.assert_allclose(res.noise[b], ref, rtol=1e-6)


def test_zero_noise_and_result_type():
    p = torch.zeros(10, 10)
    p[5, 5] = 2.0
    res = ca_cfar(p, (3, 3), (1, 1))
    assert isinstance(res, CFARResult)
    assert res.snr[5, 5] == math.inf and res.snr[0, 0] == 0
    assert res.mask(1.585).sum() == 1


@pytest.mark.parametrize("kwargs,match", [
    (dict(window=(8, 9), guard=(3, 3)), "odd"),
    (dict(window=(9, 9), guard=(9, 3)), "smaller"),
    (dict(window=(9, 9), guard=(3,)), "same number"),
    (dict(window=(9, 9, 9, 9), guard=(3, 3, 3, 3)), "1-D, 2-D and 3-D"),
    (dict(window=(9, 9), guard=(0, 3)), "odd"),
])
def test_bad_windows(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ca_cfar(torch.ones(20, 20), **kwargs)


def test_bad_power():
    with pytest.raises(ValueError, match="real"):
        ca_cfar(torch.ones(20, 20, dtype=torch.complex64))
    with pytest.raises(ValueError, match="NaN"):
        ca_cfar(torch.tensor([[1.0, float("nan")] * 10] * 20))
    with pytest.raises(ValueError, match=">= 0"):
        ca_cfar(-torch.ones(20, 20))
    with pytest.raises(ValueError, match="dims"):
        ca_cfar(torch.ones(20))
    with pytest.raises(ValueError, match="rank"):
        os_cfar(torch.ones(20, 20), (9, 9), (3, 3), 73)
    with pytest.raises(ValueError, match="quantile"):
        os_cfar(torch.ones(20, 20), (9, 9), (3, 3), 1.5)
    with pytest.raises(ValueError, match="tau"):
        ca_cfar(torch.ones(20, 20)).mask(0.0)


def test_os_cfar_blocked_equals_unblocked(monkeypatch):
    import radarpc.dsp.cfar as cfar_mod
    rng = np.random.default_rng(4)
    p = torch.from_numpy(rng.exponential(size=(2, 11, 6, 5)))
    whole = os_cfar(p, (5, 3, 3), (3, 1, 1), 0.6)
    monkeypatch.setattr(cfar_mod, "_OS_STACK_BYTES", 1)             # one row of axis 0 per block
    blocked = os_cfar(p, (5, 3, 3), (3, 1, 1), 0.6)
    torch.testing.assert_close(blocked.noise, whole.noise, rtol=0, atol=0)
    ref, _ = _brute(p[1].numpy(), (5, 3, 3), (3, 1, 1),
                    lambda v: np.sort(v)[max(1, math.ceil(0.6 * len(v))) - 1])
    np.testing.assert_array_equal(blocked.noise[1].numpy(), ref)


U32 = 2.0 ** -24                                                      # float32 unit roundoff


@pytest.mark.parametrize("shape,window,guard", CASES + [((9, 6), (7, 5), (3, 3))])
@pytest.mark.parametrize("kind", ["random", "ties"])
def test_ca_cfar_float32_within_the_rounding_bound(shape, window, guard, kind):
    # float32 noise = (float32 sum of the n valid training powers) / n: any order of the n - 1
    # additions of non-negative terms is within gamma_(n-1) of the exact sum (Higham, sec. 4.2),
    # and the division adds one rounding (n is exact); the SNR adds one more
    rng = np.random.default_rng(5)
    p = rng.exponential(size=shape).astype(np.float32) * 100
    if kind == "ties":
        p = np.floor(p / 50).astype(np.float32)                      # zeros and repeated values
    res = ca_cfar(torch.from_numpy(p), window, guard)
    noise, snr = res.noise.numpy(), res.snr.numpy()
    for cell in itertools.product(*[range(n) for n in shape]):
        vals = _training_values(p, cell, window, guard)               # float64, exact
        n = len(vals)
        mean = vals.sum() / n
        gamma = (n - 1) * U32 / (1 - (n - 1) * U32)
        rel = (1 + gamma) * (1 + U32) - 1
        assert abs(noise[cell] - mean) <= rel * mean, cell
        if kind == "ties":                                            # integer sums < 2^24: exact
            assert noise[cell] == np.float32(vals.sum()) / np.float32(n), cell
        if mean == 0:                                                 # sum of non-negatives: 0 exactly
            assert noise[cell] == 0 and snr[cell] == (math.inf if p[cell] > 0 else 0.0), cell
        else:
            want = p[cell] / mean
            assert abs(snr[cell] - want) <= ((1 + rel) / (1 - rel) * (1 + U32) - 1) * want, cell


def test_cells_without_training_cells():
    # 1-D, window 5 and guard 3: in an array of 2 every window cell is a guard cell
    res = ca_cfar(torch.tensor([1.0, 2.0]), 5, 3)
    assert torch.equal(res.noise, torch.full((2,), math.inf)) and torch.equal(res.snr, torch.zeros(2))
    # 2-D: only the centre of a 4 x 3 array with a 7 x 7 window and 5 x 5 guard has none
    p = torch.arange(1.0, 13.0).reshape(4, 3)
    res = ca_cfar(p, (7, 7), (5, 5))
    for cell in itertools.product(range(4), range(3)):
        vals = _training_values(p.numpy(), cell, (7, 7), (5, 5))
        if len(vals) == 0:
            assert res.noise[cell] == math.inf and res.snr[cell] == 0
        else:
            assert res.noise[cell].item() == pytest.approx(vals.mean(), rel=1e-6)
    assert bool(torch.isinf(res.noise).any())
    os_res = os_cfar(p, (7, 7), (5, 5), 1)
    assert torch.equal(torch.isinf(os_res.noise), torch.isinf(res.noise))


def test_infinite_power_is_rejected():
    p = torch.ones(20, 20)
    p[3, 4] = math.inf
    with pytest.raises(ValueError, match="NaN or infinite"):
        ca_cfar(p)


@pytest.mark.parametrize("rank", [1, 7, 40, 72, 0.3, 0.75])
def test_os_cfar_ties_and_every_border_k(rank):
    # integer powers (many equal values) on a thin map: most cells are border cells, with many
    # different k; each k-group must give the brute-force order statistic
    rng = np.random.default_rng(6)
    p = np.floor(rng.exponential(size=(2, 13, 10)) * 3)

    def stat(vals):
        v = np.sort(vals)
        k = min(rank, len(v)) if isinstance(rank, int) else max(1, math.ceil(rank * len(v)))
        return v[k - 1]

    res = os_cfar(torch.from_numpy(p), (9, 9), (3, 3), rank)
    for b, r, l in itertools.product(range(2), range(13), range(10)):
        assert res.noise[b, r, l].item() == stat(_training_values(p[b], (r, l), (9, 9), (3, 3))), (b, r, l)
