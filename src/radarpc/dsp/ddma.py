"""DDMA consolidation: RD envelope, Tx-0 Doppler hypothesis, replica bins, virtual snapshots.

Conventions are those of :mod:`radarpc.sensors.radial` (and of RADIal's ``rpl.py``). With
``W = slot_width`` and ``n_slots`` DDMA slots, a target of true Doppler bin ``d0`` appears for
Tx ``m`` at bin ``(d0 + doppler_offsets[m]) mod N_D``. The seed's quantities become

* ``A(r, d) = sum_rx |R(rx, r, d)|``                       magnitude sum over receivers;
* ``E(r, l) = sum_{s < n_slots} A(r, s * W + l)``          RD envelope, ``l = d mod W`` (eq. 1);
* ``T(r, l) = {(d0 + doppler_offsets[m]) mod N_D}_m``      the M = n_tx replica bins of a peak;
* ``v_j = vec(R[r_j, T(r_j, l_j), :])``                    the Tx-major virtual snapshot (eq. 4).

The DDMA hypothesis (which slot holds Tx 0) is resolved from the empty slots: the ``n_slots``
values ``A(r, l + s W)`` are read circularly and the window of ``n_empty_slots`` consecutive
slots with the least mean power is the gap; the slot just before it is Tx 0's.
"""
from __future__ import annotations

import torch

from radarpc.sensors.radial import DDMARadarConfig

__all__ = [
    "check_rd",
    "rx_magnitude_sum",
    "consolidate",
    "rd_envelope",
    "check_finite_envelope",
    "resolve_tx0_doppler",
    "replica_bins",
    "virtual_snapshots",
]

# Rows of the (B * Nr) axis processed per block on CPU: keeps the |.| intermediates in cache.
_CPU_BLOCK_BYTES = 1 << 21


