"""Data density of a peak set and the CFAR threshold that reaches a target density.

The seed's density (eq. 3) is ``|S(tau)| / (N_r * N_D)`` with ``S(tau)`` the detected cells on the
full RD grid. Every consolidated peak ``(r, l)`` maps to ``M = n_tx`` distinct full-grid cells and
distinct peaks never share one, so ``|S(tau)| = n_tx * |P(tau)|``. The largest reachable density
is therefore ``n_tx / n_slots`` (every consolidated cell detected): 0.75 for RADIal.

The density of a point cloud is the data budget it *encodes*. With the RD-neighbourhood enrichment
``rdN`` (eqs. 8-9) that is ``S*(tau)``, the ``n_tx`` replicas of

    P*(tau) = U_{(r, l) in P(tau)} N_n(r, l),    N_n truncated at the envelope borders,

so the controller then picks tau for ``|S*(tau)| / (N_r N_D)`` (seed Table 2 compares SpectralPillars
and PointPillars at matched densities). Because the square neighbourhood is symmetric, a cell lies
in ``P*(tau)`` iff some cell of its own (truncated) neighbourhood passes the test:

    P*(tau) = {(r, l) : D(r, l) > tau},    D(r, l) = max_{(r', l') in N_n(r, l)} SNR(r', l'),

i.e. ``P*(tau)`` is a plain threshold of the max-filtered SNR map ``D`` (:func:`neighbourhood_snr`).
``|P*(tau)| = #{D > tau}`` is a non-increasing step function of tau, and the controller finds its
threshold exactly from the order statistics of ``D`` (no bisection tolerance).
"""
from __future__ import annotations

import torch

from radarpc.sensors.radial import DDMARadarConfig

__all__ = ["DENSITY_MODES", "density_of_mask", "max_density", "check_density_value", "check_density", "check_neighbourhood",
           "neighbourhood_mask", "neighbourhood_snr", "tau_for_density"]

DENSITY_MODES = ("per-frame", "per-dataset")


def max_density(cfg: DDMARadarConfig) -> float:
    """Density when every consolidated cell is a peak: ``n_tx / n_slots``."""
    return cfg.n_tx / cfg.n_slots


def check_density_value(target: float) -> float:
    """Validate a target density without a sensor: a number in ``(0, 1]``; returns it as float."""
    if isinstance(target, bool) or not isinstance(target, (int, float)):
        raise ValueError(f"density must be a number in (0, 1], got {target!r}")
    t = float(target)
    if not 0.0 < t <= 1.0:   # NaN fails too
        raise ValueError(f"density must be in (0, 1] (fraction of RD cells kept), got {target}")
    return t


def check_density(target: float, cfg: DDMARadarConfig) -> float:
    """Validate a target density: in ``(0, 1]`` and reachable by ``cfg`` (``<= n_tx / n_slots``)."""
    t = check_density_value(target)
    if t > max_density(cfg) + 1e-12:
        raise ValueError(f"density {target} is unreachable for sensor {cfg.name!r}: at most "
                         f"n_tx / n_slots = {max_density(cfg):.4f} (every consolidated cell detected)")
    return t


