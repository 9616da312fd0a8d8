"""Workspace: reuse, growth, per-thread buffers, copies start empty, bad sizes."""
from __future__ import annotations

import copy
import pickle
import threading

import pytest
import torch

from radarpc.dsp.accel.workspace import Workspace


def test_buffers_are_reused_and_grown():
    ws = Workspace()
    cpu = torch.device("cpu")
    a = ws.empty("x", (4, 8), torch.float32, cpu)
    a.fill_(1.0)
    b = ws.empty("x", (2, 8), torch.float32, cpu)                 # smaller: a view of the same memory
    assert b.data_ptr() == a.data_ptr() and b.shape == (2, 8) and bool((b == 1).all())
    c = ws.empty("x", (10, 8), torch.float32, cpu)                # larger: a new buffer
    assert c.shape == (10, 8) and ws.nbytes == 10 * 8 * 4
    d = ws.empty("x", (3, 3), torch.float64, cpu)                 # another dtype is another buffer
    assert d.dtype == torch.float64 and ws.nbytes == 10 * 8 * 4 + 9 * 8
    assert ws.empty("y", (0, 5), torch.float32, cpu).shape == (0, 5)
    ws.clear()
    assert ws.nbytes == 0
    with pytest.raises(ValueError, match="negative"):
        ws.empty("x", (-1, 3), torch.float32, cpu)


def test_threads_get_their_own_buffers_and_copies_start_empty():
    ws = Workspace()
    main = ws.empty("x", (16,), torch.float32, "cpu")
    ptrs = []
    t = threading.Thread(target=lambda: ptrs.append(ws.empty("x", (16,), torch.float32, "cpu").data_ptr()))
    t.start()
    t.join()
    assert ptrs and ptrs[0] != main.data_ptr()
    for clone in (copy.deepcopy(ws), pickle.loads(pickle.dumps(ws))):
        assert clone.nbytes == 0
        assert clone.empty("x", (2,), torch.float32, "cpu").shape == (2,)


def test_beamformers_give_the_same_result_with_a_reused_workspace():
    from radarpc.dsp.accel.screened import beamform_peaks_screened
    from radarpc.dsp.beamform import beamform_peaks
    from radarpc.sensors.radial import TINY
    from radarpc.sim.radial_calibration import make_calibration
    calib = make_calibration(TINY)
    bt = calib.dictionary().transpose(0, 1).contiguous()
    g = torch.Generator().manual_seed(2)
    ws = Workspace()
    for p in (50, 7, 120):                                         # shrinking and growing batches
        v = torch.randn(p, bt.shape[0], dtype=torch.complex64, generator=g)
        ref = beamform_peaks(v, bt, calib.grid_shape, (4, 1))
        got = beamform_peaks(v, bt, calib.grid_shape, (4, 1), workspace=ws)
        assert torch.equal(ref.index, got.index) and torch.equal(ref.sectors, got.sectors)
        scr = beamform_peaks_screened(v, bt, calib.grid_shape, workspace=ws)
        assert torch.equal(scr.index, ref.index)
