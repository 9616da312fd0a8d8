"""Densifying the virtual snapshots of a peak set gives back the sparse-RD cube of that set."""
from __future__ import annotations

import pytest
import torch

from radarpc.dsp.ddma import virtual_snapshots
from radarpc.dsp.densify import densify_rd
from radarpc.dsp.sparse_rd import sparse_rd, sparse_rd_mask
from radarpc.sensors.radial import TINY


def test_densify_inverts_snapshots_on_s_tau():
    cfg = TINY
    g = torch.Generator().manual_seed(0)
    rd = torch.randn(2, cfg.n_range, cfg.n_doppler, cfg.n_rx, dtype=torch.complex64, generator=g)
    # peaks: frame 0 two in one range bin (different consolidated indices), frame 1 one
    mask = torch.zeros(2, cfg.n_range, cfg.slot_width, dtype=torch.bool)
    mask[0, 5, 1] = mask[0, 5, 6] = mask[1, 40, 3] = True
    b, r, l = torch.nonzero(mask, as_tuple=True)
    d0 = l + torch.tensor([0, 2, 3]) * cfg.slot_width     # any slot: d0 mod slot_width = l
    v = virtual_snapshots(rd, cfg, b, r, d0)
    dense = densify_rd(torch.tensor([2, 3]), r, d0, v, cfg)
    ref = sparse_rd(rd, sparse_rd_mask(mask, cfg, d0))
    assert torch.equal(dense, ref)                        # placements only: exact
    assert int((dense != 0).any(-1).sum()) == 3 * cfg.n_tx


def test_densify_empty_frame_and_bad_offsets():
    cfg = TINY
    v = torch.ones(1, cfg.n_virtual, dtype=torch.complex64)
    out = densify_rd(torch.tensor([0, 1]), torch.tensor([3]), torch.tensor([2]), v, cfg)
    assert out.shape == (2, cfg.n_range, cfg.n_doppler, cfg.n_rx) and not out[0].any()
    with pytest.raises(ValueError, match="offset must be a non-empty"):
        densify_rd(torch.tensor([0, 2]), torch.tensor([3]), torch.tensor([2]), v, cfg)
    with pytest.raises(ValueError, match="snapshots must be complex"):
        densify_rd(torch.tensor([1]), torch.tensor([3]), torch.tensor([2]), v.real, cfg)
