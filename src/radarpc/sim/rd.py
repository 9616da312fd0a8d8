"""Frequency-domain synthesis of DDMA range-Doppler cubes from point scatterers.

A frame of the RADIal-like radar (:mod:`radarpc.sensors.radial`) is the windowed 2-D FFT of the
ADC samples ``x[k, n, rx]`` (chirp ``k``, fast-time sample ``n``). For point scatterers ``s`` the
FFT is known in closed form, so the cube is built directly in the frequency domain:

.. math::

    \\mathrm{RD}[r, d, rx] = \\sum_s \\sum_{m=0}^{M-1} \\alpha_s\\, |H(f_{b_s})|\\, a_{m n_{rx} + rx}(\\theta_s)\\,
        W_r(r - b_s)\\, W_d(d - d_s - o_m) + \\mathrm{leak}[r, d, rx] + n[r, d, rx] + \\mathrm{pn}[r, d, rx]

* ``b_s = R_s / range_res_m`` is the fractional range bin (range of bin ``i`` is ``i * range_res_m``);
* ``d_s = v_s / velocity_res_mps`` the fractional Doppler bin (receding positive); with the DDMA
  offset ``o_m = tx_slots[m] * slot_width`` of Tx ``m`` it wraps modulo ``n_doppler`` because the
  point-spread function is periodic;
* ``W_N(delta) = sum_n w[n] exp(-j 2 pi delta n / N)`` is the DTFT of the window (periodic Hamming
  over ``N`` samples, as RADIal's processing uses over 512 samples and 256 chirps), evaluated at
  fractional offsets: main lobe, straddle loss and every sidelobe are the exact ones of the FFT;
* ``a_v(theta)`` is the TRUE virtual-array response of the unit: element pattern, geometry,
  mutual coupling, per-channel gain/phase errors (:func:`radarpc.sensors.radial.steering_vectors`,
  channel ``v = tx * n_rx + rx``); the calibration table only estimates it;
* ``alpha_s = A_s exp(j 4 pi R_s / lambda)``: amplitude ``A_s = sqrt(SNR_s * sigma_adc^2)`` from
  the radar equation (:meth:`DDMARadarConfig.snr_per_sample`, ``R^-4`` and RCS, boresight gain)
  and the carrier phase of the two-way path;
* ``|H(f)|``: the IF filter (high-pass and anti-alias low-pass, :func:`receiver_gain`) at the
  scatterer's beat frequency ``f_b = b_s f_s / n_range``: a tone passes a linear filter scaled by
  its gain at the tone's frequency;
* ``leak``: the Tx->Rx leakage, one more static source at ``leakage_range_m`` with the channel
  pattern :func:`leakage_coefficients` instead of an array response, so it lands at range ~0 on
  every Tx's DDMA offset;
* ``n`` is circular complex Gaussian thermal noise of power :func:`noise_profile_rd` per cell of
  range bin ``r``: ``noise_power_rd |H(f_r)|^2`` plus the ADC floor;
* ``pn``: phase-noise skirts of the strong sources (:func:`skirt_power_rd`).

``noise=False`` keeps the deterministic part (scatterers and leakage through the filter); the
random parts ``n`` and ``pn`` are drawn from the frame's generator, in that order, so a frame is
bit-reproducible from its seed on one device.

FFT normalisation: unnormalised forward FFTs (``numpy.fft.fft``), so a scatterer's peak is
``A_s * sum(w_r) * sum(w_d)`` and the thermal noise of ADC power ``sigma_adc^2`` becomes
``sigma_adc^2 * sum(w_r^2) * sum(w_d^2)`` per cell. RD units are fixed by
``noise_power_rd(cfg) = cfg.adc_full_scale ** 2`` (noise standard deviation ``adc_full_scale`` per
cell before the IF filter), which sets ``sigma_adc`` (the choice of ``adc_full_scale`` is
discussed in :class:`radarpc.sensors.radial.DDMARadarConfig`). The peak SNR of a scatterer per RD cell per virtual channel is then
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
The skirts reuse the same two products for the few sources strong enough to have one.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from radarpc.sensors.radial import SPEED_OF_LIGHT, DDMARadarConfig, array_factors

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
    "beat_hz",
    "receiver_gain",
    "noise_profile_rd",
    "leakage_coefficients",
    "phase_noise_psd",
    "skirt_power_rd",
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


@functools.lru_cache(maxsize=32)
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
def _array_constants(cfg: DDMARadarConfig) -> tuple[np.ndarray, ...]:
    t, r = array_factors(cfg)
    return (np.asarray(cfg.tx_pos, dtype=np.float64), np.asarray(cfg.rx_pos, dtype=np.float64), t, r)


def steering_torch(cfg: DDMARadarConfig, az_deg: torch.Tensor, el_deg: torch.Tensor, *,
                   hardware: bool = True) -> torch.Tensor:
    """Torch twin of :func:`radarpc.sensors.radial.steering_vectors` for ``(N,)`` angles.

    ``hardware=True``: the true response (element pattern, coupling, channel errors). Returns
    complex128 ``(N, n_virtual)`` on the angles' device.
    """
    pt_np, pr_np, t_np, r_np = _array_constants(cfg)
    dev = az_deg.device
    a = torch.deg2rad(az_deg.to(torch.float64))
    e = torch.deg2rad(el_deg.to(torch.float64))
    u = torch.stack([torch.cos(e) * torch.sin(a), torch.sin(e)], dim=1)         # (N, 2)
    ph_t = -math.pi * (u @ torch.as_tensor(pt_np, device=dev).T)                # (N, n_tx)
    ph_r = -math.pi * (u @ torch.as_tensor(pr_np, device=dev).T)                # (N, n_rx)
    et = torch.polar(torch.ones_like(ph_t), ph_t)
    er = torch.polar(torch.ones_like(ph_r), ph_r)
    if hardware:
        et = et @ torch.as_tensor(t_np, device=dev).T
        gain = (torch.cos(a).clamp_min(0) ** cfg.element_q_az) * (torch.cos(e).clamp_min(0) ** cfg.element_q_el)
        er = (er @ torch.as_tensor(r_np, device=dev).T) * gain[:, None]
    return (et[:, :, None] * er[:, None, :]).reshape(len(a), cfg.n_virtual)


# ---- receiver ------------------------------------------------------------------------------------
def beat_hz(cfg: DDMARadarConfig, bins):
    """Beat frequency (Hz) of (fractional) range bin ``bins``: ``b f_s / n_range`` (= ``S 2 R / c``)."""
    return np.asarray(bins, dtype=np.float64) * (cfg.sample_rate_hz / cfg.n_range) if not \
        isinstance(bins, torch.Tensor) else bins.to(torch.float64) * (cfg.sample_rate_hz / cfg.n_range)


def receiver_gain(cfg: DDMARadarConfig, bins):
    """Amplitude gain of the IF chain at the beat frequency of range bin ``bins``.

    .. math::

        |H(f)|^2 = \\frac{(f / f_{hp})^{2 n_{hp}}}{1 + (f / f_{hp})^{2 n_{hp}}}
                   \\cdot \\frac{1}{1 + (f / (c_{aa} f_s))^{2 n_{aa}}}

    a Butterworth high-pass of order ``if_highpass_order`` at ``if_highpass_hz`` (it attenuates
    the strong near-range returns: ``40 n_hp`` dB/decade below the corner) times a Butterworth
    anti-alias low-pass of order ``aa_order`` at ``aa_cutoff * f_s`` (the far range bins roll off).
    ``if_highpass_hz = 0`` / ``aa_order = 0`` switch a filter off. Zero-phase: the phase response
    of the filter is a constant phase per scatterer, which no stage of radarpc observes. Works on
    numpy arrays and torch tensors (float64).
    """
    f = beat_hz(cfg, bins)
    lib = torch if isinstance(f, torch.Tensor) else np
    g2 = lib.ones_like(f)
    if cfg.if_highpass_hz > 0 and cfg.if_highpass_order > 0:
        x = (lib.abs(f) / cfg.if_highpass_hz) ** (2 * cfg.if_highpass_order)
        g2 = g2 * x / (1 + x)
    if cfg.aa_order > 0:
        g2 = g2 / (1 + (lib.abs(f) / (cfg.aa_cutoff * cfg.sample_rate_hz)) ** (2 * cfg.aa_order))
    return lib.sqrt(g2)


def noise_profile_rd(cfg: DDMARadarConfig) -> np.ndarray:
    """Expected noise power per RD cell per Rx for each range bin, ``(n_range,)`` float64.

    ``noise_power_rd * (|H(f_i)|^2 + 10^(adc_floor_db / 10))``: the thermal noise passes the IF
    filter (:func:`receiver_gain`), the ADC adds its own white floor after it (quantisation, clock
    jitter), so the far rows darken by the anti-alias roll-off down to that floor.
    """
    g = receiver_gain(cfg, np.arange(cfg.n_range))
    floor = 0.0 if cfg.adc_floor_db is None else 10 ** (cfg.adc_floor_db / 10)
    return noise_power_rd(cfg) * (g * g + floor)


def leakage_coefficients(cfg: DDMARadarConfig) -> np.ndarray | None:
    """Complex Tx->Rx leakage of each virtual channel, ``(n_tx, n_rx)``, or None when off.

    Direct coupling from every Tx to every Rx (on-chip and antenna), a fixed property of the unit:
    magnitude log-normal (3 dB std) around 1, uniform phase, from ``default_rng([hardware_seed, 11])``.
    Scaled by :func:`synthesize_rd` so that an on-bin leakage peak of unit magnitude lies
    ``leakage_db`` above the thermal noise per cell.
    """
    if cfg.leakage_db is None:
        return None
    rng = np.random.default_rng([cfg.hardware_seed, 11])
    mag = 10 ** (rng.normal(0.0, 3.0, (cfg.n_tx, cfg.n_rx)) / 20)
    return mag * np.exp(2j * np.pi * rng.uniform(0.0, 1.0, (cfg.n_tx, cfg.n_rx)))


def phase_noise_psd(cfg: DDMARadarConfig, f_hz):
    """LO phase-noise PSD ``L(f)`` (rad^2/Hz, two-sided) at offset ``f_hz``; 0 when off.

    ``L(f) = L_0 / (1 + (f / f_c)^2) + L_floor``: flat inside the PLL loop bandwidth ``f_c =
    pn_corner_hz`` at ``L_0 = pn_dbc_hz``, -20 dB/decade beyond, down to ``pn_floor_dbc_hz``.
    """
    lib = torch if isinstance(f_hz, torch.Tensor) else np
    if cfg.pn_dbc_hz is None:
        return lib.zeros_like(f_hz)
    l0, lf = 10 ** (cfg.pn_dbc_hz / 10), 10 ** (cfg.pn_floor_dbc_hz / 10)
    return l0 / (1 + (f_hz / cfg.pn_corner_hz) ** 2) + lf


def skirt_power_rd(cfg: DDMARadarConfig, range_m, bins):
    """Phase-noise skirt of a scatterer at ``range_m`` in range bins ``bins``, re its per-sample power.

    The IF of a target of delay ``tau = 2 R / c`` carries the phase ``phi(t) - phi(t - tau)``: the
    transmitted and the LO phase noise are the same process, delayed. Its PSD is
    ``L(f) |1 - exp(-j 2 pi f tau)|^2 = 4 L(f) sin^2(pi f tau)`` (range correlation: near targets,
    small ``tau``, have almost no skirt; it grows with range). The small-angle term ``j Delta phi``
    at offset ``f`` from the target's beat frequency is noise of per-sample variance
    ``A^2 4 L(f) sin^2(pi f tau) f_s``; it changes from chirp to chirp (the 50 us chirp outlasts
    the 25 kHz bin spacing), so it is white over Doppler, and the windowed FFTs give per cell

    .. math::

        P_{pn}(i) = A^2\\, 4 L(f_i - f_b)\\, \\sin^2(\\pi (f_i - f_b) \\tau)\\, f_s\\, |H(f_i)|^2
                    \\textstyle\\sum w_r^2 \\sum w_d^2

    (``f_i`` the beat frequency of bin ``i``, ``f_b`` of the scatterer, ``f_s`` the sample rate;
    the skirt passes the IF filter at its own frequency). Returns
    ``P_pn / (A^2 sum w_r^2 sum w_d^2)``, broadcast over ``range_m`` and ``bins`` (numpy).
    """
    tau = 2.0 * np.asarray(range_m, dtype=np.float64) / SPEED_OF_LIGHT
    f_off = beat_hz(cfg, bins) - beat_hz(cfg, np.asarray(range_m) / cfg.range_res_m)
    g = receiver_gain(cfg, bins)
    return 4 * phase_noise_psd(cfg, f_off) * np.sin(np.pi * f_off * tau) ** 2 * cfg.sample_rate_hz * g * g


# ---- synthesis ---------------------------------------------------------------------------------
def _sources(cfg: DDMARadarConfig, sc: Scatterers, device: torch.device):
    """Per-sample complex amplitudes BEFORE the IF filter of every source: the scatterers, then the
    Tx leakage (one pseudo-scatterer at ``leakage_range_m``, zero Doppler, channel pattern
    :func:`leakage_coefficients`). Returns ``(range_m (S,), velocity (S,), chan (S, n_tx, n_rx))``
    float64 / complex128."""
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
    chan = (alpha[:, None] * steer).reshape(len(sc), cfg.n_tx, cfg.n_rx)
    leak = leakage_coefficients(cfg)
    if leak is not None:
        s_r, _ = window_sums(cfg.n_range)
        s_d, _ = window_sums(cfg.n_doppler)
        b_l = cfg.leakage_range_m / cfg.range_res_m
        a_l = math.sqrt(10 ** (cfg.leakage_db / 10) * noise_power_rd(cfg)) / (s_r * s_d) \
            / float(receiver_gain(cfg, b_l))                         # pre-filter, per sample
        ph = 2 * math.pi * math.remainder(2.0 * cfg.leakage_range_m / cfg.wavelength_m, 1.0)
        c_l = torch.as_tensor(leak * (a_l * np.exp(1j * ph)), device=device)[None]
        rng = torch.cat([rng, torch.full((1,), cfg.leakage_range_m, dtype=f64, device=device)])
        vel = torch.cat([vel, torch.zeros(1, dtype=f64, device=device)])
        chan = torch.cat([chan, c_l])
    return rng, vel, chan


def _ddma_mix(cfg: DDMARadarConfig, q0: torch.Tensor, chan: torch.Tensor) -> torch.Tensor:
    """``M[s, d, rx] = sum_m q0[s, (d - o_m) mod N_d] chan[s, m, rx]``: Tx ``m`` shifted by its DDMA
    offset. ``q0`` (S, D), ``chan`` (S, M, Rx) complex64 -> (S, D * Rx)."""
    nd = cfg.n_doppler
    offs = torch.as_tensor(cfg.doppler_offsets, device=q0.device)                # (M,)
    gather = torch.remainder(torch.arange(nd, device=q0.device)[None, :] - offs[:, None], nd)  # (M, D)
    q = q0[:, gather]                                                            # (S, M, D)
    return torch.bmm(q.transpose(1, 2), chan).reshape(q0.shape[0], nd * cfg.n_rx)  # (S, D*Rx)


def _signal_rd(cfg: DDMARadarConfig, rng: torch.Tensor, vel: torch.Tensor, chan: torch.Tensor) -> torch.Tensor:
    """Noise-free cube ``(n_range, n_doppler, n_rx)`` complex64 of the sources (after the IF filter)."""
    nr, nd, nrx = cfg.n_range, cfg.n_doppler, cfg.n_rx
    if len(rng) == 0:
        return torch.zeros((nr, nd, nrx), dtype=torch.complex64, device=rng.device)
    b = rng / cfg.range_res_m
    chan = (chan * receiver_gain(cfg, b)[:, None, None]).to(torch.complex64)     # (S, M, Rx)
    p_range = psf_columns(b, nr).to(torch.complex64)                             # (R, S): W_r(r - b_s)
    q0 = psf_columns(vel / cfg.velocity_res_mps, nd).T.to(torch.complex64)       # (S, D): W_d(d - d_s)
    return (p_range @ _ddma_mix(cfg, q0, chan)).reshape(nr, nd, nrx)


_SKIRT_FLOOR = 1e-2
"""Skirts below this fraction of the local noise floor in every cell are left out (< 1 % of the
cell power, and most scatterers: only strong ones pay for a skirt)."""


def _skirts_rd(cfg: DDMARadarConfig, rng: torch.Tensor, chan: torch.Tensor,
               generator: torch.Generator | None) -> torch.Tensor | None:
    """Phase-noise skirts of the strong sources (:func:`skirt_power_rd`), or None if there are none.

    Per source a rank-one random field: ``Skirt[r, d, rx] = sum_s e_s(r) eta_s(r) sum_m
    Xi_s[(d - o_m) mod N_d] chan[s, m, rx]`` with ``e_s^2`` the skirt power profile and ``eta``,
    ``Xi`` unit circular Gaussians: every cell has the right expected power and the channel
    signature of its source (the phase noise is common to all Tx and Rx, shifted by each Tx's DDMA
    offset); it ignores the correlation the windows put between neighbouring cells and the
    independence of cells of one source (a rank-one product instead).
    """
    if cfg.pn_dbc_hz is None or len(rng) == 0:
        return None
    _, q_r = window_sums(cfg.n_range)
    _, q_d = window_sums(cfg.n_doppler)
    profile = noise_profile_rd(cfg)
    peak2 = (chan.abs() ** 2).amax(dim=(1, 2)).cpu().numpy()                   # (S,)
    # candidates by an upper bound, then the exact profile: |H| <= 1 and
    # 4 L(f) sin^2(pi f tau) <= 4 min(L_0 + L_f, (pi tau)^2 (L_0 f_c^2 + L_f f_s^2))
    # (sin x <= x, L_0 f^2 / (1 + (f / f_c)^2) <= L_0 f_c^2, |f| <= f_s)
    l0, lf = 10 ** (cfg.pn_dbc_hz / 10), 10 ** (cfg.pn_floor_dbc_hz / 10)
    tau = 2.0 * rng.detach().cpu().numpy() / SPEED_OF_LIGHT
    fs = cfg.sample_rate_hz
    top = 4 * np.minimum(l0 + lf, (np.pi * tau) ** 2 * (l0 * cfg.pn_corner_hz ** 2 + lf * fs * fs)) * fs * q_r * q_d
    cand = np.flatnonzero(peak2 * top / profile.min() > _SKIRT_FLOOR)
    if cand.size == 0:
        return None
    r_np = rng.detach().cpu().numpy()[cand]
    env2 = skirt_power_rd(cfg, r_np[None, :], np.arange(cfg.n_range)[:, None]) * (q_r * q_d)   # (R, S')
    keep = (env2 * peak2[cand][None, :] / profile[:, None]).max(0) > _SKIRT_FLOOR
    strong, env2 = cand[keep], env2[:, keep]
    if strong.size == 0:
        return None
    dev = rng.device
    idx = torch.as_tensor(strong, device=dev)
    n = len(strong)
    nr, nd = cfg.n_range, cfg.n_doppler
    z = torch.empty((nr + nd, n, 2), dtype=torch.float32, device=dev)
    z.normal_(generator=generator)
    z = torch.view_as_complex(z) * math.sqrt(0.5)                                # CN(0, 1)
    p = torch.as_tensor(np.sqrt(env2), device=dev).to(torch.float32) * z[:nr]   # (R, S')
    m = _ddma_mix(cfg, z[nr:].T.contiguous(), chan[idx].to(torch.complex64))   # (S', D*Rx)
    return (p @ m).reshape(nr, nd, cfg.n_rx)


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
        Add the random parts: complex Gaussian thermal noise shaped by the IF filter plus the ADC
        floor (:func:`noise_profile_rd` per cell), and the phase-noise skirts of strong sources
        (:func:`skirt_power_rd`). ``False``: the deterministic cube (scatterers and Tx leakage,
        after the IF filter).
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
    rng, vel, chan = _sources(cfg, scatterers, dev)
    rd = _signal_rd(cfg, rng, vel, chan)
    if noise:
        _check_generator(generator, dev)
        z = torch.empty((*cfg.rd_shape, 2), dtype=torch.float32, device=dev)
        z.normal_(generator=generator)                               # real and imaginary parts
        scale = torch.as_tensor(np.sqrt(noise_profile_rd(cfg) / 2.0), dtype=torch.float32, device=dev)
        z.mul_(scale[:, None, None, None])
        rd.add_(torch.view_as_complex(z))
        skirts = _skirts_rd(cfg, rng, chan, generator)
        if skirts is not None:
            rd.add_(skirts)
    return rd
