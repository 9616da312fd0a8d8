"""DDMA consolidation: RD envelope, Tx-0 Doppler hypothesis, replica bins, virtual snapshots.

Conventions are those of :mod:`radarpc.sensors.radial` (and of RADIal's ``rpl.py``). With
``W = slot_width`` and ``n_slots`` DDMA slots, a target of true Doppler bin ``d0`` appears for
Tx ``m`` at bin ``(d0 + doppler_offsets[m]) mod N_D``. The seed's quantities become

* ``A(r, d) = sum_rx |R(rx, r, d)|``                       magnitude sum over receivers;
* ``T(r, l) = {(d0 + doppler_offsets[m]) mod N_D}_m``      the M = n_tx replica bins of a cell;
* ``E(r, l) = sum_{d in T(r, l)} A(r, d)``                 RD envelope, ``l = d mod W`` (eq. 1:
  power summed over the Rx, then over the Tx-replica bins of the consolidated cell);
* ``E_all(r, l) = sum_{s < n_slots} A(r, s W + l)``         RADIal ``rpl.py``'s envelope, which also
  adds the ``n_empty_slots`` noise-only slots (``envelope="all-slots"``);
* ``v_j = vec(R[r_j, T(r_j, l_j), :])``                    the Tx-major virtual snapshot (eq. 4).

The DDMA hypothesis (which slot holds Tx 0) is resolved from the empty slots: the ``n_slots``
values ``A(r, l + s W)`` are read circularly and the window of ``n_empty_slots`` consecutive
slots with the least mean power is the gap; the slot just before it is Tx 0's. The replica
sum is then ``E = E_all - min_s G_s`` with ``G_s`` the window sums of that search
(:func:`ddma_envelope` computes both at once).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from radarpc.dsp.native import native_supports, rx_magnitude_sum_native
from radarpc.sensors.radial import DDMARadarConfig

__all__ = [
    "check_rd",
    "rx_magnitude_sum",
    "consolidate",
    "ENVELOPES",
    "DDMAEnvelope",
    "gap_window_sums",
    "ddma_envelope",
    "rd_envelope",
    "check_finite_envelope",
    "check_envelope_kind",
    "resolve_tx0_doppler",
    "replica_bins",
    "virtual_snapshots",
]

ENVELOPES = ("replicas", "all-slots")
"""Envelope kinds: the seed's sum over the ``n_tx`` replica bins, or RADIal rpl.py's sum over
every slot (empty slots included)."""

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

    Magnitude, not power, as in RADIal's processing. On CPU a contiguous complex64 cube goes to
    the compiled kernel of :mod:`radarpc.dsp.native` when it is built (one pass over the cube,
    ~2.7x faster); otherwise the computation runs in row blocks with preallocated
    ``re^2 + im^2`` and ``sqrt`` buffers (several times faster than ``rd.abs()``); elsewhere in
    one pass. All give the same values up to float32 rounding of the receiver sum.
    """
    if native_supports(rd):
        return rx_magnitude_sum_native(rd)
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


def check_envelope_kind(envelope: str) -> str:
    """Validate an envelope kind (one of :data:`ENVELOPES`)."""
    if envelope not in ENVELOPES:
        raise ValueError(f"envelope must be one of {ENVELOPES} ('replicas' = seed eq. 1, sum over the "
                         f"n_tx replica bins; 'all-slots' = RADIal rpl.py, sum over every slot), got {envelope!r}")
    return envelope


def gap_window_sums(x: torch.Tensor, n_gap: int, dim: int = -1) -> torch.Tensor:
    """``G_s = x_{s+1} + ... + x_{s+n_gap}`` (indices mod ``n_slots``) along the slot axis ``dim``.

    The sums of the circular windows of ``n_gap`` consecutive slots *after* slot ``s``; the gap
    follows Tx 0, so ``argmin_s G_s`` is Tx 0's slot. One implementation (sequential adds in the
    same order) serves the whole-map envelope and the per-peak search, so both resolve the same
    slot bit for bit.
    """
    n = x.shape[dim]
    ext = torch.cat([x, x.narrow(dim, 0, n_gap)], dim=dim)                # circular continuation
    out = ext.narrow(dim, 1, n).clone()
    for k in range(2, n_gap + 1):
        out += ext.narrow(dim, k, n)
    return out


