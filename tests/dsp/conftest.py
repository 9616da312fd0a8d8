"""Fixtures shared by the DSP tests: the native extensions of radarpc.dsp.accel, enabled or disabled;
the radial-s dictionary and snapshots made of its steering vectors."""
from __future__ import annotations

import os

import pytest
import torch

from radarpc.dsp.accel import DISABLE_ENV, native
from radarpc.dsp.beamform import dictionary_tables
from radarpc.sensors.radial import RADIAL_S
from radarpc.sim.radial_calibration import make_calibration


@pytest.fixture
def built(monkeypatch):
    """The native extensions, enabled; skip if they are not built, unless RADARPC_REQUIRE_NATIVE=1
    (CI), where that is a failure."""
    monkeypatch.delenv(DISABLE_ENV, raising=False)
    if native._rxsum is None or native._screen is None:
        msg = "radarpc.dsp.accel._rxsum/_screen are not built (no C compiler at install time)"
        if os.environ.get("RADARPC_REQUIRE_NATIVE") == "1":
            pytest.fail(msg + " but RADARPC_REQUIRE_NATIVE=1")
        pytest.skip(msg)
    return native


@pytest.fixture(params=["native", "torch"])
def selection(request, monkeypatch):
    """Run a test once with the native kernels (as :fixture:`built`) and once on the torch paths."""
    if request.param == "native":
        request.getfixturevalue("built")
    else:
        monkeypatch.setenv(DISABLE_ENV, "1")
    return request.param


@pytest.fixture(scope="module")
def radial_s():
    calib = make_calibration(RADIAL_S)
    bt = calib.dictionary().transpose(0, 1).contiguous()                  # (n_virtual, K)
    return bt, dictionary_tables(bt, calib.grid_shape), calib.grid_shape


def _dictionary_snapshots(bt: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """``n`` snapshots: one or two steering vectors of the dictionary plus weak noise."""
    g = torch.Generator().manual_seed(seed)
    rows = bt.transpose(0, 1)
    k1, k2 = (torch.randint(0, rows.shape[0], (n,), generator=g) for _ in range(2))
    second = (torch.rand(n, generator=g) * 0.9).to(torch.complex64)
    noise = torch.randn(n, bt.shape[0], dtype=torch.complex64, generator=g) * 0.05
    return rows[k1].conj() + second[:, None] * rows[k2].conj() + noise


@pytest.fixture(scope="session")
def dictionary_snapshots():
    """``make(bt, n, seed)``: ``n`` snapshots of one or two of the dictionary's steering vectors."""
    return _dictionary_snapshots
