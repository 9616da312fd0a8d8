"""Exact ADC-domain synthesis of a DDMA FMCW frame from first principles, and its RD FFT.

The independent reference against which :func:`radarpc.sim.rd.synthesize_rd` is tested (on the
tiny config). Nothing here is read from the fast model: the array phase comes from the element
delays of the geometry (not from :func:`radarpc.sensors.radial.steering_vectors`), the DDMA code
from the Tx slots (not from ``cfg.doppler_offsets``), and every chirp has its own delay.

Signal model
------------
Transmitted chirp ``s(t) = exp(j 2 pi (f_c t + S t^2 / 2))`` (slope ``S``), received echo
``s(t - tau)``. The IF convention is the mixer output ``IF = tx * conj(rx)``:

.. math::

    \\mathrm{IF}(t) = \\exp\\big(j 2 \\pi (f_c \\tau + S \\tau t - S \\tau^2 / 2)\\big)

so a longer delay is a positive beat frequency ``S tau`` (positive range bins) and a receding
target a positive Doppler frequency. The residual video phase ``-S tau^2 / 2`` is removed (the
usual RVP correction; the fast model has none either).

Delay of chirp ``k`` (period ``T_c``), Tx ``m``, Rx ``r`` for a point scatterer at range
``R``, radial velocity ``v`` (receding positive) and direction ``u = (cos e cos a, cos e sin a,
sin e)``; element positions ``p`` in half wavelengths in the (y, z) array plane, so the element
sits at ``(0, p_h lambda/2, p_v lambda/2)`` metres and a plane wave from ``u`` reaches it earlier
by ``p . (u_y, u_z) lambda / 2 / c``:

.. math::

    \\tau_{k,m,r} = \\frac{2 (R + v k T_c) - (p_{tx,m} + p_{rx,r}) \\cdot u \\, \\lambda / 2}{c}

(stop-and-hop: the target does not move during one chirp). The ADC sample ``n`` (``t_n = n /
f_s``) of chirp ``k`` at Rx ``r`` is the sum over scatterers and active Tx:

.. math::

    x[k, n, r] = \\sum_s A_s \\sum_m g_{m,r}\\, c_m[k]\\, \\mathrm{IF}_{k,m,r}(t_n),\\qquad
    c_m[k] = \\exp(j 2 \\pi\\, \\mathrm{slot}_m\\, w\\, k / N_d)

with ``w`` the slot width in Doppler bins, ``g`` the unit's hardware errors
(:func:`radarpc.sensors.radial.channel_errors`, a property of the unit) and ``A_s = sqrt(SNR_s *
sigma_adc^2)`` from the radar equation (:meth:`DDMARadarConfig.snr_per_sample`).

Under this convention the array term of the carrier phase is ``-pi p . u``: the phase decreases
towards the elements nearer the target. :func:`radarpc.sensors.radial.steering_vectors` uses the
same sign, so that a target on the left (+y, positive azimuth) beamforms to positive azimuth.

What the fast frequency-domain model leaves out, both inside ``S tau t``:

* the array delay in the beat frequency (the narrowband approximation): a range offset of at most
  ``max|p . u| lambda / (4 range_res)`` bins (:func:`narrowband_bins`);
* range migration over the frame: ``v N_d T_c / range_res`` bins (:func:`migration_bins`).

``narrowband=True`` drops exactly these two (the beat frequency uses ``2 R / c``), which the fast
model must then match to float32 precision.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from radarpc.sensors.radial import SPEED_OF_LIGHT, DDMARadarConfig, channel_errors
from radarpc.sim.rd import Scatterers, adc_noise_power, window

__all__ = ["synthesize_ddma_adc", "rd_from_adc", "synthesize_rd_exact", "narrowband_bins", "migration_bins"]


def narrowband_bins(cfg: DDMARadarConfig, az_deg: float, el_deg: float) -> float:
    """Largest range offset (bins) of the array delay, ``max_v |p_v . u| lambda / (4 range_res)``."""
    a, e = math.radians(float(az_deg)), math.radians(float(el_deg))
    u = np.array([math.cos(e) * math.sin(a), math.sin(e)])                # (u_y, u_z)
    tx = np.asarray(cfg.tx_pos, dtype=np.float64)
    rx = np.asarray(cfg.rx_pos, dtype=np.float64)
    proj = np.abs((tx[:, None, :] + rx[None, :, :]) @ u).max()
    return float(proj * cfg.wavelength_m / (4.0 * cfg.range_res_m))


def migration_bins(cfg: DDMARadarConfig, velocity_mps: float) -> float:
    """Range bins a target of radial velocity ``v`` moves over one frame: ``|v| N_d T_c / range_res``."""
    return abs(float(velocity_mps)) * cfg.n_doppler * cfg.chirp_period_s / cfg.range_res_m


def synthesize_ddma_adc(cfg: DDMARadarConfig, scatterers: Scatterers, *, noise: bool = False,
                   generator: torch.Generator | None = None, narrowband: bool = False) -> torch.Tensor:
    """ADC samples of one frame, summed over Tx (what the Rx antennas receive).

    Parameters
    ----------
    cfg : DDMARadarConfig
    scatterers : Scatterers
    noise : bool
        Add complex Gaussian noise of power ``sigma_adc^2`` per sample.
    generator : torch.Generator, optional
        CPU generator for the noise.
    narrowband : bool
        Beat frequency from ``2 R / c`` only (no array delay, no range migration in ``S tau t``);
        the carrier phase keeps the full per-chirp, per-element delay.

    Returns
    -------
    Tensor
        complex128 ``(n_chirps = n_doppler, n_samples = n_range, n_rx)`` on the CPU.
    """
    if not isinstance(scatterers, Scatterers):
        raise ValueError(f"synthesize_ddma_adc expects Scatterers, got {type(scatterers).__name__}")
    nk, nn, ntx, nrx = cfg.n_doppler, cfg.n_range, cfg.n_tx, cfg.n_rx
    c, lam, fc, slope = SPEED_OF_LIGHT, cfg.wavelength_m, cfg.carrier_hz, cfg.chirp_slope_hz_per_s
    rng = scatterers.range_m.detach().cpu().double().numpy()
    vel = scatterers.velocity_mps.detach().cpu().double().numpy()
    rcs = scatterers.rcs_m2.detach().cpu().double().numpy()
    az = np.deg2rad(scatterers.azimuth_deg.detach().cpu().double().numpy())
    el = np.deg2rad(scatterers.elevation_deg.detach().cpu().double().numpy())

    t_n = np.arange(nn) / cfg.sample_rate_hz                              # (n,) fast time, s
    k = np.arange(nk, dtype=np.float64)                                   # (k,) chirp index
    width = nk // cfg.n_slots                                             # Doppler bins per slot
    slots = np.asarray(cfg.tx_slots, dtype=np.float64)                    # (m,)
    code = np.exp(2j * np.pi * np.outer(k, slots * width) / nk)           # (k, m) DDMA phase code
    p_tx = np.asarray(cfg.tx_pos, dtype=np.float64)                       # (m, 2) half wavelengths
    p_rx = np.asarray(cfg.rx_pos, dtype=np.float64)                       # (r, 2)
    p = p_tx[:, None, :] + p_rx[None, :, :]                               # (m, r, 2)
    g = channel_errors(cfg).reshape(ntx, nrx)                             # (m, r) hardware
    amp = np.sqrt(cfg.snr_per_sample(rng, rcs) * adc_noise_power(cfg))    # (S,)
    x = np.zeros((nk, nn, nrx), dtype=np.complex128)
    for s in range(len(rng)):
        u = np.array([np.cos(el[s]) * np.sin(az[s]), np.sin(el[s])])      # (u_y, u_z)
        path_k = 2.0 * (rng[s] + vel[s] * k * cfg.chirp_period_s)         # (k,) two-way path, m
        array_m = (p @ u) * lam / 2.0                                     # (m, r) path shortening, m
        tau = (path_k[:, None, None] - array_m[None]) / c                 # (k, m, r)
        # carrier phase f_c tau in cycles, reduced modulo one in float64 term by term
        cyc = (np.mod(fc * path_k / c, 1.0)[:, None, None] - np.mod(fc * array_m / c, 1.0)[None])
        carrier = np.exp(2j * np.pi * cyc)                                # (k, m, r)
        tau_b = np.full_like(tau, 2.0 * rng[s] / c) if narrowband else tau
        beat = np.exp(2j * np.pi * slope * tau_b[:, None] * t_n[None, :, None, None])   # (k, n, m, r)
        coef = amp[s] * g[None] * code[:, :, None] * carrier              # (k, m, r)
        x += np.einsum("knmr,kmr->knr", beat, coef)
    out = torch.from_numpy(x)
    if noise:
        z = torch.randn((nk, nn, nrx, 2), dtype=torch.float64, generator=generator)
        out = out + torch.view_as_complex(z) * math.sqrt(adc_noise_power(cfg) / 2.0)
    return out


def rd_from_adc(cfg: DDMARadarConfig, adc: torch.Tensor) -> torch.Tensor:
    """Windowed range FFT then windowed Doppler FFT (unnormalised, no fftshift).

    Parameters
    ----------
    adc : Tensor
        complex ``(n_doppler, n_range, n_rx)`` (chirp, sample, Rx).

    Returns
    -------
    Tensor
        complex ``(n_range, n_doppler, n_rx)``: range bin ``i`` is ``i * range_res_m``, Doppler
        bin ``d`` holds velocity ``cfg.velocity_of_bin(d)``.
    """
    want = (cfg.n_doppler, cfg.n_range, cfg.n_rx)
    if not isinstance(adc, torch.Tensor) or not adc.is_complex():
        raise ValueError("rd_from_adc expects a complex torch tensor of ADC samples")
    if tuple(adc.shape) != want:
        raise ValueError(f"ADC cube must be (n_doppler, n_range, n_rx) = {want}, got {tuple(adc.shape)}")
    real = torch.float64 if adc.dtype == torch.complex128 else torch.float32
    w_r = window(cfg.n_range, device=adc.device, dtype=real)
    w_d = window(cfg.n_doppler, device=adc.device, dtype=real)
    x = torch.fft.fft(adc * w_r[None, :, None], dim=1)                 # range FFT over fast time
    x = torch.fft.fft(x * w_d[:, None, None], dim=0)                   # Doppler FFT over chirps
    return x.permute(1, 0, 2).contiguous()


def synthesize_rd_exact(cfg: DDMARadarConfig, scatterers: Scatterers, *,
                        narrowband: bool = False) -> torch.Tensor:
    """Noise-free RD cube by the exact ADC route: ``rd_from_adc(cfg, synthesize_ddma_adc(cfg, s))``.

    complex128 ``(n_range, n_doppler, n_rx)``; cost ``O(S * n_doppler * n_range * n_virtual)``,
    meant for small configs.
    """
    return rd_from_adc(cfg, synthesize_ddma_adc(cfg, scatterers, narrowband=narrowband))
