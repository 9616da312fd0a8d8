"""Exact ADC-domain synthesis of a DDMA FMCW frame, and its range/Doppler FFT.

The reference against which :func:`radarpc.sim.rd.synthesize_rd` is tested (on the tiny config).
For every chirp ``k`` (period ``T_c``), fast-time sample ``n`` (``t_n = n / f_s``), Tx ``m`` and
Rx ``rx``, a point scatterer at range ``R`` with radial velocity ``v`` (receding positive) gives
the beat signal (stop-and-hop: the target is static during one chirp)

.. math::

    x[k, n, rx] = \\sum_s \\sum_m A_s\\, a_{m n_{rx} + rx}(\\theta_s)\\,
        \\exp\\big(j 2 \\pi (f_c \\tau_s + f_{b,s} t_n + f_{D,s} k T_c + o_m k / N_d)\\big)

with the two-way delay ``tau = 2 R / c``, beat frequency ``f_b = S tau`` (``S`` the chirp slope),
Doppler frequency ``f_D = 2 v / lambda``, and the DDMA phase code of Tx ``m`` advancing by
``2 pi o_m / N_d`` per chirp (``o_m = tx_slots[m] * slot_width``). The amplitude is
``A_s = sqrt(SNR_s * sigma_adc^2)`` with ``SNR_s`` from :meth:`DDMARadarConfig.snr_per_sample`
and ``sigma_adc^2`` = :func:`radarpc.sim.rd.adc_noise_power`.

:func:`rd_from_adc` applies the periodic Hamming windows and unnormalised FFTs over fast time
(range) and slow time (Doppler), the processing whose closed form ``synthesize_rd`` evaluates.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from radarpc.sensors.radial import SPEED_OF_LIGHT, DDMARadarConfig, steering_vectors
from radarpc.sim.rd import Scatterers, adc_noise_power, window

__all__ = ["synthesize_adc", "rd_from_adc", "synthesize_rd_exact"]


def synthesize_adc(cfg: DDMARadarConfig, scatterers: Scatterers, *, noise: bool = False,
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """ADC samples of one frame, summed over Tx (what the Rx antennas receive).

    Parameters
    ----------
    cfg : DDMARadarConfig
    scatterers : Scatterers
    noise : bool
        Add complex Gaussian noise of power ``sigma_adc^2`` per sample.
    generator : torch.Generator, optional
        CPU generator for the noise.

    Returns
    -------
    Tensor
        complex128 ``(n_chirps = n_doppler, n_samples = n_range, n_rx)`` on the CPU.
    """
    if not isinstance(scatterers, Scatterers):
        raise ValueError(f"synthesize_adc expects Scatterers, got {type(scatterers).__name__}")
    nk, nn, ntx, nrx = cfg.n_doppler, cfg.n_range, cfg.n_tx, cfg.n_rx
    rng = scatterers.range_m.detach().cpu().double().numpy()
    vel = scatterers.velocity_mps.detach().cpu().double().numpy()
    rcs = scatterers.rcs_m2.detach().cpu().double().numpy()
    az = scatterers.azimuth_deg.detach().cpu().double().numpy()
    el = scatterers.elevation_deg.detach().cpu().double().numpy()

    t_n = np.arange(nn) / cfg.sample_rate_hz                            # (n,) fast time, s
    k = np.arange(nk)                                                   # (k,) chirp index
    code = np.exp(2j * np.pi * np.outer(k, cfg.doppler_offsets) / nk)   # (k, m) DDMA phase code
    amp = np.sqrt(cfg.snr_per_sample(rng, rcs) * adc_noise_power(cfg))
    steer = steering_vectors(cfg, az, el).reshape(-1, ntx, nrx)         # (S, m, rx)
    x = np.zeros((nk, nn, nrx), dtype=np.complex128)
    for s in range(len(rng)):
        tau = 2.0 * rng[s] / SPEED_OF_LIGHT
        f_b = cfg.chirp_slope_hz_per_s * tau
        f_d = 2.0 * vel[s] / cfg.wavelength_m
        # carrier phase f_c * tau taken modulo one cycle in float64 before the exponential
        carrier = np.exp(2j * np.pi * math.fmod(cfg.carrier_hz * tau, 1.0))
        fast = np.exp(2j * np.pi * f_b * t_n)                           # (n,)
        slow = np.exp(2j * np.pi * f_d * k * cfg.chirp_period_s)        # (k,)
        per_chirp_rx = np.einsum("km,mr->kr", code, steer[s])           # (k, rx): sum over Tx
        x += amp[s] * carrier * slow[:, None, None] * fast[None, :, None] * per_chirp_rx[:, None, :]
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


def synthesize_rd_exact(cfg: DDMARadarConfig, scatterers: Scatterers) -> torch.Tensor:
    """Noise-free RD cube by the exact ADC route: ``rd_from_adc(cfg, synthesize_adc(cfg, s))``.

    complex128 ``(n_range, n_doppler, n_rx)``; cost ``O(S * n_doppler * n_range * n_rx)``, meant
    for small configs.
    """
    return rd_from_adc(cfg, synthesize_adc(cfg, scatterers))
