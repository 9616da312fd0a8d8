"""Frequency-domain synthesis of DDMA range-Doppler cubes from point scatterers.

A frame of the RADIal-like radar (:mod:`radarpc.sensors.radial`) is the windowed 2-D FFT of the
ADC samples ``x[k, n, rx]`` (chirp ``k``, fast-time sample ``n``). For point scatterers ``s`` the
FFT is known in closed form, so the cube is built directly in the frequency domain:

.. math::

    \\mathrm{RD}[r, d, rx] = \\sum_s \\sum_{m=0}^{M-1} \\alpha_s\\, a_{m n_{rx} + rx}(\\theta_s)\\,
        W_r(r - b_s)\\, W_d(d - d_s - o_m) + n[r, d, rx]

* ``b_s = R_s / range_res_m`` is the fractional range bin (range of bin ``i`` is ``i * range_res_m``);
* ``d_s = v_s / velocity_res_mps`` the fractional Doppler bin (receding positive); with the DDMA
  offset ``o_m = tx_slots[m] * slot_width`` of Tx ``m`` it wraps modulo ``n_doppler`` because the
  point-spread function is periodic;
* ``W_N(delta) = sum_n w[n] exp(-j 2 pi delta n / N)`` is the DTFT of the window (periodic Hamming
  over ``N`` samples, as RADIal's processing uses over 512 samples and 256 chirps), evaluated at
  fractional offsets: main lobe, straddle loss and every sidelobe are the exact ones of the FFT;
* ``a_v(theta)`` is the virtual-array response with the hardware errors of the unit
  (:func:`radarpc.sensors.radial.steering_vectors`, channel ``v = tx * n_rx + rx``);
* ``alpha_s = A_s exp(j 4 pi R_s / lambda)``: amplitude ``A_s = sqrt(SNR_s * sigma_adc^2)`` from
  the radar equation (:meth:`DDMARadarConfig.snr_per_sample`, ``R^-4`` and RCS) and the carrier
  phase of the two-way path;
* ``n`` is circular complex Gaussian thermal noise of power :func:`noise_power_rd` per cell.

FFT normalisation: unnormalised forward FFTs (``numpy.fft.fft``), so a scatterer's peak is
``A_s * sum(w_r) * sum(w_d)`` and the thermal noise of ADC power ``sigma_adc^2`` becomes
``sigma_adc^2 * sum(w_r^2) * sum(w_d^2)`` per cell. RD units are fixed by
``noise_power_rd(cfg) = cfg.adc_full_scale ** 2`` (noise standard deviation ``adc_full_scale`` per
cell), which sets ``sigma_adc``. The peak SNR of a scatterer per RD cell per virtual channel is then
``SNR_sample * n_range * n_doppler * L_r * L_d`` with window losses ``L = (sum w)^2 / (N sum w^2)``.

Approximations, against the exact model of :mod:`radarpc.sim.adc` (which keeps the per-chirp,
per-element delay): stop-and-hop within a chirp and no residual video phase (both models); the
range bin ``b_s`` is fixed over the frame, so there is no range migration (a target moves
``|v| n_doppler T_c / range_res_m`` bins per frame: 0.11 bin at 27 m/s on ``tiny``, 1.9 bins at
30 m/s on full-size RADIal, 0.12 on ``radial-s``), and the array delay enters the carrier phase
only (narrowband array, at most ``max|p.u| lambda / (4 range_res_m)`` bins: 0.017 on ``tiny``,
0.40 at endfire on full-size RADIal).

The sum over scatterers is two dense products: ``M[s, d, rx] = sum_m W_d(...) alpha_s a(...)``
(a batched ``(n_doppler x M) @ (M x n_rx)`` product per scatterer) and
``RD = P @ M`` with ``P[r, s] = W_r(r - b_s)`` -- full-length kernels, so far sidelobes of strong
scatterers are kept. The kernels on the full axis are computed as FFTs of windowed tones
(:func:`psf_columns`, 3-4x faster than the closed form :func:`window_psf`, equal to 1e-10).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from radarpc.sensors.radial import DDMARadarConfig, channel_errors

__all__ = [
    "HAMMING",
    "Scatterers",
    "window",
    "window_psf",
    "psf_columns",
    "window_sums",
    "noise_power_rd",
    "adc_noise_power",
    "peak_snr_rd",
    "steering_torch",
    "synthesize_rd",
]

HAMMING: tuple[float, float] = (0.54, 0.46)
"""Coefficients ``(a0, a1)`` of the periodic Hamming window ``w[n] = a0 - a1 cos(2 pi n / N)``
used for both the range and the Doppler FFT."""


# ---- scatterers ------------------------------------------------------------------------------
@dataclass
class Scatterers:
    """``N`` point scatterers in the radar frame at the frame time.

    All fields are real float tensors of shape ``(N,)`` on one device. Frame and angle conventions
    are those of :mod:`radarpc.sensors.radial` (x forward, y left, z up; azimuth left positive).

    Attributes
    ----------
    range_m : Tensor ``(N,)``
        Distance from the radar phase centre, metres, > 0.
    azimuth_deg : Tensor ``(N,)``
        ``atan2(y, x)`` in degrees, left positive.
    elevation_deg : Tensor ``(N,)``
        ``asin(z / R)`` in degrees.
    velocity_mps : Tensor ``(N,)``
        Radial velocity relative to the radar, receding positive.
    rcs_m2 : Tensor ``(N,)``
        Radar cross-section in square metres, >= 0.
    """

    range_m: torch.Tensor
    azimuth_deg: torch.Tensor
    elevation_deg: torch.Tensor
    velocity_mps: torch.Tensor
    rcs_m2: torch.Tensor

    _FIELDS = ("range_m", "azimuth_deg", "elevation_deg", "velocity_mps", "rcs_m2")

    def __post_init__(self) -> None:
        ref = self.range_m
        if not isinstance(ref, torch.Tensor):
            raise ValueError(f"Scatterers.range_m must be a torch.Tensor, got {type(ref).__name__}")
        for name in self._FIELDS:
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor):
                raise ValueError(f"Scatterers.{name} must be a torch.Tensor, got {type(t).__name__}")
            if t.ndim != 1 or t.shape != ref.shape:
                raise ValueError(f"Scatterers.{name} must have shape (N,) = {tuple(ref.shape)}, "
                                 f"got {tuple(t.shape)}")
            if t.is_complex() or not t.is_floating_point():
                raise ValueError(f"Scatterers.{name} must be a real float tensor, got {t.dtype}")
            if t.device != ref.device:
                raise ValueError(f"Scatterers.{name} is on {t.device}, range_m on {ref.device}")
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"Scatterers.{name} contains NaN or infinite values")
        if ref.numel() and not bool((ref > 0).all()):
            raise ValueError(f"Scatterers.range_m must be > 0, got min {float(ref.min()):g}")
        if self.rcs_m2.numel() and not bool((self.rcs_m2 >= 0).all()):
            raise ValueError(f"Scatterers.rcs_m2 must be >= 0, got min {float(self.rcs_m2.min()):g}")

    def __len__(self) -> int:
        return int(self.range_m.shape[0])

    @property
    def device(self) -> torch.device:
        return self.range_m.device

    def to(self, device: torch.device | str | None = None,
           dtype: torch.dtype | None = None) -> "Scatterers":
        """Copy to ``device`` / ``dtype`` (a real float dtype)."""
        return Scatterers(*(getattr(self, f).to(device=device, dtype=dtype) for f in self._FIELDS))

    def select(self, mask_or_index: torch.Tensor) -> "Scatterers":
        """The scatterers picked by a boolean mask or an index tensor."""
        return Scatterers(*(getattr(self, f)[mask_or_index] for f in self._FIELDS))

    @classmethod
    def cat(cls, parts: "list[Scatterers]") -> "Scatterers":
        """Concatenate several sets (at least one)."""
        if not parts:
            raise ValueError("Scatterers.cat needs at least one set")
        return cls(*(torch.cat([getattr(p, f) for p in parts]) for f in cls._FIELDS))

    @classmethod
    def from_xyz(cls, xyz, velocity_xyz, rcs_m2) -> "Scatterers":
        """Scatterers from Cartesian positions and velocities relative to the radar.

        Parameters
        ----------
        xyz : array_like or Tensor ``(N, 3)``
            Positions in the radar frame (x forward, y left, z up), metres.
        velocity_xyz : array_like or Tensor ``(N, 3)``
            Velocities relative to the radar, m/s; the radial velocity is ``<p, v> / |p|``.
        rcs_m2 : array_like or Tensor ``(N,)``

        Returns
        -------
        Scatterers
            On the device of ``xyz`` (CPU for array input), in ``xyz``'s float dtype (float32
            for non-float input).
        """
        p = torch.as_tensor(xyz)
        dev = p.device
        dt = p.dtype if p.is_floating_point() and not p.is_complex() else torch.float32
        p = p.to(dt)
        v = torch.as_tensor(velocity_xyz, device=dev).to(dt)
        rcs = torch.as_tensor(rcs_m2, device=dev).to(dt)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"xyz must have shape (N, 3), got {tuple(p.shape)}")
        if v.shape != p.shape:
            raise ValueError(f"velocity_xyz must have shape {tuple(p.shape)} like xyz, got {tuple(v.shape)}")
        if rcs.shape != p.shape[:1]:
            raise ValueError(f"rcs_m2 must have shape ({p.shape[0]},), got {tuple(rcs.shape)}")
        r = torch.linalg.vector_norm(p, dim=1)                     # (N,)
        if p.shape[0] and not bool((r > 0).all()):
            raise ValueError("xyz contains a point at the radar origin (range 0)")
        az = torch.rad2deg(torch.atan2(p[:, 1], p[:, 0]))
        el = torch.rad2deg(torch.asin(torch.clamp(p[:, 2] / r.clamp_min(1e-12), -1.0, 1.0)))
        vr = (p * v).sum(dim=1) / r.clamp_min(1e-12)
        return cls(range_m=r, azimuth_deg=az, elevation_deg=el, velocity_mps=vr, rcs_m2=rcs)


# ---- windows and their point-spread functions -------------------------------------------------
def window(n: int, *, device: torch.device | str | None = None,
           dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Periodic Hamming window ``w[k] = 0.54 - 0.46 cos(2 pi k / n)``, shape ``(n,)``."""
    if int(n) < 1:
        raise ValueError(f"window length must be >= 1, got {n}")
    k = torch.arange(int(n), device=device, dtype=torch.float64)
    a0, a1 = HAMMING
    return (a0 - a1 * torch.cos(2 * math.pi * k / int(n))).to(dtype)