def check_rd(rd: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """Validate an RD cube (batch) against ``cfg`` and return it as ``(B, Nr, Nd, Nrx)``.

    Raises
    ------
    ValueError
        Not a complex tensor, or a shape other than ``(Nr, Nd, Nrx)`` / ``(B, Nr, Nd, Nrx)`` of
        the sensor. (NaN is detected later, on the envelope, where it costs nothing.)
    """
    if not isinstance(rd, torch.Tensor):
        raise ValueError(f"rd must be a complex torch.Tensor, got {type(rd).__name__}")
    if not rd.is_complex():
        raise ValueError(f"rd must be complex (the per-Rx RD spectrum), got dtype {rd.dtype}")
    expected = cfg.rd_shape
    if rd.ndim not in (3, 4) or tuple(rd.shape[-3:]) != expected:
        raise ValueError(f"rd must have shape (B, {expected[0]}, {expected[1]}, {expected[2]}) or "
                         f"{expected} for sensor {cfg.name!r} (n_range, n_doppler, n_rx), "
                         f"got {tuple(rd.shape)}")
    return rd if rd.ndim == 4 else rd.unsqueeze(0)


def rx_magnitude_sum(rd: torch.Tensor) -> torch.Tensor:
    """``A = sum_rx |rd|`` over the last axis: ``(..., Nr, Nd, Nrx)`` complex -> ``(..., Nr, Nd)`` real.

    Magnitude, not power, as in RADIal's processing. On CPU the computation runs in row blocks
    with preallocated ``re^2 + im^2`` and ``sqrt`` buffers (several times faster than ``rd.abs()``); elsewhere in
    one pass. Both give the same values.
    """
    x = torch.view_as_real(rd.resolve_conj())                   # (..., Nd, Nrx, 2)
    if rd.device.type != "cpu":
        sq = x.square()
        return torch.add(sq[..., 0], sq[..., 1]).sqrt_().sum(-1)
    nd, nrx = rd.shape[-2], rd.shape[-1]
    rows = x.reshape(-1, nd, nrx, 2)                             # (B*Nr, Nd, Nrx, 2)
    n = rows.shape[0]
    out = torch.empty(n, nd, dtype=x.dtype, device=x.device)
    step = max(1, _CPU_BLOCK_BYTES // max(1, nd * nrx * 2 * x.element_size()))
    sq = torch.empty(min(step, n), nd, nrx, 2, dtype=x.dtype, device=x.device)
    mag = torch.empty(min(step, n), nd, nrx, dtype=x.dtype, device=x.device)
    for i in range(0, n, step):
        c = rows[i:i + step]
        m = c.shape[0]
        torch.mul(c, c, out=sq[:m])                              # contiguous re^2, im^2
        torch.add(sq[:m, ..., 0], sq[:m, ..., 1], out=mag[:m]).sqrt_()
        torch.sum(mag[:m], dim=-1, out=out[i:i + m])
    return out.reshape(rd.shape[:-1])


def consolidate(a: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """Sum the Doppler axis over the DDMA slots: ``(..., Nr, Nd) -> (..., Nr, slot_width)``."""
    shape = a.shape[:-1] + (cfg.n_slots, cfg.slot_width)
    return a.reshape(shape).sum(-2)


def rd_envelope(rd: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """RD envelope ``E(r, l) = sum_s sum_rx |R(rx, r, s W + l)|`` (the seed's consolidated map).

    Parameters
    ----------
    rd : Tensor, complex, ``(B, Nr, Nd, Nrx)`` or ``(Nr, Nd, Nrx)``
    cfg : DDMARadarConfig

    Returns
    -------
    Tensor, real, ``(B, Nr, slot_width)``
    """
    rd = check_rd(rd, cfg)
    e = consolidate(rx_magnitude_sum(rd), cfg)
    check_finite_envelope(e)
    return e


def check_finite_envelope(e: torch.Tensor) -> None:
    """NaN or inf anywhere in a cube propagates into its envelope: check the small map."""
    bad = ~torch.isfinite(e).flatten(1).all(dim=1)
    if bool(bad.any()):
        frames = torch.nonzero(bad).flatten().tolist()
        raise ValueError(f"rd contains NaN or infinite values (or overflows float) in frame(s) "
                         f"{frames[:10]}{' ...' if len(frames) > 10 else ''}")


def _flat_index(a: torch.Tensor, batch_idx: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    if a.ndim == 2:
        a = a.unsqueeze(0)
    if batch_idx is None:
        if a.shape[0] != 1:
            raise ValueError(f"batch_idx is required for a batch of {a.shape[0]} frames")
        return a, torch.zeros((), dtype=torch.long, device=a.device)
    return a, batch_idx.long()


def resolve_tx0_doppler(rd_mag_sum: torch.Tensor, cfg: DDMARadarConfig, range_idx: torch.Tensor,
                        cons_idx: torch.Tensor, batch_idx: torch.Tensor | None = None) -> torch.Tensor:
    """Full Doppler bin ``d0`` of the Tx-0 replica of each consolidated peak ``(r, l)``.

    ``x_s = A(r, l + s W)`` for ``s = 0..n_slots-1``; with ``G = n_empty_slots`` and indices mod
    ``n_slots``, ``m_s = mean(x_{s+1}, ..., x_{s+G})`` is the mean over the ``G`` slots after
    ``s``; the gap follows Tx 0, so ``slot = argmin_s m_s`` and ``d0 = slot * W + l``.

    Parameters
    ----------
    rd_mag_sum : Tensor, ``(B, Nr, Nd)`` or ``(Nr, Nd)``
        ``A`` from :func:`rx_magnitude_sum`.
    range_idx, cons_idx : LongTensor, ``(P,)``
        Range bin and consolidated Doppler index of each peak.
    batch_idx : LongTensor, ``(P,)``, optional
        Frame of each peak; may be omitted for a single frame.

    Returns
    -------
    LongTensor, ``(P,)``
    """
    a, b = _flat_index(rd_mag_sum, batch_idx)
    w, ns, g = cfg.slot_width, cfg.n_slots, cfg.n_empty_slots
    r = range_idx.long()
    l = cons_idx.long()
    s = torch.arange(ns, device=a.device)
    cols = l.unsqueeze(-1) + s * w                                 # (P, n_slots) Doppler bins
    if a.is_contiguous():
        x = a.view(-1).take((b * a.shape[1] + r).unsqueeze(-1) * a.shape[2] + cols)
    else:
        x = a[b.unsqueeze(-1) if b.ndim else b, r.unsqueeze(-1), cols]  # (P, n_slots)
    ext = torch.cat([x, x[:, :g]], dim=1)                          # circular continuation
    m = ext[:, 1:].unfold(1, g, 1).sum(-1)                         # (P, n_slots): sum of x_{s+1..s+G}
    slot = torch.argmin(m, dim=1)
    return slot * w + l


def replica_bins(cfg: DDMARadarConfig, d0: torch.Tensor) -> torch.Tensor:
    """The ``M = n_tx`` full-Doppler bins ``(d0 + doppler_offsets) mod N_D`` in Tx order: ``(P, n_tx)``."""
    off = torch.as_tensor(cfg.doppler_offsets, device=d0.device)
    return (d0.long().unsqueeze(-1) + off) % cfg.n_doppler


def virtual_snapshots(rd: torch.Tensor, cfg: DDMARadarConfig, batch_idx: torch.Tensor | None,
                      range_idx: torch.Tensor, d0: torch.Tensor) -> torch.Tensor:
    """Virtual-array snapshots ``v_j = vec(R[r_j, T_j, :])``, Tx-major: ``(P, n_tx * n_rx)`` complex.

    Entry ``tx * n_rx + rx`` is ``rd[b_j, r_j, (d0_j + doppler_offsets[tx]) mod N_D, rx]``.
    ``batch_idx`` may be ``None`` for a single frame ``(Nr, Nd, Nrx)``.
    """
    if rd.ndim == 3:
        rd = rd.unsqueeze(0)
    if batch_idx is None:
        if rd.shape[0] != 1:
            raise ValueError(f"batch_idx is required for a batch of {rd.shape[0]} frames")
        batch_idx = torch.zeros_like(range_idx)
    bins = replica_bins(cfg, d0)                                   # (P, n_tx)
    row = batch_idx.long() * cfg.n_range + range_idx.long()        # (P,) index of (b, r)
    if rd.is_contiguous():                                         # row gather: fast on CPU and GPU
        flat = (row.unsqueeze(-1) * cfg.n_doppler + bins).reshape(-1)
        v = rd.view(-1, rd.shape[-1]).index_select(0, flat)        # (P * n_tx, n_rx)
    else:
        v = rd[batch_idx.long().unsqueeze(-1), range_idx.long().unsqueeze(-1), bins]  # (P, n_tx, n_rx)
    return v.reshape(-1, cfg.n_virtual)
