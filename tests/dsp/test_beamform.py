"""The exact beamformer and the float32 matmul precision setting (warned, never changed)."""
from __future__ import annotations

import pytest
import torch

from radarpc.dsp.beamform import beamform_peaks, reduced_fp32_matmul


def test_reduced_float32_matmul_precision_is_warned_not_changed(radial_s, dictionary_snapshots):
    bt, tables, grid = radial_s
    v = dictionary_snapshots(bt, 50, seed=4)
    assert not reduced_fp32_matmul("cpu")                              # torch's default: exact
    prev = torch.get_float32_matmul_precision()
    try:
        for precision in ("medium", "high"):
            torch.set_float32_matmul_precision(precision)
            assert reduced_fp32_matmul("cpu")
            with pytest.warns(RuntimeWarning, match="float32 matmul precision is reduced"):
                beamform_peaks(v, tables, grid)
            assert torch.get_float32_matmul_precision() == precision    # the setting is the user's
    finally:
        torch.set_float32_matmul_precision(prev)


def test_per_backend_precision_api_does_not_break_the_beamformer():
    # torch >= 2.9: after the per-backend fp32_precision settings, the legacy getter raises; run in a
    # fresh process, since that state cannot be undone reliably within one
    import subprocess
    import sys

    code = """
import warnings, torch
from radarpc.dsp.beamform import beamform_peaks, dictionary_tables, reduced_fp32_matmul
from radarpc.sensors.radial import TINY
from radarpc.sim.radial_calibration import make_calibration
if not hasattr(torch.backends.mkldnn.matmul, "fp32_precision"):
    print("no per-backend API"); raise SystemExit(0)
torch.backends.mkldnn.matmul.fp32_precision = "bf16"
calib = make_calibration(TINY)
bt = calib.dictionary().transpose(0, 1).contiguous()
v = torch.randn(8, bt.shape[0], dtype=torch.complex64)
assert reduced_fp32_matmul("cpu")
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    res = beamform_peaks(v, dictionary_tables(bt, calib.grid_shape), calib.grid_shape)
assert res.index.shape == (8,) and any("precision is reduced" in str(x.message) for x in w)
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() in ("ok", "no per-backend API")