def window_sums(n: int) -> tuple[float, float]:
    """``(sum w, sum w^2)`` of the length-``n`` window: coherent gain and noise gain of the FFT."""
    w = window(n)
    return float(w.sum()), float((w * w).sum())


def _dirichlet(delta: torch.Tensor, n: int) -> torch.Tensor:
    # D_N(delta) = sum_{k<N} exp(-j 2 pi delta k / N) = exp(-j pi delta (N-1)/N) sin(pi delta) / sin(pi delta / N)
    # periodic in delta with period N: reduce to [-N/2, N/2) where the only pole is delta = 0 (D = N).
    d = delta - n * torch.round(delta / n)
    small = d.abs() < 1e-9
    ds = torch.where(small, torch.ones_like(d), d)
    mag = torch.sin(math.pi * ds) / torch.sin(math.pi * ds / n)
    mag = torch.where(small, torch.full_like(d, float(n)), mag)
    return torch.polar(mag, -math.pi * d * (n - 1) / n)


def psf_columns(bins: torch.Tensor, n: int) -> torch.Tensor:
    """Point-spread functions on the whole FFT axis: ``P[i, s] = W(i - bins[s])``, ``(n, S)``.

    Computed as the FFT of the windowed tone ``w[k] exp(j 2 pi bins[s] k / n)`` (phases reduced
    modulo one cycle in float64), which equals :func:`window_psf` at the offsets ``i - bins[s]``
    and is cheaper than the closed form on a full axis.

    Parameters
    ----------
    bins : Tensor ``(S,)``
        Real fractional bin positions.
    n : int
        FFT length.

    Returns
    -------
    Tensor
        complex128 ``(n, S)``.
    """
    if bins.is_complex() or bins.ndim != 1:
        raise ValueError(f"psf_columns: bins must be a real (S,) tensor, got {tuple(bins.shape)} {bins.dtype}")
    b = bins.to(torch.float64)
    k = torch.arange(int(n), device=b.device, dtype=torch.float64)
    cycles = torch.remainder(k[:, None] * b[None, :], float(n)) / n              # (n, S)
    w = window(n, device=b.device)[:, None].expand(int(n), b.shape[0])
    return torch.fft.fft(torch.polar(w.contiguous(), (2 * math.pi) * cycles), dim=0)


