"""Fixtures shared by the DSP tests: the native extensions of radarpc.dsp.accel, enabled or disabled."""
from __future__ import annotations

import os

import pytest

from radarpc.dsp.accel import DISABLE_ENV, native


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
