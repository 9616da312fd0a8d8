"""Sparse RD: the RD cube restricted to the full-grid peak set ``S(tau)`` (eq. 2).

``S(tau) = U_{(r, l) in P(tau)} {(r, d) : d in T(r, l)}`` with ``T(r, l)`` the ``n_tx`` replica bins of
the peak's resolved Tx-0 Doppler bin (see :mod:`radarpc.dsp.ddma`). ``|S(tau)| = n_tx |P(tau)|``.

The mask of a point cloud with the RD-neighbourhood enrichment ``rdN`` is ``S*(tau)``: pass
``P*(tau)`` (``SpectralPointCloud.encode(rd).kept``) with its ``d0`` (``EncodedSet.tx0_doppler()``),
the set the cloud encodes and the one :func:`radarpc.pipelines.sparse_rd.write_sparse_rd` writes;
:func:`encoded_sparse_rd` does the three steps (detection, mask, masking) on cubes.
:func:`encoded_cells` gives that set from a one-frame cloud alone (its points' cells and ``d0``).
"""
from __future__ import annotations

import torch

from radarpc.dsp.ddma import check_rd, replica_bins, resolve_tx0_doppler, rx_magnitude_sum
from radarpc.dsp.pointcloud import EncodedSet, SpectralPointCloud
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import DDMARadarConfig

__all__ = ["sparse_rd_mask", "sparse_rd", "encoded_sparse_rd", "encoded_cells"]


def sparse_rd_mask(mask_consolidated: torch.Tensor, cfg: DDMARadarConfig,
                   source: torch.Tensor) -> torch.Tensor:
    """Full-grid peak set ``S(tau)`` as a boolean mask.

    Parameters
    ----------
    mask_consolidated : BoolTensor, ``(B, Nr, slot_width)`` or ``(Nr, slot_width)``
        ``P(tau)`` (or ``P*(tau)``), e.g. from :meth:`SpectralPointCloud.detect`.
    cfg : DDMARadarConfig
    source : Tensor
        Either the RD cube(s) ``(B, Nr, Nd, Nrx)`` / ``(Nr, Nd, Nrx)`` complex, from which each
        peak's Tx-0 Doppler bin is resolved, or those bins ``d0`` already resolved: a LongTensor
        ``(P,)`` in the order of ``torch.nonzero(mask_consolidated)`` (frame, range, Doppler
        row-major), e.g. ``PointCloudBatch.doppler_full``.

    Returns
    -------
    BoolTensor, ``(B, Nr, Nd)``
    """
    m = mask_consolidated.unsqueeze(0) if mask_consolidated.ndim == 2 else mask_consolidated
    if m.dtype != torch.bool or m.ndim != 3 or tuple(m.shape[1:]) != (cfg.n_range, cfg.slot_width):
        raise ValueError(f"mask_consolidated must be a bool (B, {cfg.n_range}, {cfg.slot_width}) "
                         f"tensor, got {m.dtype} {tuple(mask_consolidated.shape)}")
    b, r, l = torch.nonzero(m, as_tuple=True)
    if source.is_complex():
        rd = check_rd(source, cfg)
        if rd.shape[0] != m.shape[0]:
            raise ValueError(f"rd has {rd.shape[0]} frames, the mask {m.shape[0]}")
        d0 = resolve_tx0_doppler(rx_magnitude_sum(rd), cfg, r, l, b)
    else:
        if source.dtype.is_floating_point or source.ndim != 1 or source.numel() != b.numel():
            raise ValueError(f"d0 must be an integer tensor of one full Doppler bin per peak "
                             f"({b.numel()} peaks), got {source.dtype} {tuple(source.shape)}")
        d0 = source.to(device=m.device, dtype=torch.long)
        if bool(((d0 % cfg.slot_width) != l).any()):
            raise ValueError("d0 does not match the mask: d0 mod slot_width must equal each peak's "
                             "consolidated Doppler index (peaks in torch.nonzero order)")
    out = torch.zeros(m.shape[0], cfg.n_range, cfg.n_doppler, dtype=torch.bool, device=m.device)
    bins = replica_bins(cfg, d0)                                      # (P, n_tx)
    out[b.unsqueeze(-1), r.unsqueeze(-1), bins] = True
    return out


