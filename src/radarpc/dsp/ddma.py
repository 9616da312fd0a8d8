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
(:func:`ddma_envelope` computes both at once). The envelope needs only ``min_s G_s``; the slot
``argmin_s G_s`` is looked up for the cells that are kept (:meth:`DDMAEnvelope.tx0_doppler`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

import radarpc.dsp.accel as accel
from radarpc.dsp.accel.rxsum import rx_magnitude_sum_fast
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

# Bytes of A per block of the envelope on CPU (a block's slot sums G_s stay in cache).
_ENVELOPE_BLOCK_BYTES = 1 << 21


def check_rd(rd: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """Validate an RD cube (batch) against ``cfg`` and return it as ``(B, Nr, Nd, Nrx)``.

    Raises
    ------
    ValueError
        Not a complex tensor, a shape other than ``(Nr, Nd, Nrx)`` / ``(B, Nr, Nd, Nrx)`` of the
        sensor, or an empty batch (``B = 0``). (NaN is detected later, on the envelope, where it
        costs nothing.)
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
    if rd.ndim == 4 and rd.shape[0] == 0:
        raise ValueError(f"rd is an empty batch (shape {tuple(rd.shape)}): give at least one frame")
    return rd if rd.ndim == 4 else rd.unsqueeze(0)


def rx_magnitude_sum(rd: torch.Tensor) -> torch.Tensor:
    """``A = sum_rx |rd|`` over the last axis: ``(..., Nr, Nd, Nrx)`` complex -> ``(..., Nr, Nd)`` real.

    Magnitude, not power, as in RADIal's processing: ``|z| = sqrt(re^2 + im^2)`` (the formula,
    not ``hypot``: NaN and inf propagate as it says, squares beyond float32 overflow to inf).
    On CPU, when :func:`radarpc.dsp.accel.enabled`, the cube goes to
    :func:`radarpc.dsp.accel.rxsum.rx_magnitude_sum_fast` (the C kernel, ~3x faster, or this
    formula in cache-sized blocks): the same ``|z|``, the receiver sum rounded in another order.
    """
    if accel.enabled() and rd.device.type == "cpu":
        return rx_magnitude_sum_fast(rd)
    re_im = torch.view_as_real(rd.resolve_conj()).square()      # (..., Nd, Nrx, 2)
    return torch.add(re_im[..., 0], re_im[..., 1]).sqrt_().sum(-1)


def consolidate(a: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """Sum the Doppler axis over the DDMA slots: ``(..., Nr, Nd) -> (..., Nr, slot_width)``."""
    shape = a.shape[:-1] + (cfg.n_slots, cfg.slot_width)
    return a.reshape(shape).sum(-2)


def check_envelope_kind(envelope: str) -> str:
    """Validate an envelope kind (one of :data:`ENVELOPES`)."""
    if envelope not in ENVELOPES:
        raise ValueError(f"envelope must be one of {ENVELOPES} ('replicas' = the paper's eq. 1, sum over the "
                         f"n_tx replica bins; 'all-slots' = RADIal rpl.py, sum over every slot), got {envelope!r}")
    return envelope


def _sequential_sum(terms: list[torch.Tensor], out: torch.Tensor) -> torch.Tensor:
    """``out = ((t_0 + t_1) + t_2) + ...``: the terms added one by one, in this order."""
    if len(terms) == 1:
        return out.copy_(terms[0])
    torch.add(terms[0], terms[1], out=out)
    for t in terms[2:]:
        out += t
    return out


def gap_window_sums(x: torch.Tensor, n_gap: int, dim: int = -1, *, out: torch.Tensor | None = None) -> torch.Tensor:
    """``G_s = x_{s+1} + ... + x_{s+n_gap}`` (indices mod ``n_slots``) along the slot axis ``dim``.

    The sums of the circular windows of ``n_gap`` consecutive slots *after* slot ``s``; the gap
    follows Tx 0, so ``argmin_s G_s`` is Tx 0's slot. The terms are added one by one in the
    order ``k = 1, ..., n_gap`` for every window, so the whole-map envelope and the per-peak
    search (both use this function) resolve the same slot bit for bit. The windows that do not
    wrap read ``x`` in place; only the ``2 n_gap - 1`` slots around the wrap are copied.
    ``out`` (shaped like ``x``) receives the sums if given.

    Raises
    ------
    ValueError
        ``n_gap`` not in ``[1, n_slots)``.
    """
    n = x.shape[dim]
    if isinstance(n_gap, bool) or not isinstance(n_gap, int) or not 1 <= n_gap < n:
        raise ValueError(f"n_gap must be an int in [1, {n}) (empty slots of {n} slots), got {n_gap!r}")
    out = torch.empty_like(x) if out is None else out
    n_in = n - n_gap                                                       # windows s < n_in do not wrap
    _sequential_sum([x.narrow(dim, k, n_in) for k in range(1, n_gap + 1)], out.narrow(dim, 0, n_in))
    # windows s = n_in + j read slots n_in + 1, ..., n - 1, 0, ..., n_gap - 1: tail[j + k - 1]
    tail = torch.cat([x.narrow(dim, n_in + 1, n_gap - 1), x.narrow(dim, 0, n_gap)], dim=dim)
    _sequential_sum([tail.narrow(dim, k, n_gap) for k in range(n_gap)], out.narrow(dim, n_in, n_gap))
    return out


def _slot_min(g: torch.Tensor) -> torch.Tensor:
    """``min_s g[..., s, :]`` by pairwise ``torch.minimum`` of halves (exact: a minimum does not
    round; NaN propagates): ``(..., n, W) -> (..., W)``. Much faster than a strided reduction."""
    while g.shape[-2] > 1:
        n = g.shape[-2]
        h = n // 2
        g = torch.minimum(g.narrow(-2, 0, n - h), g.narrow(-2, h, n - h))  # odd n: slot h taken twice
    return g.squeeze(-2)


@dataclass
class DDMAEnvelope:
    """Consolidated maps of a batch of cubes.

    Attributes
    ----------
    mag_sum : Tensor ``(B, Nr, Nd)``           ``A = sum_rx |R|``
    all_slots : Tensor ``(B, Nr, W)``          ``E_all``: sum over every slot (RADIal rpl.py)
    replicas : Tensor ``(B, Nr, W)``           ``E``: sum over the ``n_tx`` replica bins (seed eq. 1)
    gap_sums : Tensor ``(B, Nr, n_slots, W)``  ``G_s`` (:func:`gap_window_sums`) of every cell
    tx0_slot : LongTensor ``(B, Nr, W)``       slot ``argmin_s G_s`` (first on ties) of the Tx-0
        replica of every cell; a property, computed from ``gap_sums`` on first use
    """

    mag_sum: torch.Tensor
    all_slots: torch.Tensor
    replicas: torch.Tensor
    gap_sums: torch.Tensor
    _tx0_slot: torch.Tensor | None = field(default=None, init=False, repr=False)

    def envelope(self, kind: str) -> torch.Tensor:
        """``replicas`` or ``all_slots`` by kind (:data:`ENVELOPES`)."""
        return self.replicas if check_envelope_kind(kind) == "replicas" else self.all_slots

    @property
    def tx0_slot(self) -> torch.Tensor:
        """``argmin_s G_s`` of every cell ``(B, Nr, W)`` (first on ties), computed once."""
        if self._tx0_slot is None:
            self._tx0_slot = torch.min(self.gap_sums, dim=-2).indices
        return self._tx0_slot

    def tx0_doppler(self, batch_idx: torch.Tensor, range_idx: torch.Tensor,
                    cons_idx: torch.Tensor) -> torch.Tensor:
        """Full Doppler bin ``d0 = s0 W + l`` of the Tx-0 replica of cells ``(b, r, l)``: ``(P,)`` long.

        ``s0 = argmin_s G_s(b, r, l)`` (first on ties). For a few cells (at most half the map)
        the ``n_slots`` sums of each cell are gathered and searched; for more, the whole map
        :attr:`tx0_slot` is computed once and indexed. Both give the same slots.
        """
        _, n_range, n_slots, w = self.gap_sums.shape
        l = cons_idx.long()
        if 2 * l.numel() > self.all_slots.numel() or self._tx0_slot is not None:
            slot = self.tx0_slot[batch_idx, range_idx, cons_idx]
        else:
            row = torch.add(range_idx.long(), batch_idx.long(), alpha=n_range)     # b Nr + r, (P,)
            first = torch.add(l, row, alpha=n_slots * w)                          # flat index of G_0(b, r, l)
            cols = first.unsqueeze(-1) + torch.arange(0, n_slots * w, w, device=l.device)  # (P, n_slots)
            slot = torch.min(self.gap_sums.take(cols), dim=1).indices
        return torch.add(l, slot, alpha=w)


def ddma_envelope(a: torch.Tensor, cfg: DDMARadarConfig) -> DDMAEnvelope:
    """Both envelopes and the gap sums of every consolidated cell from ``A`` ``(B, Nr, Nd)``.

    ``x_s = A(r, s W + l)``, ``G_s`` = :func:`gap_window_sums`, ``E_all = sum_s x_s`` and
    ``E = E_all - min_s G_s``: the sum over the ``n_tx`` slots ``s0 + tx_slots`` with
    ``s0 = argmin_s G_s`` (first on ties, as :func:`resolve_tx0_doppler`), i.e. the replica bins
    ``T(r, l)``. The slots ``s0`` themselves are looked up on demand
    (:meth:`DDMAEnvelope.tx0_doppler`, :attr:`DDMAEnvelope.tx0_slot`). On CPU the rows are
    processed in blocks of about 2 MB of ``A`` (a block's ``x`` and ``G`` stay in cache).
    """
    w = cfg.slot_width
    x = a.reshape(-1, cfg.n_slots, w)                                       # (B Nr, n_slots, W) rows
    rows = x.shape[0]
    e_all = x.new_empty(rows, w)                                            # (B Nr, W)
    e = x.new_empty(rows, w)
    g = torch.empty_like(x)                                                 # (B Nr, n_slots, W)
    step = rows
    if a.device.type == "cpu":
        step = max(1, _ENVELOPE_BLOCK_BYTES // (cfg.n_doppler * x.element_size()))
    for i in range(0, rows, step):
        xi, gi, ei = x[i:i + step], g[i:i + step], e_all[i:i + step]
        torch.sum(xi, dim=-2, out=ei)                                       # E_all
        gap_window_sums(xi, cfg.n_empty_slots, dim=-2, out=gi)              # G_s
        torch.sub(ei, _slot_min(gi), out=e[i:i + step])                     # E = E_all - min_s G_s
    lead = a.shape[:-1]
    return DDMAEnvelope(mag_sum=a, all_slots=e_all.reshape(lead + (w,)),
                        replicas=e.clamp_min_(0.0).reshape(lead + (w,)),
                        gap_sums=g.reshape(lead + (cfg.n_slots, w)))


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
    lo, hi = torch.aminmax(e.flatten(1), dim=1)                    # NaN propagates into both
    bad = ~(torch.isfinite(lo) & torch.isfinite(hi))               # (B,)
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
    """The ``M = n_tx`` full-Doppler bins ``(d0 + doppler_offsets) mod N_D`` in Tx order: ``(P, n_tx)`` long.

    Row ``d0 mod N_D`` of the table ``(d + doppler_offsets) mod N_D``, ``d = 0..N_D-1``, is
    gathered (a modulo per peak instead of one per peak and Tx).
    """
    off = torch.as_tensor(cfg.doppler_offsets, device=d0.device)
    d = torch.arange(cfg.n_doppler, device=d0.device)
    table = (d.unsqueeze(-1) + off).remainder_(cfg.n_doppler)      # (N_D, n_tx)
    return table.index_select(0, d0.long().remainder(cfg.n_doppler))


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
    if rd.is_contiguous():                                         # row gather: fast on CPU and GPU
        row = torch.add(range_idx.long(), batch_idx.long(), alpha=cfg.n_range)           # (P,) b Nr + r
        flat = torch.add(bins, row.unsqueeze(-1), alpha=cfg.n_doppler).reshape(-1)      # (P * n_tx,)
        v = rd.view(-1, rd.shape[-1]).index_select(0, flat)        # (P * n_tx, n_rx)
    else:
        v = rd[batch_idx.long().unsqueeze(-1), range_idx.long().unsqueeze(-1), bins]  # (P, n_tx, n_rx)
    return v.reshape(-1, cfg.n_virtual)
