"""Single-chip TDM-MIMO cube processing (RaLD): ADC frames -> (range, azimuth, elevation) cube.

Tensors in, tensors out; batched over leading dimensions; the output lives on the input's device.
The steps, for ADC ``x[t, r, c, n]`` (Tx ``t``, Rx ``r``, chirp loop ``c``, sample ``n``):

1. DC removal over the whole frame and a Blackman window ``w[n]`` on the samples;
2. range FFT (``n_range``), Doppler FFT over the loops (``n_doppler``, fftshift);
3. TDM velocity compensation: Tx ``t`` fires ``t T_c`` after Tx 0 within a loop, so Doppler bin
   ``k`` (centred) is multiplied by ``exp(-j 2 pi t k / (N_tx N_d))``;
4. virtual array ``(elevation rows, azimuth columns)`` from the integer virtual positions,
   duplicate positions summed; azimuth and elevation FFTs (``n_azimuth``, ``n_elevation``,
   fftshift); the first and last ``crop`` fraction of range bins zeroed (5 %):
   :func:`tdm_spectrum` returns this complex cube ``S[e, a, k, i]``;
5. :func:`radar_cube`: power ``P = |S|^2``, per cell the Doppler-summed power ``sum_k P``
   normalised by its ``noise_quantile`` quantile over the frame (30 %), ``10 log10(p + 1)`` (dB),
   the velocity of the peak Doppler bin and a validity mask (peak ``(1 - 0.3)`` above the second
   peak).

Velocity axis, RaLD's convention (:func:`rald_velocity_bin_width`): Doppler bin ``k`` (centred)
is ``k dv`` with ``dv = 2 v_max / n_doppler`` and ``v_max = lambda_0 / (4 N_tx T_c)``, where RaLD
takes ``lambda_0 = c / f_0`` at the chirp's start frequency and the chirp time ``T_c = idle +
N_s / f_s + t_adc_start``: 0.03930 m/s on the AWR1843 with 128 Doppler bins. The physical bin
width of the sampled sweep (:meth:`radarpc.sensors.coloradar.WaveformConfig.velocity_bin_width`:
wavelength at the sweep centre, ``T_c = idle + ramp end``) is 1.7 % smaller, 0.03862 m/s; the
cube here is RaLD's, so it uses RaLD's.

The normalisation assumes receiver noise: the 30 % quantile is then the noise floor. On a
noise-free input (an ideal simulated target) the quantile is floating-point residue of the FFTs,
which differs between FFT kernels (CPUs), so only ratios of intensities within one cube (and
:func:`tdm_spectrum`'s powers) are meaningful there.

Sign conventions (bin order ascending towards +y and +z) are those of
:mod:`radarpc.sensors.coloradar`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from radarpc.sensors.coloradar import SPEED_OF_LIGHT, ColoRadarChipConfig, WaveformConfig

__all__ = ["RadarCube", "tdm_spectrum", "radar_cube", "rald_velocity_bin_width"]


@dataclass
class RadarCube:
    """RaLD radar cube of one frame (or a batch, leading dims first)."""

    intensity_db: torch.Tensor   # (..., R, A, E) 10 log10(P / noise + 1)
    doppler: torch.Tensor        # (..., R, A, E) radial velocity of the peak Doppler bin (m/s, RaLD's bin width)
    valid: torch.Tensor          # (..., R, A, E) bool: peak clearly above the second Doppler peak
    range_m: torch.Tensor        # (R,) bin ranges
    azimuth_rad: torch.Tensor    # (A,) bin azimuths (fftshift order, ascending towards +y)
    elevation_rad: torch.Tensor  # (E,) bin elevations

    def stacked(self) -> torch.Tensor:
        """``(..., R, A, E, 3)`` float32: intensity, Doppler, validity (RaLD's ``RAEIVVmap``)."""
        return torch.stack([self.intensity_db, self.doppler, self.valid.to(self.doppler.dtype)], -1)


def rald_velocity_bin_width(waveform: WaveformConfig, n_doppler: int) -> float:
    """m/s per bin of an ``n_doppler``-point Doppler FFT as RaLD's preprocessing computes it.

    .. math::

        \\Delta v = \\frac{2 v_{max}}{n_{doppler}}, \\quad
        v_{max} = \\frac{c / f_0}{4 N_{tx} T_c}, \\quad
        T_c = t_{idle} + \\frac{N_s}{f_s} + t_{adc\\,start}

    with ``f_0`` the chirp's start frequency and ``N_s`` the ADC samples per chirp (RaLD's "ramp
    time" ``N_s / f_s`` plus the ADC start time, not the configured ramp end). AWR1843, 128 bins:
    0.03930 m/s (the physical width, :meth:`WaveformConfig.velocity_bin_width`, is 0.03862 m/s).
    """
    n = int(n_doppler)
    if n < 1:
        raise ValueError(f"n_doppler must be >= 1, got {n_doppler}")
    w = waveform
    t_chirp = w.idle_time + w.num_adc_samples_per_chirp / w.adc_sample_frequency + w.adc_start_time
    v_max = (SPEED_OF_LIGHT / w.start_frequency) / (4 * w.num_tx * t_chirp)
    return 2 * v_max / n


def _virtual_grid(chip: ColoRadarChipConfig) -> tuple[np.ndarray, np.ndarray, int, int]:
    pos = chip.virtual_positions
    if not np.allclose(pos, np.round(pos)) or (pos < 0).any():
        raise ValueError(f"{chip.name}: virtual positions must be non-negative integers for the FFT array")
    pos = np.round(pos).astype(np.int64)
    return pos[:, 0], pos[:, 1], int(pos[:, 0].max()) + 1, int(pos[:, 1].max()) + 1


def tdm_spectrum(adc, chip: ColoRadarChipConfig, *, n_range: int = 128, n_doppler: int = 128,
                 n_azimuth: int = 8, n_elevation: int = 2, crop: float = 0.05) -> torch.Tensor:
    """Steps 1-4 of the module docstring: the complex cube ``(..., E, A, D, R)`` (complex64).

    Parameters
    ----------
    adc : complex array or tensor
        ``(..., tx, rx, chirps, samples)``; leading dims are a batch. Torch input keeps its device.
    chip : ColoRadarChipConfig
        Single-chip configuration (waveform for the sizes, antenna for the virtual array).
    n_range, n_doppler, n_azimuth, n_elevation : int
        FFT sizes (RaLD: 128, 128, 8, 2).
    crop : float
        Fraction of range bins zeroed at each end (RaLD: 0.05).

    Raises
    ------
    ValueError
        Real input, a shape that does not match ``chip``, NaN/inf samples, or bad sizes.
    """
    x = torch.as_tensor(adc)
    if not torch.is_complex(x):
        raise ValueError(f"adc must be complex (I + jQ), got dtype {x.dtype}")
    w = chip.waveform
    want = (w.num_tx, w.num_rx, w.num_chirps_per_frame, w.num_adc_samples_per_chirp)
    if x.ndim < 4 or tuple(x.shape[-4:]) != want:
        raise ValueError(f"adc must have shape (..., {', '.join(map(str, want))}) for {chip.name}, "
                         f"got {tuple(x.shape)}")
    if not torch.isfinite(torch.view_as_real(x)).all():
        raise ValueError("adc contains NaN or infinite values")
    for k, v in dict(n_range=n_range, n_doppler=n_doppler, n_azimuth=n_azimuth, n_elevation=n_elevation).items():
        if int(v) < 1:
            raise ValueError(f"{k} must be >= 1, got {v}")
    if not (0 <= crop < 0.5):
        raise ValueError(f"crop must be in [0, 0.5), got {crop}")
    x = x.to(torch.complex64)
    dev = x.device
    lead = x.shape[:-4]
    ntx, nrx, nc, ns = want
    x = x - x.mean(dim=(-4, -3, -2, -1), keepdim=True)
    win = torch.as_tensor(np.blackman(ns), dtype=torch.float32, device=dev)
    x = x * win
    rfft = torch.fft.fft(x, n=n_range, dim=-1)                                         # (..., tx, rx, c, R)
    dfft = torch.fft.fftshift(torch.fft.fft(rfft, n=n_doppler, dim=-2), dim=-2)       # (..., tx, rx, D, R)
    # TDM-MIMO velocity compensation: Tx t fires t T_c after Tx 0 within a loop
    tl = torch.arange(ntx, device=dev, dtype=torch.float32)
    cl = torch.arange(n_doppler, device=dev, dtype=torch.float32) - n_doppler // 2
    vcomp = torch.exp(-2j * math.pi * tl[:, None] * cl[None, :] / (ntx * n_doppler))
    dfft = dfft * vcomp[:, None, :, None]
    # virtual array (elevation rows, azimuth columns), duplicates summed
    ph, pv, na_v, ne_v = _virtual_grid(chip)
    flat = dfft.reshape(*lead, ntx * nrx, n_doppler, n_range)
    va = torch.zeros((*lead, ne_v * na_v, n_doppler, n_range), dtype=flat.dtype, device=dev)
    va.index_add_(len(lead), torch.as_tensor(pv * na_v + ph, device=dev), flat)
    va = va.reshape(*lead, ne_v, na_v, n_doppler, n_range)
    afft = torch.fft.fftshift(torch.fft.fft(va, n=n_azimuth, dim=-3), dim=-3)
    efft = torch.fft.fftshift(torch.fft.fft(afft, n=n_elevation, dim=-4), dim=-4)    # (..., E, A, D, R)
    c = int(n_range * crop)
    if c > 0:
        efft[..., :c] = 0
        efft[..., n_range - c:] = 0
    return efft


def radar_cube(adc, chip: ColoRadarChipConfig, *, n_range: int = 128, n_doppler: int = 128,
               n_azimuth: int = 8, n_elevation: int = 2, crop: float = 0.05,
               noise_quantile: float = 0.30) -> RadarCube:
    """RaLD's ADC -> (range, azimuth, elevation) cube (see module docstring).

    Parameters
    ----------
    adc, chip, n_range, n_doppler, n_azimuth, n_elevation, crop
        As for :func:`tdm_spectrum`.
    noise_quantile : float
        Quantile of the Doppler-summed power used as noise level and validity margin (0.3).

    Returns
    -------
    RadarCube
    """
    if not (0 < noise_quantile < 1):
        raise ValueError(f"noise_quantile must be in (0, 1), got {noise_quantile}")
    efft = tdm_spectrum(adc, chip, n_range=n_range, n_doppler=n_doppler, n_azimuth=n_azimuth,
                        n_elevation=n_elevation, crop=crop)                            # (..., E, A, D, R)
    lead = efft.shape[:-4]
    dev = efft.device
    w = chip.waveform
    power = efft.abs() ** 2
    top2 = torch.topk(power, k=min(2, n_doppler), dim=-2).values                     # (..., E, A, 2, R)
    peak = power.argmax(dim=-2)                                                        # (..., E, A, R)
    vbin = rald_velocity_bin_width(w, n_doppler)                                      # RaLD's convention
    velocity = (peak - n_doppler // 2).to(torch.float32) * vbin
    if n_doppler > 1:
        valid = top2[..., 0, :] * (1 - noise_quantile) > top2[..., 1, :]
    else:
        valid = torch.ones_like(peak, dtype=torch.bool)
    p = power.sum(dim=-2)                                                              # (..., E, A, R)
    noise = torch.quantile(p.reshape(*lead, -1).double(), noise_quantile, dim=-1).to(p.dtype)
    p = p / (noise.reshape(*lead, 1, 1, 1) + 1e-6)
    db = 10 * torch.log10(p + 1)
    perm = (*range(len(lead)), -1, -2, -3)                                             # -> (..., R, A, E)
    rbw = w.range_bin_width(n_range)
    d = chip.element_spacing
    fa = (torch.arange(n_azimuth, device=dev, dtype=torch.float32) - n_azimuth // 2) / n_azimuth
    fe = (torch.arange(n_elevation, device=dev, dtype=torch.float32) - n_elevation // 2) / n_elevation
    return RadarCube(db.permute(perm).contiguous(), velocity.permute(perm).contiguous(),
                     valid.permute(perm).contiguous(),
                     torch.arange(n_range, device=dev, dtype=torch.float32) * rbw,
                     torch.asin((fa / d).clamp(-1, 1)), torch.asin((fe / d).clamp(-1, 1)))
