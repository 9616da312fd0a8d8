"""Native RD magnitude sum vs a float64 numpy reference and the core torch path (within the float32
bounds of the receiver sum); chunking; the thread pool; errors."""
from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
import torch

from radarpc.dsp import accel
from radarpc.dsp.accel import DISABLE_ENV, native
from radarpc.dsp.accel.native import native_available, native_kernels, native_supports, rx_magnitude_sum_native
from radarpc.dsp.ddma import rx_magnitude_sum


def _cube(shape, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, dtype=torch.complex64, generator=g)


def _reference(rd: torch.Tensor) -> np.ndarray:
    """``sum_rx sqrt(re^2 + im^2)`` in float64 (the formula itself, also for inf/NaN)."""
    x = torch.view_as_real(rd.resolve_conj()).numpy().astype(np.float64)      # (..., Nd, Nrx, 2)
    with np.errstate(invalid="ignore"):
        return np.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2).sum(-1)


U32 = 2.0 ** -24                                   # float32 unit roundoff


def _gamma(n: int) -> float:
    """``gamma_n = n u / (1 - n u)``: the relative error bound of a float32 sum of ``n + 1``
    non-negative terms, in any order (Higham, Accuracy and Stability, 2nd ed., sec. 4.2)."""
    return n * U32 / (1 - n * U32)


def _reference_rtol(n_rx: int) -> float:
    """Relative bound of ``sum_rx |z|`` in float32 against the exact value: each
    ``sqrt(fl(fl(re^2) + fl(im^2)))`` is within ``(1 + u)^2 - 1`` of ``|z|``, then ``n_rx``
    non-negative terms are summed (``gamma_(n_rx - 1)``)."""
    per_term = (1 + U32) ** 2 - 1
    return (1 + per_term) * (1 + _gamma(n_rx - 1)) - 1


def _core_rtol(n_rx: int) -> float:
    """Relative bound between two float32 sums of the same ``n_rx`` non-negative terms in
    different orders (the kernel's tree, torch's reduction): ``2 gamma_(n_rx - 1)`` of the terms'
    sum, which is at most ``1 / (1 - gamma)`` times either computed sum (0 for one term)."""
    g = _gamma(n_rx - 1)
    return 2 * g / (1 - g)


def _core(rd: torch.Tensor) -> torch.Tensor:
    """ddma.rx_magnitude_sum on its core torch path (the accel switch off)."""
    with accel.disabled():
        return rx_magnitude_sum(rd)


SHAPES = [
    (1, 256, 16),          # one range row
    (3, 37, 16),           # odd Nd, tail cells after the 8-cell blocks
    (2, 5, 33, 16),        # batch dim
    (2, 3, 17, 4),         # Nrx = 4 (scalar kernel)
    (4, 9, 8),             # Nrx = 8 (one AVX group)
    (3, 13, 5),            # odd Nrx
    (1, 1, 16),            # a single cell
    (2, 24),               # Nrx = 24 (three AVX groups), 2-D input
    (3, 200, 8),           # long enough for the software-prefetch loop at every Nrx % 8 == 0
    (301, 24),
]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("threads", [1, 2, 7])
def test_matches_float64_reference_every_kernel(built, monkeypatch, shape, threads):
    monkeypatch.setattr(native, "_CHUNK_BYTES", 1)              # items of 16 cells: many, even here
    rd = _cube(shape, seed=len(shape) + shape[-1])
    ref = _reference(rd)
    for kernel in ("auto",) + native_kernels(shape[-1]):
        a = rx_magnitude_sum_native(rd, threads=threads, kernel=kernel)
        assert a.dtype == torch.float32 and a.shape == shape[:-1] and a.device.type == "cpu"
        np.testing.assert_allclose(a.numpy(), ref, rtol=_reference_rtol(shape[-1]), atol=0, err_msg=f"kernel {kernel}")


@pytest.mark.parametrize("shape", SHAPES)
def test_matches_core(built, shape):
    rd = _cube(shape, seed=3)
    rd[..., 0, 0] = complex(3e19, 0.0)              # |z|^2 overflows float32 in both: inf
    fallback = _core(rd)
    got = rx_magnitude_sum_native(rd, threads=2)
    assert torch.isinf(got[..., 0]).all() and torch.isinf(fallback[..., 0]).all()
    np.testing.assert_allclose(got.numpy(), fallback.numpy(), rtol=_core_rtol(shape[-1]), atol=0)