@dataclass
class DDMAEnvelope:
    """Consolidated maps of a batch of cubes.

    Attributes
    ----------
    mag_sum : Tensor ``(B, Nr, Nd)``      ``A = sum_rx |R|``
    all_slots : Tensor ``(B, Nr, W)``     ``E_all``: sum over every slot (RADIal rpl.py)
    replicas : Tensor ``(B, Nr, W)``      ``E``: sum over the ``n_tx`` replica bins (seed eq. 1)
    tx0_slot : LongTensor ``(B, Nr, W)``  slot of the Tx-0 replica of every cell
    """

    mag_sum: torch.Tensor
    all_slots: torch.Tensor
    replicas: torch.Tensor
    tx0_slot: torch.Tensor

    def envelope(self, kind: str) -> torch.Tensor:
        """``replicas`` or ``all_slots`` by kind (:data:`ENVELOPES`)."""
        return self.replicas if check_envelope_kind(kind) == "replicas" else self.all_slots

    def tx0_doppler(self, batch_idx: torch.Tensor, range_idx: torch.Tensor,
                    cons_idx: torch.Tensor) -> torch.Tensor:
        """Full Doppler bin ``d0 = slot * W + l`` of the Tx-0 replica of cells ``(b, r, l)``: ``(P,)``."""
        w = self.all_slots.shape[-1]
        return self.tx0_slot[batch_idx, range_idx, cons_idx] * w + cons_idx


def ddma_envelope(a: torch.Tensor, cfg: DDMARadarConfig) -> DDMAEnvelope:
    """Both envelopes and the Tx-0 slot of every consolidated cell from ``A`` ``(B, Nr, Nd)``.

    ``x_s = A(r, s W + l)``, ``G_s`` = :func:`gap_window_sums`, ``s0 = argmin_s G_s`` (first on
    ties, as :func:`resolve_tx0_doppler`), ``E_all = sum_s x_s`` and ``E = E_all - G_{s0}``: the
    sum over the ``n_tx`` slots ``s0 + tx_slots`` (the replica bins ``T(r, l)``).
    """
    x = a.reshape(a.shape[:-1] + (cfg.n_slots, cfg.slot_width))            # (B, Nr, n_slots, W)
    e_all = x.sum(-2)                                                       # (B, Nr, W)
    g = gap_window_sums(x, cfg.n_empty_slots, dim=-2)                       # (B, Nr, n_slots, W)
    g_min, slot = torch.min(g, dim=-2)                                      # (B, Nr, W) each
    return DDMAEnvelope(mag_sum=a, all_slots=e_all, replicas=(e_all - g_min).clamp_min_(0.0), tx0_slot=slot)


def rd_envelope(rd: torch.Tensor, cfg: DDMARadarConfig, envelope: str = "replicas") -> torch.Tensor:
    """RD envelope of a cube (batch): the seed's ``E(r, l) = sum_{d in T(r, l)} sum_rx |R(r, d, rx)|``.

    Parameters
    ----------
    rd : Tensor, complex, ``(B, Nr, Nd, Nrx)`` or ``(Nr, Nd, Nrx)``
    cfg : DDMARadarConfig
    envelope : {"replicas", "all-slots"}
        ``"replicas"`` (default, seed eq. 1): the sum over the ``M = n_tx`` replica bins of each
        consolidated cell. ``"all-slots"`` = RADIal ``rpl.py``: the sum over all ``n_slots``
        slots, i.e. plus the ``n_empty_slots`` noise-only slots.

    Returns
    -------
    Tensor, real, ``(B, Nr, slot_width)``
    """
    check_envelope_kind(envelope)
    rd = check_rd(rd, cfg)
    a = rx_magnitude_sum(rd)
    e = consolidate(a, cfg) if envelope == "all-slots" else ddma_envelope(a, cfg).replicas
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
    m = gap_window_sums(x, g, dim=1)                               # (P, n_slots): sum of x_{s+1..s+G}
    slot = torch.min(m, dim=1).indices
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
