"""Sparse RD keeps exactly S(tau): the n_tx replica cells of every consolidated peak."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from radarpc.dsp.ddma import replica_bins
from radarpc.dsp.density import density_of_mask
from radarpc.dsp.pointcloud import SpectralPointCloud
from radarpc.dsp.sparse_rd import encoded_cells, encoded_sparse_rd, sparse_rd, sparse_rd_mask
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


@pytest.mark.parametrize("enrich", [(), ("rd3",)])
def test_encoded_cells_of_a_cloud_is_its_sparse_rd_mask(enrich):
    # the set a one-frame cloud encodes, from its points alone, is the mask of the cube's P (P*)
    cfg = TINY
    g = torch.Generator().manual_seed(3)
    sc = Scatterers(torch.tensor([8.0, 15.0, 22.0]), torch.tensor([-10.0, 20.0, 5.0]), torch.zeros(3),
                    torch.tensor([2.0, -5.0, 1.0]), torch.tensor([10.0, 10.0, 10.0]))
    rd = synthesize_rd(cfg, [sc], noise=True, generator=g)
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=0.1, enrich=enrich)
    enc, cloud = spc.encode(rd), spc(rd)
    want = sparse_rd_mask(enc.kept, cfg, rd)[0]                        # d0 resolved from the cube
    got = encoded_cells(cloud, cfg)
    assert torch.equal(got, want) and int(got.sum()) == cfg.n_tx * cloud.num_points > 0
    # every point's range x its n_tx replica bins, built by hand
    ref = torch.zeros(cfg.n_range, cfg.n_doppler, dtype=torch.bool)
    bins = replica_bins(cfg, cloud.doppler_full)
    ref[cloud.range_bin[:, None].expand_as(bins), bins] = True
    assert torch.equal(got, ref)
    # any point order gives the same cells
    perm = torch.randperm(cloud.num_points, generator=torch.Generator().manual_seed(0))
    shuffled = type(cloud)(**{**{k: getattr(cloud, k) for k in ("offset", "tau", "density", "peak_density")},
                              **{k: (None if getattr(cloud, k) is None else getattr(cloud, k)[perm])
                                 for k in cloud._PER_POINT}})
    assert torch.equal(encoded_cells(shuffled, cfg), want)


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


@pytest.mark.parametrize("enrich", [(), ("rd3",)], ids=["S", "S*"])
def test_encoded_sparse_rd_keeps_the_cells_the_cloud_encodes(enrich):
    cfg = TINY
    g = torch.Generator().manual_seed(2)
    sc = Scatterers(torch.tensor([8.0, 15.0]), torch.tensor([-10.0, 20.0]), torch.zeros(2),
                    torch.tensor([2.0, -5.0]), torch.tensor([10.0, 10.0]))
    rd = synthesize_rd(cfg, [sc, sc], noise=True, generator=g)
    spc = SpectralPointCloud(cfg, make_calibration(cfg), density=0.05, enrich=enrich)
    sparse, mask, enc = encoded_sparse_rd(spc, rd)
    clouds = spc(rd)
    for b in range(2):                       # the set each frame's cloud encodes, from its points alone
        assert torch.equal(mask[b], encoded_cells(clouds.frame(b), cfg))
    assert torch.equal(sparse, torch.where(mask[..., None], rd, torch.zeros((), dtype=rd.dtype)))
    assert torch.equal(enc.kept, spc.encode(rd).kept)
    one, one_mask, _ = encoded_sparse_rd(spc, rd[0])                 # one frame without a batch axis
    assert one.shape == (1, *cfg.rd_shape) and torch.equal(one_mask[0], mask[0])
