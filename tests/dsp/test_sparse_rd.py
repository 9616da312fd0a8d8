"""Sparse RD keeps exactly S(tau): the n_tx replica cells of every consolidated peak."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp.density import density_of_mask
from radarpc.dsp.pointcloud import SpectralPointCloud
from radarpc.dsp.sparse_rd import sparse_rd, sparse_rd_mask
from radarpc.sensors.radial import RADIAL_S, TINY
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.rd import Scatterers, synthesize_rd


@pytest.mark.parametrize("cfg", [TINY, RADIAL_S], ids=lambda c: c.name)
def test_sparse_rd_keeps_exactly_s_tau(cfg):
    g = torch.Generator().manual_seed(0)
    sc = Scatterers(torch.tensor([8.0, 15.0]), torch.tensor([-10.0, 20.0]), torch.zeros(2),
                    torch.tensor([2.0, -5.0]), torch.tensor([10.0, 10.0]))
    rd = synthesize_rd(cfg, [sc, sc], noise=True, generator=g)
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=0.05)
    _, _, mask = spc.detect(rd)
    clouds = spc(rd)
    s_mask = sparse_rd_mask(mask, cfg, rd)
    assert s_mask.shape == (2, cfg.n_range, cfg.n_doppler)
    # |S| = n_tx |P| and the density matches the cloud's
    assert int(s_mask.sum()) == cfg.n_tx * int(mask.sum())
    torch.testing.assert_close(density_of_mask(s_mask, cfg), clouds.density)
    # S is exactly the union of each point's replica bins (built here by loops)
    ref = np.zeros(s_mask.shape, dtype=bool)
    bidx = np.repeat(np.arange(2), np.diff(clouds.offset.numpy(), prepend=0))
    for b, r, d0 in zip(bidx, clouds.range_bin.numpy(), clouds.doppler_full.numpy()):
        for slot in cfg.tx_slots:
            ref[b, r, (d0 + slot * cfg.slot_width) % cfg.n_doppler] = True
    np.testing.assert_array_equal(s_mask.numpy(), ref)
    # the d0 path gives the same set
    torch.testing.assert_close(sparse_rd_mask(mask, cfg, clouds.doppler_full), s_mask)
    # masked cube: rd on S, 0 elsewhere
    sp = sparse_rd(rd, s_mask)
    assert sp.dtype == rd.dtype and sp.shape == rd.shape
    assert torch.equal(sp[s_mask], rd[s_mask])
    assert int((sp[~s_mask] != 0).sum()) == 0


def test_sparse_rd_of_rd_neighbourhood_cloud_is_s_star():
    # with rd3 the cloud encodes S*(tau): one point per kept cell of P*, each with its own d0
    cfg = RADIAL_S
    g = torch.Generator().manual_seed(2)
    sc = Scatterers(torch.tensor([20.0, 40.0]), torch.tensor([-10.0, 20.0]), torch.zeros(2),
                    torch.tensor([3.0, -6.0]), torch.tensor([10.0, 10.0]))
    rd = synthesize_rd(cfg, [sc], noise=True, generator=g)
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=0.05, enrich=("rd3",))
    enc = spc.encode(rd)
    clouds = spc(rd)
    assert int(enc.kept.sum()) > int(enc.peaks.sum()) and clouds.num_points == int(enc.kept.sum())
    s_star = sparse_rd_mask(enc.kept, cfg, enc.tx0_doppler())
    torch.testing.assert_close(density_of_mask(s_star, cfg), clouds.density)
    # the per-cell gap search on the cube resolves the same d0 as the envelope's map
    assert torch.equal(sparse_rd_mask(enc.kept, cfg, rd), s_star)
    assert torch.equal(enc.tx0_doppler(), clouds.doppler_full)


def test_single_frame_and_bad_input():
    cfg = TINY
    rd = torch.randn(cfg.rd_shape, dtype=torch.complex64, generator=torch.Generator().manual_seed(1))
    mask = torch.zeros(cfg.n_range, cfg.slot_width, dtype=torch.bool)
    mask[3, 2] = True
    s = sparse_rd_mask(mask, cfg, rd)
    assert s.shape == (1, cfg.n_range, cfg.n_doppler) and int(s.sum()) == cfg.n_tx
    assert s[0, 3].nonzero().flatten().remainder(cfg.slot_width).tolist() == [2] * cfg.n_tx
    assert sparse_rd(rd, s[0]).shape == (1, *cfg.rd_shape)
    with pytest.raises(ValueError, match="bool"):
        sparse_rd_mask(mask.float(), cfg, rd)
    with pytest.raises(ValueError, match="d0 must be"):
        sparse_rd_mask(mask, cfg, torch.tensor([2, 3]))
    with pytest.raises(ValueError, match="mod slot_width"):
        sparse_rd_mask(mask, cfg, torch.tensor([3]))
    with pytest.raises(ValueError, match="complex"):
        sparse_rd(rd.real, s)
    with pytest.raises(ValueError, match="mask_full"):
        sparse_rd(rd, s[:, :, :5])
