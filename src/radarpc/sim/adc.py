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

with ``w`` the slot width in Doppler bins and ``A_s = sqrt(SNR_s * sigma_adc^2)`` from the radar
equation (:meth:`DDMARadarConfig.snr_per_sample`). The hardware enters per element pair: channel
``(m, r)`` receives ``sum_{m', r'} T[m, m'] R[r, r'] IF_{k, m', r'}`` with every coupled element pair
``(m', r')`` at its own delay, ``T, R`` the coupling-and-error matrices of the unit
(:func:`radarpc.sensors.radial.array_factors`), times the element pattern evaluated from the
direction cosines, ``(u_x^2 / (u_x^2 + u_y^2))^(q_az / 2) (u_x^2 + u_y^2)^(q_el / 2)`` (= ``cos^q_az(az)
cos^q_el(el)``).

Receiver: every tone of beat frequency ``f = S tau`` is multiplied by the IF filter's gain
``|H(j 2 pi f)|``, computed here from the Butterworth poles (:func:`butterworth_gain`), not from the
closed form the fast model uses; the thermal noise is filtered in the frequency domain over fast
time and the ADC floor added after; the Tx leakage is one more tone per channel, of delay
``2 leakage_range_m / c``, static, through each Tx's DDMA code. Not modelled here: phase noise
(the fast model's skirts are tested against their closed form instead).

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

from radarpc.sensors.radial import SPEED_OF_LIGHT, DDMARadarConfig, array_factors
from radarpc.sim.rd import Scatterers, adc_noise_power, leakage_coefficients, noise_power_rd, window

__all__ = ["synthesize_ddma_adc", "rd_from_adc", "synthesize_rd_exact", "narrowband_bins", "migration_bins",
           "butterworth_gain", "if_filter_gain"]


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


def butterworth_gain(f_hz, corner_hz: float, order: int, *, highpass: bool) -> np.ndarray:
    """``|H(j 2 pi f)|`` of an analog Butterworth filter from its poles.

    Low-pass ``H(s) = prod_k (-p_k) / (s - p_k)`` with ``p_k = w_c exp(j pi (2k + n - 1) / (2n))``,
    ``k = 1..n``; high-pass ``H(s) = prod_k s / (s - p_k)`` (the transform ``s -> w_c^2 / s``).
    """
    s = 2j * np.pi * np.asarray(f_hz, dtype=np.float64)[..., None]
    k = np.arange(1, order + 1)
    p = 2 * np.pi * corner_hz * np.exp(1j * np.pi * (2 * k + order - 1) / (2 * order))
    num = s if highpass else -p
    return np.abs(np.prod(num / (s - p), axis=-1))


def if_filter_gain(cfg: DDMARadarConfig, f_hz) -> np.ndarray:
    """Gain of the sensor's IF chain (high-pass then anti-alias low-pass) at beat frequency ``f_hz``."""
    g = np.ones_like(np.asarray(f_hz, dtype=np.float64))
    if cfg.if_highpass_hz > 0 and cfg.if_highpass_order > 0:
        g = g * butterworth_gain(f_hz, cfg.if_highpass_hz, cfg.if_highpass_order, highpass=True)
    if cfg.aa_order > 0:
        g = g * butterworth_gain(f_hz, cfg.aa_cutoff * cfg.sample_rate_hz, cfg.aa_order, highpass=False)
    return g


def synthesize_ddma_adc(cfg: DDMARadarConfig, scatterers: Scatterers, *, noise: bool = False,
                   generator: torch.Generator | None = None, narrowband: bool = False) -> torch.Tensor:
    """ADC samples of one frame, summed over Tx (what the Rx antennas receive).

    Parameters
    ----------
    cfg : DDMARadarConfig
    scatterers : Scatterers
    noise : bool
        Add complex Gaussian thermal noise of power ``sigma_adc^2`` per sample, through the IF
        filter, plus the ADC floor.
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
    p = p_tx[:, None, :] + p_rx[None, :, :]                               # (m', r', 2) element pairs
    t_mat, r_mat = array_factors(cfg)                                     # (m, m'), (r, r')
    amp = np.sqrt(cfg.snr_per_sample(rng, rcs) * adc_noise_power(cfg))    # (S,)
    x = np.zeros((nk, nn, nrx), dtype=np.complex128)
    for s in range(len(rng)):
        ux, uy, uz = np.cos(el[s]) * np.cos(az[s]), np.cos(el[s]) * np.sin(az[s]), np.sin(el[s])
        h2 = ux * ux + uy * uy                                            # cos^2 el
        pattern = max(ux, 0.0) ** cfg.element_q_az / h2 ** ((cfg.element_q_az - cfg.element_q_el) / 2) \
            if h2 > 0 else 0.0
        u = np.array([uy, uz])
        path_k = 2.0 * (rng[s] + vel[s] * k * cfg.chirp_period_s)         # (k,) two-way path, m
        array_m = (p @ u) * lam / 2.0                                     # (m', r') path shortening, m
        tau = (path_k[:, None, None] - array_m[None]) / c                 # (k, m', r')
        # carrier phase f_c tau in cycles, reduced modulo one in float64 term by term
        cyc = (np.mod(fc * path_k / c, 1.0)[:, None, None] - np.mod(fc * array_m / c, 1.0)[None])
        carrier = np.exp(2j * np.pi * cyc)                                # (k, m', r')
        tau_b = np.full_like(tau, 2.0 * rng[s] / c) if narrowband else tau
        gain = if_filter_gain(cfg, slope * tau_b)                         # (k, m', r') IF filter
        beat = np.exp(2j * np.pi * slope * tau_b[:, None] * t_n[None, :, None, None])   # (k, n, m', r')
        pair = np.einsum("kmr,Mm,Rr,knmr->knMR", carrier * gain, t_mat, r_mat, beat)     # (k, n, m, r)
        x += amp[s] * pattern * np.einsum("knmr,km->knr", pair, code)
    leak = leakage_coefficients(cfg)
    if leak is not None:
        # on-bin leakage peak leakage_db above the thermal noise per cell, after the filter
        w_r, w_d = window(nn), window(nk)
        tau_l = 2.0 * cfg.leakage_range_m / c
        g_l = float(if_filter_gain(cfg, slope * tau_l))
        a_l = math.sqrt(10 ** (cfg.leakage_db / 10) * noise_power_rd(cfg)) / float(w_r.sum() * w_d.sum()) / g_l
        tone = np.exp(2j * np.pi * (np.mod(fc * tau_l, 1.0) + slope * tau_l * t_n)) * g_l    # (n,)
        x += a_l * np.einsum("km,n,mr->knr", code, tone, leak)
    out = torch.from_numpy(x)
    if noise:
        sigma = math.sqrt(adc_noise_power(cfg) / 2.0)
        z = torch.view_as_complex(torch.randn((nk, nn, nrx, 2), dtype=torch.float64, generator=generator))
        f_n = np.arange(nn) * cfg.sample_rate_hz / nn                     # beat frequency of each fast-time bin
        h = torch.from_numpy(if_filter_gain(cfg, f_n))[None, :, None]
        thermal = torch.fft.ifft(torch.fft.fft(z, dim=1) * h, dim=1)
        out = out + thermal * sigma
        if cfg.adc_floor_db is not None:
            z = torch.view_as_complex(torch.randn((nk, nn, nrx, 2), dtype=torch.float64, generator=generator))
            out = out + z * (sigma * 10 ** (cfg.adc_floor_db / 20))
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