def test_full_radial_frame_matches_core(built):
    rd = _cube((512, 256, 16), seed=5)
    np.testing.assert_allclose(rx_magnitude_sum_native(rd, threads=2).numpy(),
                               _core(rd).numpy(), rtol=_core_rtol(16), atol=0)


def test_nan_and_inf_propagate(built, monkeypatch):
    monkeypatch.setattr(native, "_CHUNK_BYTES", 1)
    rd = _cube((2, 21, 16), seed=7)
    inf, nan = float("inf"), float("nan")
    rd[0, 0, 3] = complex(inf, 0.0)                 # inf -> inf
    rd[0, 9, 15] = complex(0.0, -inf)
    rd[0, 17, 0] = complex(nan, 1.0)                # NaN -> NaN
    rd[1, 4, 2] = complex(inf, 0.0)                 # inf and NaN in one cell -> NaN
    rd[1, 4, 7] = complex(0.0, nan)
    rd[1, 20, 5] = complex(inf, nan)                # sqrt(inf + nan) -> NaN (the formula, not hypot)
    ref = _reference(rd)
    fallback = _core(rd).numpy()
    for kernel in native_kernels(16):
        for threads in (1, 3):
            got = rx_magnitude_sum_native(rd, threads=threads, kernel=kernel).numpy()
            for want in (ref, fallback):
                np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
                np.testing.assert_array_equal(np.isposinf(got), np.isposinf(want))
            assert np.isposinf(got[0, [0, 9]]).all() and np.isnan(got[0, 17]) and np.isnan(got[1, [4, 20]]).all()
            fin = np.isfinite(ref)
            np.testing.assert_allclose(got[fin], ref[fin], rtol=_reference_rtol(16), atol=0)


def test_conjugate_view_and_batch_rows_independent(built):
    rd = _cube((3, 4, 40, 16), seed=11)
    a = rx_magnitude_sum_native(rd)
    assert torch.equal(rx_magnitude_sum_native(rd.conj()), a)               # |conj z| = |z|
    assert torch.equal(rx_magnitude_sum_native(rd[1]), a[1])               # rows do not mix
    np.testing.assert_allclose(a.numpy(), _reference(rd), rtol=_reference_rtol(16), atol=0)


def test_hand_worked_cell(built):
    # |3+4j| + |-5+12j| + |0| + |8-15j| + |-7-24j| + 4 * |1+0j| + 8 * |0| = 5 + 13 + 0 + 17 + 25 + 4
    vals = [3 + 4j, -5 + 12j, 0, 8 - 15j, -7 - 24j] + [1] * 4 + [0] * 7
    rd = torch.tensor([[vals, vals[::-1]]], dtype=torch.complex64)          # (1, 2, 16)
    for kernel in native_kernels(16):
        assert rx_magnitude_sum_native(rd, kernel=kernel).tolist() == [[64.0, 64.0]]


def test_empty_inputs(built):
    assert rx_magnitude_sum_native(torch.zeros(0, 5, 16, dtype=torch.complex64)).shape == (0, 5)
    z = rx_magnitude_sum_native(torch.ones(3, 5, 0, dtype=torch.complex64))
    assert z.shape == (3, 5) and bool((z == 0).all())


@pytest.mark.parametrize("n_rx", [1, 4, 5, 16, 24, 10**6])
def test_chunk_cells(n_rx):
    step = native._chunk_cells(n_rx)
    assert step >= native._CHUNK_ALIGN and step % native._CHUNK_ALIGN == 0
    assert step * 8 * n_rx <= max(native._CHUNK_BYTES, 8 * n_rx * native._CHUNK_ALIGN)
    assert native._chunk_cells(16) * 8 * 16 == native._CHUNK_BYTES


def test_kernel_lists(built):
    assert native_kernels(16)[-1] == "scalar" and native_kernels(3) == ("scalar",)
    assert set(native_kernels(16)) <= set(native.KERNELS) - {"auto"}
    assert built._rxsum.rx_magnitude_sum(0, 0, 0, 16, "scalar") == "scalar"      # empty call: nothing read
    with pytest.raises(ValueError, match="n_rx"):
        native_kernels(0)
    with pytest.raises(ValueError, match="kernel must be"):
        built._rxsum.rx_magnitude_sum(0, 0, 0, 16, "sse9")
    with pytest.raises(ValueError, match="n_rx >= 1"):
        built._rxsum.rx_magnitude_sum(0, 0, 0, 0)
    with pytest.raises(ValueError, match="non-null"):
        built._rxsum.rx_magnitude_sum(0, 0, 4, 16)


