"""Data density of a peak set and the CFAR threshold that reaches a target density.

The seed's density (eq. 3) is ``|S(tau)| / (N_r * N_D)`` with ``S(tau)`` the detected cells on the
full RD grid. Every consolidated peak ``(r, l)`` maps to ``M = n_tx`` distinct full-grid cells and
distinct peaks never share one, so ``|S(tau)| = n_tx * |P(tau)|``. The largest reachable density
is therefore ``n_tx / n_slots`` (every consolidated cell detected): 0.75 for RADIal.
"""
from __future__ import annotations

import torch

from radarpc.sensors.radial import DDMARadarConfig

__all__ = ["DENSITY_MODES", "density_of_mask", "max_density", "check_density", "tau_for_density"]

DENSITY_MODES = ("per-frame", "per-dataset")


def max_density(cfg: DDMARadarConfig) -> float:
    """Density when every consolidated cell is a peak: ``n_tx / n_slots``."""
    return cfg.n_tx / cfg.n_slots


def check_density(target: float, cfg: DDMARadarConfig) -> float:
    """Validate a target density: in ``(0, 1]`` and reachable by ``cfg`` (``<= n_tx / n_slots``)."""
    if isinstance(target, bool) or not isinstance(target, (int, float)):
        raise ValueError(f"density must be a number in (0, 1], got {target!r}")
    t = float(target)
    if not 0.0 < t <= 1.0:
        raise ValueError(f"density must be in (0, 1] (fraction of RD cells kept), got {target}")
    if t > max_density(cfg) + 1e-12:
        raise ValueError(f"density {target} is unreachable for sensor {cfg.name!r}: at most "
                         f"n_tx / n_slots = {max_density(cfg):.4f} (every consolidated cell detected)")
    return t


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


def tau_for_density(snr_batch: torch.Tensor, cfg: DDMARadarConfig, target: float, *,
                    mode: str = "per-frame") -> torch.Tensor:
    """The linear SNR threshold(s) ``tau`` whose peak set ``{snr > tau}`` has the target density.

    The number of consolidated peaks is ``n = round(target * N_r N_D / n_tx)`` per frame; ``tau``
    is the midpoint between the ``n``-th and ``(n + 1)``-th largest SNR, so exactly ``n`` cells pass
    (fewer only when SNR values tie at the boundary).

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

    Returns
    -------
    Tensor
        ``(B,)`` for ``per-frame``, a 0-d tensor for ``per-dataset``; ``snr_batch``'s dtype and device.
    """
    target = check_density(target, cfg)
    if mode not in DENSITY_MODES:
        raise ValueError(f"density mode must be one of {DENSITY_MODES}, got {mode!r}")
    if snr_batch.ndim == 2:
        snr_batch = snr_batch.unsqueeze(0)
    if snr_batch.ndim != 3 or tuple(snr_batch.shape[1:]) != (cfg.n_range, cfg.slot_width):
        raise ValueError(f"snr_batch must be (B, {cfg.n_range}, {cfg.slot_width}), got {tuple(snr_batch.shape)}")
    if snr_batch.is_complex() or bool(torch.isnan(snr_batch).any()):
        raise ValueError("snr_batch must be real without NaN")
    cells = cfg.n_range * cfg.slot_width
    n = int(round(target * cfg.n_range * cfg.n_doppler / cfg.n_tx))
    n = min(max(n, 0), cells)
    if mode == "per-frame":
        flat = snr_batch.flatten(1)                                          # (B, cells)
        if n >= cells:
            return _below(flat.min(dim=1).values)
        top = torch.topk(flat, n + 1, dim=1, largest=True, sorted=True).values  # (B, n + 1)
        return _midpoint_threshold(top, n)
    flat = snr_batch.flatten()
    total = flat.numel()
    m = int(round(target * snr_batch.shape[0] * cfg.n_range * cfg.n_doppler / cfg.n_tx))
    m = min(max(m, 0), total)
    if m >= total:
        return _below(flat.min())
    # the m-th and (m+1)-th largest = the (total - m + 1)-th and (total - m)-th smallest
    lo = torch.kthvalue(flat, total - m).values
    hi = torch.kthvalue(flat, total - m + 1).values if m > 0 else None
    if hi is None:
        return lo.clone()
    return _midpoint_threshold(torch.stack([hi, lo]), 1)