def sparse_rd(rd: torch.Tensor, mask_full: torch.Tensor) -> torch.Tensor:
    """The RD cube kept on ``S(tau)`` and zero elsewhere.

    Parameters
    ----------
    rd : Tensor, complex, ``(B, Nr, Nd, Nrx)`` or ``(Nr, Nd, Nrx)``
    mask_full : BoolTensor, ``(B, Nr, Nd)`` or ``(Nr, Nd)`` from :func:`sparse_rd_mask`

    Returns
    -------
    Tensor, complex, shaped like ``rd`` with a batch axis: ``(B, Nr, Nd, Nrx)``
    """
    if not isinstance(rd, torch.Tensor) or not rd.is_complex():
        raise ValueError(f"rd must be a complex tensor, got {getattr(rd, 'dtype', type(rd).__name__)}")
    x = rd.unsqueeze(0) if rd.ndim == 3 else rd
    m = mask_full.unsqueeze(0) if mask_full.ndim == 2 else mask_full
    if x.ndim != 4 or m.dtype != torch.bool or tuple(m.shape) != tuple(x.shape[:3]):
        raise ValueError(f"mask_full must be bool with shape {tuple(x.shape[:3])} (B, Nr, Nd) of rd, "
                         f"got {m.dtype} {tuple(mask_full.shape)}")
    return torch.where(m.unsqueeze(-1), x, torch.zeros((), dtype=x.dtype, device=x.device))


@torch.no_grad()
def encoded_sparse_rd(spc: SpectralPointCloud, rd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, EncodedSet]:
    """RD cubes masked to the set ``spc``'s point clouds of them encode.

    ``spc.encode(rd)`` (CFAR, threshold, ``P*(tau)`` with ``rdN``), then :func:`sparse_rd_mask` of
    its kept cells and their ``d0``, then :func:`sparse_rd`: what sparse-RD FFTRadNet reads at the
    density ``spc`` is set to.

    Parameters
    ----------
    spc : SpectralPointCloud
    rd : Tensor, complex, ``(B, Nr, Nd, Nrx)`` or ``(Nr, Nd, Nrx)``

    Returns
    -------
    sparse : Tensor, complex, ``(B, Nr, Nd, Nrx)``
    mask_full : BoolTensor, ``(B, Nr, Nd)``
    encoded : EncodedSet
    """
    enc = spc.encode(rd)
    mask_full = sparse_rd_mask(enc.kept, spc.sensor, enc.tx0_doppler())
    return sparse_rd(rd, mask_full), mask_full, enc


def encoded_cells(cloud: PointCloudBatch, cfg: DDMARadarConfig) -> torch.Tensor:
    """The full-grid set a one-frame cloud encodes, ``S(tau)`` (``S*(tau)`` with ``rdN`` points):
    :func:`sparse_rd_mask` of the points' consolidated cells and their ``d0``.

    Parameters
    ----------
    cloud : PointCloudBatch
        One frame (e.g. ``SpectralPointCloud(rd)`` of one cube, or ``PointStore[i]``); any point order.
    cfg : DDMARadarConfig

    Returns
    -------
    BoolTensor ``(Nr, Nd)``, on the CPU
    """
    r, l = cloud.range_bin.cpu().long(), cloud.doppler_bin.cpu().long()
    kept = torch.zeros(cfg.n_range, cfg.slot_width, dtype=torch.bool)
    kept[r, l] = True
    order = torch.argsort(r * cfg.slot_width + l)          # d0 in torch.nonzero(kept) order
    return sparse_rd_mask(kept, cfg, cloud.doppler_full.cpu().long()[order])[0]