def test_bad_input_errors(built):
    good = _cube((2, 8, 16))
    with pytest.raises(ValueError, match="torch.Tensor"):
        rx_magnitude_sum_native(good.numpy())
    with pytest.raises(ValueError, match="CPU"):
        rx_magnitude_sum_native(torch.empty(2, 8, 16, dtype=torch.complex64, device="meta"))
    with pytest.raises(ValueError, match="complex64"):
        rx_magnitude_sum_native(good.real)
    with pytest.raises(ValueError, match="complex64"):
        rx_magnitude_sum_native(good.to(torch.complex128))
    with pytest.raises(ValueError, match="ndim >= 2"):
        rx_magnitude_sum_native(good[0, 0])
    with pytest.raises(ValueError, match="C-contiguous"):
        rx_magnitude_sum_native(good.transpose(0, 1))
    for bad in (0, -1, True, 1.5):
        with pytest.raises(ValueError, match="threads"):
            rx_magnitude_sum_native(good, threads=bad)
    with pytest.raises(ValueError, match="kernel must be one of"):
        rx_magnitude_sum_native(good, kernel="avx512x")
    if "avx" in native_kernels(16):
        with pytest.raises(ValueError, match="cannot run here for Nrx=4"):
            rx_magnitude_sum_native(_cube((2, 8, 4)), kernel="avx")


def test_env_var_disables(monkeypatch):
    for ext in ("_rxsum", "_screen"):               # the env var alone, also on a build without them
        if getattr(native, ext) is None:
            monkeypatch.setattr(native, ext, object())
    monkeypatch.setenv(DISABLE_ENV, "1")
    assert not native_available() and native_kernels(16) == ()
    assert not native_supports(_cube((2, 8, 16)))
    with pytest.raises(RuntimeError, match=r"radarpc\.dsp\.accel\._rxsum.*RADARPC_NO_NATIVE"):
        rx_magnitude_sum_native(_cube((2, 8, 16)))


def test_missing_extension_raises(monkeypatch):
    monkeypatch.delenv(DISABLE_ENV, raising=False)
    for ext in ("_rxsum", "_screen"):               # either one missing: both reported missing
        with monkeypatch.context() as m:
            m.setattr(native, ext, None)
            assert not native_available()
            with pytest.raises(RuntimeError, match=r"radarpc\.dsp\.accel\._rxsum/_screen are not built"):
                rx_magnitude_sum_native(_cube((2, 8, 16)))


def test_native_supports(built):
    rd = _cube((2, 8, 16))
    assert native_supports(rd) and native_supports(rd.conj())
    assert not native_supports(rd.transpose(0, 1))
    assert not native_supports(rd.to(torch.complex128)) and not native_supports(rd.real)
    assert not native_supports(rd[0, 0])
    assert not native_supports(rd.clone().requires_grad_())
    with torch.no_grad():
        assert native_supports(rd.clone().requires_grad_())


def test_pool_recreated_after_fork_and_shared_by_threads(built, monkeypatch):
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.setattr(native, "_CHUNK_BYTES", 1)
    rd = _cube((6, 40, 16), seed=13)
    ref = rx_magnitude_sum_native(rd, threads=1)
    rx_magnitude_sum_native(rd, threads=3)
    pool = native._pool
    monkeypatch.setattr(native, "_pool_pid", -1)       # as in a forked child: the pool has no threads
    assert torch.equal(rx_magnitude_sum_native(rd, threads=3), ref)
    assert native._pool is not pool and native._pool_pid == os.getpid()
    with ThreadPoolExecutor(4) as callers:             # concurrent callers, growing the pool
        outs = list(callers.map(lambda t: rx_magnitude_sum_native(rd, threads=t), [2, 5, 3, 8, 2, 6]))
    assert all(torch.equal(o, ref) for o in outs)


def test_run_items_waits_for_every_item_before_raising():
    # the caller's buffers must outlive the work: an error in one item may not return early
    done, lock = [], threading.Lock()

    def item(start: int, count: int) -> None:
        if threading.current_thread() is not threading.main_thread() and not failed.is_set():
            failed.set()
            raise MemoryError("an item failed")                      # the first pool thread's item
        time.sleep(0.05)
        with lock:
            done.append(start)

    for threads in (2, 3, 4):
        done.clear()
        failed = threading.Event()
        with pytest.raises(MemoryError, match="an item failed"):
            native._run_items(item, 8, 1, threads=threads)
        assert len(done) == 7, threads                                 # every other item finished