def window_psf(delta: torch.Tensor, n: int) -> torch.Tensor:
    """DTFT of the periodic Hamming window at (fractional) bin offsets ``delta``.

    ``W(delta) = sum_k w[k] exp(-j 2 pi delta k / n) = a0 D(delta) - a1/2 (D(delta-1) + D(delta+1))``
    with ``D`` the Dirichlet kernel. This is the complex response of FFT bin ``i`` to a tone at
    fractional bin ``i - delta``; it is periodic in ``delta`` with period ``n``.

    Parameters
    ----------
    delta : Tensor
        Real offsets in bins, any shape; computed in float64.
    n : int
        FFT length.

    Returns
    -------
    Tensor
        complex128, shape of ``delta``.
    """
    if delta.is_complex():
        raise ValueError("window_psf: delta must be real bin offsets, got a complex tensor")
    d = delta.to(torch.float64)
    a0, a1 = HAMMING
    return a0 * _dirichlet(d, n) - 0.5 * a1 * (_dirichlet(d - 1, n) + _dirichlet(d + 1, n))


# ---- units -------------------------------------------------------------------------------------
def noise_power_rd(cfg: DDMARadarConfig) -> float:
    """``E|n|^2`` of the thermal noise per RD cell per Rx, in RD units: ``cfg.adc_full_scale ** 2``."""
    return float(cfg.adc_full_scale) ** 2