def check_neighbourhood(n: int) -> int:
    """Validate the side ``n`` of the RD neighbourhood (eq. 8): an odd integer ``>= 3``."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 3 or n % 2 == 0:
        raise ValueError(f"the RD neighbourhood size n must be an odd integer >= 3, got {n!r}")
    return n


def _check_maps(x: torch.Tensor, what: str) -> None:
    if x.ndim != 3:
        raise ValueError(f"{what} must be (B, Nr, W), got {tuple(x.shape)}")


def neighbourhood_snr(snr: torch.Tensor, n: int) -> torch.Tensor:
    """``D(r, l) = max`` of ``snr`` over the ``n x n`` neighbourhood of ``(r, l)``, truncated at
    the borders (eq. 8), so that ``P*(tau) = {D > tau}`` (eq. 9).

    Parameters
    ----------
    snr : Tensor, real, ``(B, Nr, W)``
        CFAR SNR of the consolidated envelope.
    n : int
        Odd neighbourhood side ``>= 3``.

    Returns
    -------
    Tensor, ``(B, Nr, W)``, ``snr``'s dtype and device
    """
    check_neighbourhood(n)
    _check_maps(snr, "snr")
    if not snr.is_floating_point():
        raise ValueError(f"snr must be a real floating-point SNR map, got {snr.dtype}")
    return _box_max(snr, n // 2)


def _box_max(x: torch.Tensor, h: int) -> torch.Tensor:
    """Max of ``x`` over the ``(2h + 1) x (2h + 1)`` box around every cell of the last two axes,
    truncated at the borders (cells outside the grid never win), NaN propagating.

    Separable: the max over the Doppler offsets, then over the range offsets, each as ``2h``
    shifted ``torch.maximum`` into the overlapping slice. Exact (a maximum does not round) and the
    same values as ``max_pool2d`` with ``-inf`` padding, several times faster on these thin maps.
    """
    out = x
    for axis in (-1, -2):
        src = out
        out = src.clone()
        n = src.shape[axis]
        for d in range(1, min(h, n - 1) + 1):
            head, tail = out.narrow(axis, 0, n - d), out.narrow(axis, d, n - d)
            torch.maximum(tail, src.narrow(axis, 0, n - d), out=tail)    # neighbour at offset -d
            torch.maximum(head, src.narrow(axis, d, n - d), out=head)    # neighbour at offset +d
    return out


def neighbourhood_mask(peaks: torch.Tensor, n: int) -> torch.Tensor:
    """``P*`` (eq. 9): union of the ``n x n`` neighbourhoods (truncated at the borders) of ``peaks``.

    Parameters
    ----------
    peaks : BoolTensor ``(B, Nr, W)``
        Consolidated peak set ``P(tau)``.
    n : int
        Odd neighbourhood side ``>= 3``.

    Returns
    -------
    BoolTensor ``(B, Nr, W)``
    """
    check_neighbourhood(n)
    _check_maps(peaks, "peaks")
    if peaks.dtype != torch.bool:
        raise ValueError(f"peaks must be a bool mask, got {peaks.dtype}")
    # dilation = box max of the 0/1 bytes (the same bytes viewed back as bool)
    return _box_max(peaks.view(torch.uint8), n // 2).view(torch.bool)


def density_of_mask(mask: torch.Tensor, cfg: DDMARadarConfig) -> torch.Tensor:
    """Density ``|S| / (N_r N_D)`` of each frame of a detection mask.

    Parameters
    ----------
    mask : BoolTensor, ``(..., Nr, slot_width)`` consolidated ``P`` (then ``|S| = n_tx |P|``) or
        ``(..., Nr, Nd)`` full-grid ``S``.
    cfg : DDMARadarConfig

    Returns
    -------
    Tensor, float32, ``mask.shape[:-2]``
    """
    if mask.ndim < 2 or mask.shape[-2] != cfg.n_range or mask.shape[-1] not in (cfg.slot_width, cfg.n_doppler):
        raise ValueError(f"mask must be (..., {cfg.n_range}, {cfg.slot_width}) consolidated or "
                         f"(..., {cfg.n_range}, {cfg.n_doppler}) full-grid, got {tuple(mask.shape)}")
    count = mask.flatten(-2).sum(-1).to(torch.float64)
    if mask.shape[-1] == cfg.slot_width:
        count = count * cfg.n_tx
    return (count / (cfg.n_range * cfg.n_doppler)).to(torch.float32)


def _midpoint_threshold(values_desc: torch.Tensor, n: int) -> torch.Tensor:
    """tau such that exactly the ``n`` largest values exceed it (up to ties), from the ``n + 1``
    largest values sorted descending along the last axis."""
    hi = values_desc[..., n - 1] if n > 0 else None
    lo = values_desc[..., n]
    if hi is None:
        return lo.clone()
    tau = 0.5 * (hi + lo)
    # a tie (hi == lo) or a midpoint rounded onto hi would drop the n-th value: keep tau = lo then
    return torch.where(tau < hi, tau, lo)


def _below(smallest: torch.Tensor) -> torch.Tensor:
    """A threshold every cell passes: half the smallest SNR, or -1 when that is 0."""
    return torch.where(smallest > 0, 0.5 * smallest, torch.full_like(smallest, -1.0))


def _between(hi: torch.Tensor, lo: torch.Tensor) -> torch.Tensor:
    """A threshold in ``[lo, hi)`` for ``hi > lo``: the midpoint, or ``lo`` when rounding puts the
    midpoint on ``hi`` (``{x > tau}`` then keeps every value ``>= hi`` and none ``<= lo``)."""
    tau = 0.5 * hi + 0.5 * lo                                   # no overflow for huge SNRs
    return torch.where(tau < hi, tau, lo)


def _count_threshold(values: torch.Tensor, n: int) -> torch.Tensor:
    """Per row of ``values`` ``(G, N)``, the tau that exactly the ``n`` largest values exceed (fewer
    on ties): the midpoint of the ``n``-th and ``(n + 1)``-th largest (:func:`_midpoint_threshold`),
    read as the two smallest of the ``n + 1`` largest (one partial selection, no sort)."""
    if n >= values.shape[1]:
        return _below(values.amin(dim=1))                                     # every value passes
    if n == 0:
        return values.amax(dim=1)                                             # nothing exceeds the max
    top = torch.topk(values, n + 1, dim=1, sorted=False).values              # the n + 1 largest, (G, n + 1)
    lo_hi = torch.topk(top, 2, dim=1, largest=False, sorted=True).values     # (n+1)-th and n-th largest
    return _midpoint_threshold(lo_hi.flip(1), 1)


def _closest_count_threshold(values: torch.Tensor, m: int) -> torch.Tensor:
    """Per row of ``values`` ``(G, N)``, a tau whose count ``#{values > tau}`` is the reachable
    count closest to ``m`` (a tie between two reachable counts goes to the smaller one).

    The reachable counts are ``0`` and ``#{values >= v}`` for every value ``v``: ties (equal values)
    make the count jump. With ``v`` the ``m``-th largest value, the two candidates around ``m`` are
    ``c_lo = #{values > v} < m`` (tau in ``[v, next larger value)``) and ``c_hi = #{values >= v} >= m``
    (tau in ``[next smaller value, v)``); ``c_hi == m`` when ``v`` is not tied.
    """
    g, total = values.shape
    if m <= 0:
        return values.amax(dim=1)                                             # nothing exceeds the max
    if m >= total:
        return _below(values.amin(dim=1))
    top = torch.topk(values, m, dim=1, sorted=False).values                  # the m largest, (G, m)
    v = top.amin(dim=1)                                                       # m-th largest, (G,)
    vv = v[:, None]
    # every value > v is among the m largest: c_lo and the next larger value come from top alone
    gt = top > vv                                                             # (G, m)
    c_lo = gt.sum(1)                                                          # (G,)
    above = top.masked_fill(~gt, float("inf")).amin(dim=1)                   # next larger value (inf: none)
    ge = values >= vv                                                         # (G, N)
    c_hi = ge.sum(1)
    below = values.masked_fill(ge, float("-inf")).amax(dim=1)                 # next smaller value (-inf: none)
    tau_lo = torch.where(torch.isinf(above), v, _between(above, v))           # keeps c_lo cells
    tau_hi = torch.where(torch.isinf(below), _below(v), _between(v, below))   # keeps c_hi cells
    return torch.where((c_hi - m) < (m - c_lo), tau_hi, tau_lo)


def tau_for_density(snr_batch: torch.Tensor, cfg: DDMARadarConfig, target: float, *,
                    mode: str = "per-frame", neighbourhood: int | None = None) -> torch.Tensor:
    """The linear SNR threshold(s) ``tau`` whose encoded set has the target density.

    Without ``neighbourhood`` the encoded set is ``S(tau)`` (peaks ``{snr > tau}``): the number of
    consolidated peaks is ``m = round(target * N_r N_D / n_tx)`` per frame and ``tau`` is the
    midpoint between the ``m``-th and ``(m + 1)``-th largest SNR, so exactly ``m`` cells pass (fewer
    only when SNR values tie at the boundary).

    With ``neighbourhood = n`` the encoded set is ``S*(tau)`` (eq. 9, the ``n x n`` RD-neighbourhood
    enrichment): ``|P*(tau)| = #{D > tau}`` with ``D`` the max-filtered SNR
    (:func:`neighbourhood_snr`), and tau is chosen *exactly* over all thresholds: the returned tau
    realises the reachable ``|P*|`` closest to ``m`` (a tie between two goes to the smaller set).
    ``|P*|`` can only take the values ``#{D >= v}``: one more peak adds its whole neighbourhood,
    up to ``n^2`` cells at once, so the achieved density may differ from the target by up to half
    such a step (per frame, full RADIal, rd3: ``<= 4.5 * 12 / 131072 = 4e-4``); when two frames'
    cells share exactly the same SNR the step can be larger. The achieved density is what
    :class:`~radarpc.dsp.pointcloud.PointCloudBatch` reports. A target above ``n_tx / n_slots``
    raises ``ValueError`` in both cases.

    Parameters
    ----------
    snr_batch : Tensor, ``(B, Nr, slot_width)``
        CFAR SNR of the consolidated envelope of each frame.
    cfg : DDMARadarConfig
    target : float
        Target density in ``(0, n_tx / n_slots]``.
    mode : {"per-frame", "per-dataset"}
        ``per-frame``: one tau per frame, each frame hits the target. ``per-dataset``: one tau for
        all the given frames (pooled SNRs), so that their *mean* density hits the target; call it
        on the SNRs of the training split and reuse the tau on every split.
    neighbourhood : int, optional
        Odd ``n >= 3`` of an active ``rdN`` enrichment: target ``|S*(tau)|`` instead of ``|S(tau)|``.

    Returns
    -------
    Tensor
        ``(B,)`` for ``per-frame``, a 0-d tensor for ``per-dataset``; ``snr_batch``'s dtype and device.
    """
    target = check_density(target, cfg)
    if mode not in DENSITY_MODES:
        raise ValueError(f"density mode must be one of {DENSITY_MODES}, got {mode!r}")
    if neighbourhood is not None:
        check_neighbourhood(neighbourhood)
    if snr_batch.ndim == 2:
        snr_batch = snr_batch.unsqueeze(0)
    if snr_batch.ndim != 3 or tuple(snr_batch.shape[1:]) != (cfg.n_range, cfg.slot_width):
        raise ValueError(f"snr_batch must be (B, {cfg.n_range}, {cfg.slot_width}), got {tuple(snr_batch.shape)}")
    if snr_batch.is_complex() or bool(torch.isnan(snr_batch.amax())):   # amax propagates NaN
        raise ValueError("snr_batch must be real without NaN")
    cells = cfg.n_range * cfg.slot_width
    n = int(round(target * cfg.n_range * cfg.n_doppler / cfg.n_tx))
    n = min(max(n, 0), cells)
    if neighbourhood is not None:                              # S*(tau): threshold D = max-filtered SNR
        d = neighbourhood_snr(snr_batch, neighbourhood)        # (B, Nr, W)
        if mode == "per-frame":
            return _closest_count_threshold(d.flatten(1), n)   # (B,)
        m = int(round(target * snr_batch.shape[0] * cfg.n_range * cfg.n_doppler / cfg.n_tx))
        return _closest_count_threshold(d.reshape(1, -1), m)[0]
    if mode == "per-frame":
        return _count_threshold(snr_batch.flatten(1), n)                    # (B,)
    m = int(round(target * snr_batch.shape[0] * cfg.n_range * cfg.n_doppler / cfg.n_tx))
    return _count_threshold(snr_batch.reshape(1, -1), max(m, 0))[0]
