"""The accel switch, and ``A = sum_rx |R|`` through it: every accelerated path against the core's
torch path (the same ``|z|``, the receiver sum within its float32 bound) and float64."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp import accel
from radarpc.dsp.accel import DISABLE_ENV, native, rxsum
from radarpc.dsp.ddma import rx_magnitude_sum

U32 = 2.0 ** -24                                                      # float32 unit roundoff


def _gamma(n: int) -> float:
    """``gamma_n = n u / (1 - n u)`` (Higham, Accuracy and Stability, sec. 4.2)."""
    return n * U32 / (1 - n * U32)


def _cube(shape, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, dtype=torch.complex64, generator=g)


def _core(rd: torch.Tensor) -> torch.Tensor:
    with accel.disabled():
        return rx_magnitude_sum(rd)


def test_switch_env_var_and_context_manager(monkeypatch):
    monkeypatch.delenv(DISABLE_ENV, raising=False)
    assert accel.enabled()
    for off in ("1", "yes"):
        monkeypatch.setenv(DISABLE_ENV, off)
        assert not accel.enabled() and not native.native_available()
    for on in ("", "0"):
        monkeypatch.setenv(DISABLE_ENV, on)
        assert accel.enabled()
    with accel.disabled():
        assert not accel.enabled() and not native.native_available()
        with accel.disabled():                                        # nested
            assert not accel.enabled()
        assert not accel.enabled()
    assert accel.enabled()
    with pytest.raises(KeyError), accel.disabled():                  # restored on error
        raise KeyError
    assert accel.enabled()


def test_core_path_is_the_formula():
    # the switch off: sqrt(fl(re^2) + fl(im^2)) per receiver, then the float32 sum over receivers
    rd = _cube((3, 37, 16), seed=1)
    x = torch.view_as_real(rd).numpy()
    mag = np.sqrt(x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1], dtype=np.float32)   # float32, IEEE
    exact = mag.astype(np.float64).sum(-1)
    core = _core(rd).numpy()
    assert core.dtype == np.float32
    np.testing.assert_allclose(core, exact, rtol=_gamma(15), atol=0)


@pytest.mark.parametrize("shape", [(2, 5, 33, 16), (3, 13, 5), (301, 24), (1, 1, 16), (4, 9, 1)])
def test_blocked_torch_path_matches_core(shape, monkeypatch):
    # the same |z| values; only the receiver sum may be rounded in another order
    monkeypatch.setattr(rxsum, "_CPU_BLOCK_BYTES", 1)                # a block per row: many blocks
    rd = _cube(shape, seed=shape[-1])
    core = _core(rd)
    n = shape[-1]
    g = _gamma(n - 1)
    for x in (rd, rd.conj(), rd.to(torch.complex128)):
        got = rxsum.rx_magnitude_sum_blocked(x)
        assert got.shape == shape[:-1] and got.dtype == x.real.dtype
        np.testing.assert_allclose(got.float().numpy() if x.dtype == torch.complex64 else got.numpy(),
                                   core.numpy() if x.dtype == torch.complex64 else _core(x).numpy(),
                                   rtol=2 * g / (1 - g), atol=0)


@pytest.mark.parametrize("shape", [(2, 5, 33, 16), (3, 13, 5), (301, 24)])
def test_dispatch_runs_accel_when_enabled_and_core_when_not(shape, selection, monkeypatch):
    # enabled: the kernel when it can take the cube, else the blocked torch path; disabled: the core
    calls = []
    monkeypatch.setattr("radarpc.dsp.ddma.rx_magnitude_sum_fast",
                        lambda rd: calls.append(rd) or rxsum.rx_magnitude_sum_fast(rd))
    rd = _cube(shape, seed=5)
    got = rx_magnitude_sum(rd)
    assert len(calls) == (1 if selection == "native" else 0)
    g = _gamma(shape[-1] - 1)
    np.testing.assert_allclose(got.numpy(), _core(rd).numpy(), rtol=2 * g / (1 - g), atol=0)
    assert len(calls) == (1 if selection == "native" else 0)        # disabled() bypasses accel


def test_without_the_kernels_the_blocked_path_runs(monkeypatch):
    # a pure-Python install: the switch on, the extensions missing
    monkeypatch.delenv(DISABLE_ENV, raising=False)
    monkeypatch.setattr(native, "_rxsum", None)
    rd = _cube((2, 7, 16), seed=9)
    assert not native.native_available()
    assert torch.equal(rx_magnitude_sum(rd), rxsum.rx_magnitude_sum_blocked(rd))