def adc_noise_power(cfg: DDMARadarConfig) -> float:
    """Thermal noise power per complex ADC sample in the same units, ``sigma_adc^2``.

    ``noise_power_rd = sigma_adc^2 * sum(w_r^2) * sum(w_d^2)`` (unnormalised windowed FFTs).
    """
    _, q_r = window_sums(cfg.n_range)
    _, q_d = window_sums(cfg.n_doppler)
    return noise_power_rd(cfg) / (q_r * q_d)


def peak_snr_rd(cfg: DDMARadarConfig, range_m, rcs_m2) -> np.ndarray:
    """SNR (linear) of a scatterer's on-bin peak in one RD cell of one virtual channel.

    ``SNR_sample * (sum w_r)^2 (sum w_d)^2 / (sum w_r^2 sum w_d^2)`` with unit channel gain.
    """
    s_r, q_r = window_sums(cfg.n_range)
    s_d, q_d = window_sums(cfg.n_doppler)
    return cfg.snr_per_sample(range_m, rcs_m2) * (s_r * s_r * s_d * s_d) / (q_r * q_d)


@functools.lru_cache(maxsize=16)
def _array_constants(cfg: DDMARadarConfig) -> tuple[np.ndarray, np.ndarray]:
    return cfg.virtual_positions.copy(), channel_errors(cfg)


def steering_torch(cfg: DDMARadarConfig, az_deg: torch.Tensor, el_deg: torch.Tensor, *,
                   hardware: bool = True) -> torch.Tensor:
    """Torch twin of :func:`radarpc.sensors.radial.steering_vectors` for ``(N,)`` angles.

    Returns complex128 ``(N, n_virtual)`` on the angles' device.
    """
    pos_np, err_np = _array_constants(cfg)
    dev = az_deg.device
    a = torch.deg2rad(az_deg.to(torch.float64))
    e = torch.deg2rad(el_deg.to(torch.float64))
    pos = torch.as_tensor(pos_np, device=dev)                       # (V, 2)
    uy = torch.cos(e) * torch.sin(a)
    uz = torch.sin(e)
    phase = -math.pi * (uy[:, None] * pos[None, :, 0] + uz[:, None] * pos[None, :, 1])  # (N, V)
    resp = torch.polar(torch.ones_like(phase), phase)
    if hardware:
        resp = resp * torch.as_tensor(err_np, device=dev)[None, :]
    return resp


