"""Sparse RD back to a dense cube: the virtual-array snapshots of a peak set placed at their RD cells.

A spectral point set is a compact encoding of the RD cells ``S(tau)`` (the seed's Fig. 4): the
snapshot ``v_j = vec(R[r_j, T(d0_j), :])`` of peak ``j`` holds the ``n_tx x n_rx`` values of its
``n_tx`` replica bins (:func:`radarpc.dsp.ddma.virtual_snapshots`). Putting every snapshot back at
``(r_j, (d0_j + doppler_offsets[tx]) mod N_D, rx)`` and zeros elsewhere gives the sparse-RD cube
``sparse_rd(R, S(tau))`` (:mod:`radarpc.dsp.sparse_rd`), the dense FFTRadNet's input in the
sparse-RD baseline.
"""
from __future__ import annotations

import torch

from radarpc.dsp.ddma import replica_bins
from radarpc.sensors.radial import DDMARadarConfig

__all__ = ["densify_rd"]


def densify_rd(offset: torch.Tensor, range_bin: torch.Tensor, doppler_full: torch.Tensor,
               snapshots: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """Dense complex RD cubes from offset-batched peaks and their virtual snapshots.

    Parameters
    ----------
    offset : LongTensor ``(B,)``
        Cumulative end index of each frame's peaks (``offset[-1] = P``), as
        :class:`radarpc.points.PointCloudBatch`.
    range_bin, doppler_full : LongTensor ``(P,)``
        Range bin and resolved Tx-0 full Doppler bin ``d0`` of each peak.
    snapshots : complex Tensor ``(P, n_tx * n_rx)``
        Tx-major virtual snapshots (entry ``tx * n_rx + rx``).
    cfg : DDMARadarConfig

    Returns
    -------
    complex Tensor ``(B, Nr, Nd, Nrx)``, zero outside the peaks' replica cells.

    Two peaks of one frame and range bin never share a cell: replica bins are ``d0 mod slot_width``
    apart from those of any other consolidated Doppler index.
    """
    offset = torch.as_tensor(offset)
    p = snapshots.shape[0] if snapshots.ndim else -1
    if offset.ndim != 1 or offset.numel() == 0 or (offset.numel() and int(offset[-1]) != p):
        raise ValueError(f"offset must be a non-empty (B,) cumulative count ending at the number of "
                         f"snapshots {p}, got {offset.tolist() if offset.numel() < 10 else tuple(offset.shape)}")
    if not snapshots.is_complex() or snapshots.ndim != 2 or snapshots.shape[1] != cfg.n_virtual:
        raise ValueError(f"snapshots must be complex (P, n_tx * n_rx = {cfg.n_virtual}), got "
                         f"{snapshots.dtype} {tuple(snapshots.shape)}")
    if range_bin.shape != (p,) or doppler_full.shape != (p,):
        raise ValueError(f"range_bin and doppler_full must be ({p},), got {tuple(range_bin.shape)} and "
                         f"{tuple(doppler_full.shape)}")
    counts = torch.diff(offset, prepend=offset.new_zeros(1))
    if bool((counts < 0).any()):
        raise ValueError(f"offset must be non-decreasing, got {offset.tolist()}")
    dev = snapshots.device
    b = torch.repeat_interleave(torch.arange(offset.numel(), device=dev), counts.to(dev))   # (P,)
    bins = replica_bins(cfg, doppler_full.to(dev))                                         # (P, n_tx)
    out = torch.zeros(offset.numel(), cfg.n_range, cfg.n_doppler, cfg.n_rx, dtype=snapshots.dtype, device=dev)
    v = snapshots.reshape(p, cfg.n_tx, cfg.n_rx)                                           # (P, n_tx, n_rx)
    out[b.view(-1, 1), range_bin.to(dev).view(-1, 1), bins] = v
    return out