# ---- synthesis ---------------------------------------------------------------------------------
def _signal_rd(cfg: DDMARadarConfig, sc: Scatterers, device: torch.device) -> torch.Tensor:
    """Noise-free cube ``(n_range, n_doppler, n_rx)`` complex64 of the scatterers."""
    nr, nd, ntx, nrx = cfg.n_range, cfg.n_doppler, cfg.n_tx, cfg.n_rx
    n = len(sc)
    if n == 0:
        return torch.zeros((nr, nd, nrx), dtype=torch.complex64, device=device)
    f64 = torch.float64
    rng = sc.range_m.to(device=device, dtype=f64)                   # (S,)
    vel = sc.velocity_mps.to(device=device, dtype=f64)
    rcs = sc.rcs_m2.to(device=device, dtype=f64)
    # radar equation: SNR = K * rcs / R^4 with K the SNR of 1 m^2 at 1 m (same clamp as cfg.snr_per_sample)
    k_snr = float(cfg.snr_per_sample(1.0, 1.0))
    amp = torch.sqrt(k_snr * rcs / rng.clamp_min(0.1) ** 4 * adc_noise_power(cfg))
    carrier = torch.remainder(2.0 * rng / cfg.wavelength_m, 1.0) * (2 * math.pi)   # 4 pi R / lambda mod 2 pi
    alpha = torch.polar(amp, carrier)                                # (S,)
    steer = steering_torch(cfg, sc.azimuth_deg.to(device), sc.elevation_deg.to(device))  # (S, V)
    chan = (alpha[:, None] * steer).reshape(n, ntx, nrx).to(torch.complex64)      # (S, M, Rx)

    # range PSF P[r, s] = W_r(r - b_s)
    b = rng / cfg.range_res_m
    p_range = psf_columns(b, nr).to(torch.complex64)                             # (R, S)

    # Doppler PSF of Tx m: W_d(d - d_s - o_m) = Q0[s, (d - o_m) mod N_d] with Q0[s, d] = W_d(d - d_s)
    d_s = vel / cfg.velocity_res_mps
    q0 = psf_columns(d_s, nd).T.to(torch.complex64)                              # (S, D)
    offs = torch.as_tensor(cfg.doppler_offsets, device=device)                   # (M,)
    gather = torch.remainder(torch.arange(nd, device=device)[None, :] - offs[:, None], nd)  # (M, D)
    q = q0[:, gather]                                                            # (S, M, D)

    m = torch.bmm(q.transpose(1, 2), chan)                                       # (S, D, Rx)
    rd = p_range @ m.reshape(n, nd * nrx)                                        # (R, D*Rx)
    return rd.reshape(nr, nd, nrx)


def _check_generator(generator: torch.Generator | None, device: torch.device) -> None:
    if generator is not None and torch.device(generator.device).type != device.type:
        raise ValueError(f"generator is on {generator.device}, synthesis runs on {device}; "
                         "create the torch.Generator on the same device")


def synthesize_rd(cfg: DDMARadarConfig, scatterers: Scatterers | list[Scatterers], *,
                  noise: bool = True, generator: torch.Generator | None = None,
                  device: torch.device | str | None = None) -> torch.Tensor:
    """Synthesise the complex RD cube of point scatterers (see the module docstring).

    Parameters
    ----------
    cfg : DDMARadarConfig
        Sensor: sizes, DDMA offsets, array, radar equation.
    scatterers : Scatterers or list of Scatterers
        One frame, or a batch of frames.
    noise : bool
        Add complex Gaussian thermal noise of power :func:`noise_power_rd` per cell.
    generator : torch.Generator, optional
        Source of the noise (on ``device``); the global torch RNG if omitted.
    device : torch.device or str, optional
        Where to compute; default the scatterers' device.

    Returns
    -------
    Tensor
        complex64 ``(n_range, n_doppler, n_rx)``, or ``(B, n_range, n_doppler, n_rx)`` for a list.
    """
    if isinstance(scatterers, (list, tuple)):
        if not scatterers:
            raise ValueError("synthesize_rd: empty list of scatterer sets")
        return torch.stack([synthesize_rd(cfg, s, noise=noise, generator=generator, device=device)
                            for s in scatterers])
    if not isinstance(scatterers, Scatterers):
        raise ValueError(f"synthesize_rd expects Scatterers or a list of them, got {type(scatterers).__name__}")
    dev = torch.device(device) if device is not None else scatterers.device
    rd = _signal_rd(cfg, scatterers, dev)
    if noise:
        _check_generator(generator, dev)
        z = torch.empty((*cfg.rd_shape, 2), dtype=torch.float32, device=dev)
        z.normal_(generator=generator)                               # real and imaginary parts
        z.mul_(math.sqrt(noise_power_rd(cfg) / 2.0))
        rd.add_(torch.view_as_complex(z))
    return rd
