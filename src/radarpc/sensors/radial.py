"""RADIal-like DDMA MIMO radar: sensor configs, virtual array, calibration table.

Conventions (shared by the simulator, the DSP and the readers, and equal to those of RADIal's
own processing, so that a real ``CalibrationTable`` and real cubes work unchanged):

* Frame: x forward, y left, z up (metres). Azimuth ``a`` is measured from +x towards +y (left is
  positive), elevation ``e`` from the x-y plane towards +z. A direction is the unit vector
  ``u = (cos e cos a, cos e sin a, sin e)``.
* RD cube: complex ``(n_range, n_doppler, n_rx)``; range of bin ``i`` is ``i * range_res_m``;
  Doppler bin ``d`` (no fftshift) has radial velocity ``((d + n_doppler/2) mod n_doppler -
  n_doppler/2) * velocity_res_mps``, positive for a receding target.
* DDMA: the Doppler axis holds ``n_slots`` slots of ``slot_width = n_doppler / n_slots`` bins.
  Tx ``m`` is phase-coded so that a target of true Doppler bin ``d0`` appears for that Tx at bin
  ``(d0 + tx_slots[m] * slot_width) mod n_doppler``. Tx 0 sits in slot 0, the next
  ``n_empty_slots`` slots are empty and the other Tx fill the rest (RADIal: slot 0 and 5..15).
  The consolidated Doppler index is ``d mod slot_width``.
* Virtual channel index ``v = tx * n_rx + rx``. Element positions are given in half wavelengths
  in the array plane (horizontal = +y direction, vertical = +z); the geometric response of
  direction ``u`` at virtual element ``p = p_tx + p_rx`` is ``exp(-j * pi * (p_h * u_y + p_v *
  u_z))``. The minus sign is the physics of the IF convention ``IF = tx * conj(rx)`` that gives
  positive range bins and receding-positive Doppler: an element nearer the target sees a shorter
  delay, hence a smaller phase ``2 pi f_c tau`` (derivation in :mod:`radarpc.sim.adc`).
* True array response (what the simulator synthesises with, :func:`steering_vectors`): the
  element pattern :func:`element_gain` (``cos^1.5(az) cos^20(el)`` one way) times the geometric
  response mixed by the mutual coupling of the Tx and of the Rx elements
  (:func:`coupling_matrix`, -22 dB between neighbouring Rx) and the per-chain gain/phase errors
  (:func:`channel_errors`), all fixed by ``hardware_seed``: unknown to the user, who only has the
  calibration table.
* Calibration table (RADIal's ``CalibrationTable.npy`` content, stored by radarpc as
  ``calibration.npz``, read and written by :mod:`radarpc.data.radial_format`, simulated for a
  unit by :func:`radarpc.sim.radial_calibration.make_calibration` as a chamber measurement with
  noise, positioner error and drift): ``Signal`` ``(n_az, n_virtual, n_el)`` complex beamforming
  weights, the conjugate of the measured array response (normalised per direction); ``H``
  ``(1, n_virtual)`` channel taper; ``Azimuth_table`` ``(n_az,)`` and ``Elevation_table``
  ``(n_el,)`` in degrees. The angle spectrum of a virtual snapshot ``v`` is ``|Signal[az, :, el]
  @ (H * v)|``. Grids: ``radial`` and ``radial-s`` have RADIal's real size, 751 azimuths at 0.2
  deg over +-75 deg x 11 elevations at 3 deg over +-15 deg (index 5 = 0 deg, the one RADIal's
  ``rpl.py`` reads for RA maps); ``tiny`` 61 azimuths at 2 deg x 5 elevations at 10 deg.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = [
    "SPEED_OF_LIGHT",
    "DDMARadarConfig",
    "Calibration",
    "RADIAL",
    "RADIAL_S",
    "TINY",
    "RADIAL_SENSORS",
    "radial_sensor",
    "ideal_receiver",
    "element_gain",
    "coupling_matrix",
    "channel_errors",
    "array_factors",
    "steering_vectors",
]

SPEED_OF_LIGHT = 299_792_458.0
BOLTZMANN = 1.380649e-23


def _radial_tx_positions() -> tuple[tuple[float, float], ...]:
    # 9 Tx on the horizontal line, 8 half-wavelengths apart (the 16-element Rx line fills the
    # gaps twice over: an 84-element horizontal virtual aperture with 2x redundancy), then three
    # Tx raised by 1, 2 and 3 half-wavelengths whose virtual elements overlap the horizontal ones,
    # so that elevation is measurable.
    horizontal = tuple((8.0 * k, 0.0) for k in range(9))
    raised = ((4.0, 1.0), (36.0, 2.0), (68.0, 3.0))
    return horizontal + raised


@dataclass(frozen=True)
class DDMARadarConfig:
    """A DDMA FMCW MIMO radar whose frames are range-Doppler cubes (RADIal's radar and variants).

    Every stage (simulator, DSP, models) takes its sizes from this object, never from constants.

    Amplitude scale: RD cells are in units where the thermal noise has standard deviation
    ``adc_full_scale`` per complex cell before the IF filter (``noise_power_rd``); for ``radial``
    that is ``2000 / sqrt(sum w_r^2 sum w_d^2) = 13.9`` ADC counts per complex sample through
    the unnormalised windowed FFTs -- a few counts of thermal noise above the quantisation step, as
    a receiver is set up -- and puts the per-channel real/imaginary std of full-size cubes of
    default simulated scenes in the range of the real RADIal cubes (FFTRadNet's ``input_std``
    14.5k..36.7k, mean ~0). The std is dominated by the strongest near returns, so it scales with
    the scene mix; it scales linearly with ``adc_full_scale``.

    Receiver (:mod:`radarpc.sim.rd`, equations there), beat frequency ``f = i f_s / n_range`` of
    range bin ``i`` (``f_s`` = :attr:`sample_rate_hz`):

    * IF filter ``|H(f)|^2 = x / (1 + x) / (1 + y)``, ``x = (f / if_highpass_hz)^(2
      if_highpass_order)``, ``y = (f / (aa_cutoff f_s))^(2 aa_order)``: a Butterworth high-pass
      (150 kHz, order 2 on ``radial``: -3 dB at range bin 6 = 1.2 m, 40 dB/decade below) and a
      Butterworth anti-alias low-pass (0.8 f_s, order 8: -3 dB at bin 410 = 82 m, -15.5 dB at the
      last bin). Applied to every scatterer at its beat frequency and to the thermal noise per
      range bin; the ADC adds a white floor ``adc_floor_db`` (-15 dB) after it, so the noise of the
      last rows is 12 dB below mid-range.
    * Tx leakage: every Tx couples into every Rx through a path of equivalent range
      ``leakage_range_m``; static, so it sits at range ~0 and zero relative Doppler, i.e. at each
      Tx's DDMA offset; on-bin peak ``leakage_db`` (40 dB) above the thermal noise per cell, times a
      per-channel log-normal (3 dB) magnitude and random phase fixed by ``hardware_seed``.
    * Phase noise ``L(f) = pn_dbc_hz / (1 + (f / pn_corner_hz)^2) + pn_floor_dbc_hz`` (-85 dBc/Hz
      inside a 1 MHz loop bandwidth): skirts along range around strong targets, range-correlated
      (``4 L(f) sin^2(pi f tau)``), white over Doppler.

    ``0`` / ``None`` switches one off (:func:`ideal_receiver` switches all off; ``tiny`` has none).
    """

    name: str
    n_range: int = 512                      # range bins (complex ADC samples per chirp)
    range_res_m: float = 0.201171875        # metres per range bin
    n_doppler: int = 256                    # Doppler bins (chirps per frame)
    n_tx: int = 12                          # transmitters, all active at once (DDMA)
    n_rx: int = 16                          # receivers
    n_slots: int = 16                       # DDMA Doppler slots
    tx_slots: tuple[int, ...] = (0,) + tuple(range(5, 16))  # slot of each Tx
    carrier_hz: float = 77e9                # carrier frequency
    chirp_period_s: float = 50e-6           # chirp repetition interval
    ramp_fraction: float = 0.8              # sampled part of the chirp period
    tx_pos: tuple[tuple[float, float], ...] = field(default_factory=_radial_tx_positions)
    rx_pos: tuple[tuple[float, float], ...] = tuple((float(k), 0.0) for k in range(16))
    az_grid_deg: tuple[float, float, int] = (-75.0, 75.0, 751)   # calibration azimuths (start, stop, n): 0.2 deg
    el_grid_deg: tuple[float, float, int] = (-15.0, 15.0, 11)    # calibration elevations: 3 deg, index 5 = 0 deg
    tx_power_dbm: float = 12.0              # per Tx
    antenna_gain_dbi: float = 12.0          # Tx and Rx element gain at boresight
    element_q_az: float = 1.5               # element power pattern cos(az)^q_az (one way)
    element_q_el: float = 20.0              # ... times cos(el)^q_el (series-fed patch column: narrow in elevation)
    noise_figure_db: float = 12.0           # receiver noise figure
    system_loss_db: float = 3.0             # feeds, window losses not in the FFT gain
    adc_full_scale: float = 2000.0          # thermal-noise std per RD cell in RD units (sets the RD scale)
    gain_error_db: float = 0.5              # std of per-Tx and per-Rx gain errors of the hardware
    phase_error_deg: float = 6.0            # std of per-Tx and per-Rx phase errors of the hardware
    coupling_db: float = -22.0              # mutual coupling of two elements one half wavelength apart
    coupling_reach: float = 9.0             # coupling is neglected beyond this distance (half wavelengths)
    hardware_seed: int = 1234               # seeds the hardware errors (a property of the unit)
    # chamber measurement that produced the calibration table (radarpc.sim.radial_calibration)
    cal_snr_db: float = 40.0                # measurement SNR per channel at boresight
    cal_positioner_deg: tuple[float, float] = (0.02, 0.05)   # max positioner error (az, el), uniform
    cal_drift: tuple[float, float] = (0.1, 1.0)   # max per-channel gain (dB) / phase (deg) drift since, uniform
    # receiver (radarpc.sim.rd): IF filter, Tx leakage, phase noise; 0 / None switches one off
    if_highpass_hz: float = 150e3           # IF high-pass corner (Butterworth)
    if_highpass_order: int = 2
    aa_cutoff: float = 0.8                  # anti-alias low-pass corner as a fraction of the sample rate
    aa_order: int = 8
    adc_floor_db: float | None = -15.0      # ADC noise floor after the filter, re passband thermal noise
    leakage_db: float | None = 40.0         # Tx->Rx leakage peak per RD cell re thermal noise (on-bin)
    leakage_range_m: float = 0.1            # leakage path as an equivalent target range (delay 2 R_L / c)
    pn_dbc_hz: float | None = -85.0         # LO phase noise L(f) inside the loop bandwidth, dBc/Hz
    pn_corner_hz: float = 1e6               # PLL loop bandwidth: L falls 20 dB/decade beyond
    pn_floor_dbc_hz: float = -140.0         # far-out phase-noise floor

    def __post_init__(self) -> None:
        def bad(msg: str) -> None:
            raise ValueError(f"sensor {self.name!r}: {msg}")

        for k in ("n_range", "n_doppler", "n_tx", "n_rx", "n_slots"):
            if int(getattr(self, k)) <= 0:
                bad(f"{k} must be positive, got {getattr(self, k)}")
        if self.n_doppler % self.n_slots:
            bad(f"n_doppler={self.n_doppler} must be a multiple of n_slots={self.n_slots}")
        if len(self.tx_slots) != self.n_tx:
            bad(f"tx_slots has {len(self.tx_slots)} entries for n_tx={self.n_tx}")
        expected = (0,) + tuple(range(self.n_slots - self.n_tx + 1, self.n_slots))
        if tuple(self.tx_slots) != expected:
            bad(f"tx_slots must be Tx 0 in slot 0, then {self.n_slots - self.n_tx} empty slots, "
                f"then the other Tx: expected {expected}, got {tuple(self.tx_slots)}")
        if self.n_slots - self.n_tx < 1:
            bad("DDMA needs at least one empty slot to resolve the Doppler hypothesis")
        if len(self.tx_pos) != self.n_tx or len(self.rx_pos) != self.n_rx:
            bad(f"tx_pos/rx_pos must have n_tx={self.n_tx}/n_rx={self.n_rx} entries")
        for nm in ("az_grid_deg", "el_grid_deg"):
            lo, hi, n = getattr(self, nm)
            if int(n) < 1 or (int(n) > 1 and not hi > lo):
                bad(f"{nm}={getattr(self, nm)} must be (start, stop, n) with stop > start")
        for k in ("element_q_az", "element_q_el", "coupling_reach", "if_highpass_hz", "aa_cutoff",
                  "leakage_range_m", "pn_corner_hz"):
            if not float(getattr(self, k)) >= 0:
                bad(f"{k} must be >= 0, got {getattr(self, k)}")
        for k in ("if_highpass_order", "aa_order"):
            if int(getattr(self, k)) < 0 or int(getattr(self, k)) != getattr(self, k):
                bad(f"{k} must be an integer >= 0, got {getattr(self, k)}")
        if self.aa_order and not self.aa_cutoff > 0:
            bad(f"aa_cutoff must be > 0 with aa_order={self.aa_order}, got {self.aa_cutoff}")
        if self.leakage_db is not None and not self.leakage_range_m > 0:
            bad(f"leakage_range_m must be > 0 with leakage on, got {self.leakage_range_m}")
        if len(self.cal_positioner_deg) != 2 or len(self.cal_drift) != 2 or \
                min(*self.cal_positioner_deg, *self.cal_drift) < 0:
            bad(f"cal_positioner_deg={self.cal_positioner_deg} and cal_drift={self.cal_drift} must be "
                "pairs of non-negative numbers")

    # ---- derived quantities -------------------------------------------------------------------
    @property
    def wavelength_m(self) -> float:
        return SPEED_OF_LIGHT / self.carrier_hz

    @property
    def bandwidth_hz(self) -> float:
        """Swept bandwidth: range resolution ``c / (2 B)`` equals one range bin."""
        return SPEED_OF_LIGHT / (2.0 * self.range_res_m)

    @property
    def sample_rate_hz(self) -> float:
        """Complex ADC sample rate: ``n_range`` samples over the sampled ramp."""
        return self.n_range / (self.ramp_fraction * self.chirp_period_s)

    @property
    def chirp_slope_hz_per_s(self) -> float:
        return self.bandwidth_hz / (self.ramp_fraction * self.chirp_period_s)

    @property
    def max_range_m(self) -> float:
        """Unambiguous (instrumented) range ``n_range * range_res_m``."""
        return self.n_range * self.range_res_m

    @property
    def velocity_res_mps(self) -> float:
        """Doppler bin width in radial velocity: ``lambda / (2 * n_doppler * T_c)``."""
        return self.wavelength_m / (2.0 * self.n_doppler * self.chirp_period_s)

    @property
    def max_velocity_mps(self) -> float:
        """Unambiguous radial velocity: velocities wrap outside ``[-v_max, v_max)``."""
        return self.velocity_res_mps * self.n_doppler / 2

    @property
    def slot_width(self) -> int:
        """Bins per DDMA slot = length of the consolidated Doppler axis."""
        return self.n_doppler // self.n_slots

    @property
    def n_empty_slots(self) -> int:
        return self.n_slots - self.n_tx

    @property
    def n_virtual(self) -> int:
        return self.n_tx * self.n_rx

    @property
    def doppler_offsets(self) -> np.ndarray:
        """Doppler-bin offset of each Tx, ``tx_slots * slot_width``, shape ``(n_tx,)``."""
        return np.asarray(self.tx_slots, dtype=np.int64) * self.slot_width

    @property
    def virtual_positions(self) -> np.ndarray:
        """Virtual element positions in half wavelengths, ``(n_virtual, 2)`` (horizontal, vertical),
        row ``tx * n_rx + rx``."""
        tx = np.asarray(self.tx_pos, dtype=np.float64)
        rx = np.asarray(self.rx_pos, dtype=np.float64)
        return (tx[:, None, :] + rx[None, :, :]).reshape(-1, 2)

    @property
    def azimuth_table_deg(self) -> np.ndarray:
        lo, hi, n = self.az_grid_deg
        return np.linspace(lo, hi, int(n))

    @property
    def elevation_table_deg(self) -> np.ndarray:
        lo, hi, n = self.el_grid_deg
        return np.linspace(lo, hi, int(n))

    @property
    def rd_shape(self) -> tuple[int, int, int]:
        return (self.n_range, self.n_doppler, self.n_rx)

    def range_of_bin(self, i):
        """Range in metres of (possibly fractional) range bin ``i``."""
        return i * self.range_res_m

    def velocity_of_bin(self, d):
        """Signed radial velocity (m/s, receding positive) of full-axis Doppler bin ``d``."""
        half = self.n_doppler // 2
        return ((np.asarray(d) + half) % self.n_doppler - half) * self.velocity_res_mps

    def doppler_bin_of_velocity(self, v_mps):
        """Fractional full-axis Doppler bin in ``[0, n_doppler)`` of radial velocity ``v_mps``."""
        return np.mod(np.asarray(v_mps, dtype=np.float64) / self.velocity_res_mps, self.n_doppler)

    def noise_power_w(self) -> float:
        """Thermal noise power per complex ADC sample: ``k T0 F f_s``."""
        return BOLTZMANN * 290.0 * 10 ** (self.noise_figure_db / 10) * self.sample_rate_hz

    def snr_per_sample(self, range_m, rcs_m2):
        """Radar equation: SNR of one target in one ADC sample of one virtual channel (linear).

        ``P_r = P_t G^2 lambda^2 sigma / ((4 pi)^3 R^4 L)``, over :meth:`noise_power_w`.
        The range and Doppler FFTs add the coherent gain ``n_range * n_doppler`` on top.
        """
        pt = 10 ** ((self.tx_power_dbm - 30) / 10)
        g = 10 ** (self.antenna_gain_dbi / 10)
        loss = 10 ** (self.system_loss_db / 10)
        r = np.maximum(np.asarray(range_m, dtype=np.float64), 0.1)
        pr = pt * g * g * self.wavelength_m ** 2 * np.asarray(rcs_m2) / ((4 * math.pi) ** 3 * r ** 4 * loss)
        return pr / self.noise_power_w()

    def to_dict(self) -> dict:
        """Plain JSON/YAML-able dict (tuples as lists); :meth:`from_dict` inverts it."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DDMARadarConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown sensor config keys: {sorted(unknown)}")
        kw = {}
        for k, v in d.items():
            if isinstance(v, list):
                v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
            kw[k] = v
        return cls(**kw)


RADIAL = DDMARadarConfig(name="radial")
"""Full-size RADIal radar: 512 range x 256 Doppler x 16 Rx, 12 Tx DDMA, 192 virtual channels;
calibration table of RADIal's real size (751 azimuths at 0.2 deg over +-75 deg x 11 elevations)."""

RADIAL_S = dataclasses.replace(
    RADIAL, name="radial-s", n_range=128, range_res_m=4 * 0.201171875, n_doppler=64,
    if_highpass_hz=RADIAL.if_highpass_hz / 4,
)
"""Reduced RADIal: the same 12 x 16 DDMA array, field of view and calibration grid (751 azimuths
at 0.2 deg x 11 elevations: the azimuth quantisation stays finer than the label tolerance), 128
range x 64 Doppler bins. A quarter of the bandwidth means a quarter of the beat frequency per metre,
so the IF high-pass corner is a quarter too: every receiver effect sits at the same range in metres
as on ``radial``."""

TINY = DDMARadarConfig(
    name="tiny",
    n_range=64,
    range_res_m=0.4,
    n_doppler=32,
    n_tx=2,
    n_rx=4,
    n_slots=4,
    tx_slots=(0, 3),
    tx_pos=((0.0, 0.0), (4.0, 1.0)),
    rx_pos=tuple((float(k), 0.0) for k in range(4)),
    az_grid_deg=(-60.0, 60.0, 61),
    el_grid_deg=(-20.0, 20.0, 5),
    if_highpass_hz=0.0,
    aa_order=0,
    adc_floor_db=None,
    leakage_db=None,
    pn_dbc_hz=None,
)
"""Tiny 2 Tx x 4 Rx DDMA radar with a 64 x 32 cube, for fast tests: coarse calibration grid (2 deg
x 10 deg), the element pattern, coupling and measured calibration of the big ones, but an ideal
receiver (no IF filter, ADC floor, leakage or phase noise; tests switch them on with
``dataclasses.replace``)."""

RADIAL_SENSORS: dict[str, DDMARadarConfig] = {"radial": RADIAL, "radial-s": RADIAL_S, "tiny": TINY}


def ideal_receiver(cfg: DDMARadarConfig) -> DDMARadarConfig:
    """``cfg`` without IF filter, ADC floor, Tx leakage and phase noise (array and hardware kept)."""
    return dataclasses.replace(cfg, if_highpass_hz=0.0, aa_order=0, adc_floor_db=None, leakage_db=None,
                               pn_dbc_hz=None)


def radial_sensor(name: str) -> DDMARadarConfig:
    """The DDMA sensor config called ``name`` (one of ``RADIAL_SENSORS``)."""
    try:
        return RADIAL_SENSORS[name]
    except KeyError:
        raise ValueError(f"unknown sensor {name!r}; expected one of {sorted(RADIAL_SENSORS)}") from None


# ---- array response and calibration ----------------------------------------------------------
def element_gain(cfg: DDMARadarConfig, az_deg, el_deg) -> np.ndarray:
    """One-way power gain of a Tx or Rx element relative to boresight, ``G(az, el) / G0``.

    ``G / G0 = cos(az)^q_az * cos(el)^q_el`` (zero beyond 90 deg): a patch column, wide in azimuth,
    narrow in elevation. With the defaults (q_az = 1.5, q_el = 20) it falls one way by 4.5 dB at
    60 deg, 7.0 dB at 70 deg and 8.8 dB at 75 deg azimuth (two way: 9.0, 14.0, 17.6 dB), and by
    1.3 dB at 10 deg elevation. Every element has the same pattern, so in the array response it is
    the common amplitude ``sqrt(G_tx G_rx) / G0 = G / G0`` of a direction.
    """
    a = np.deg2rad(np.asarray(az_deg, dtype=np.float64))
    e = np.deg2rad(np.asarray(el_deg, dtype=np.float64))
    return (np.clip(np.cos(a), 0.0, None) ** cfg.element_q_az) * (np.clip(np.cos(e), 0.0, None) ** cfg.element_q_el)


def coupling_matrix(cfg: DDMARadarConfig, positions) -> np.ndarray:
    """Mutual-coupling matrix of elements at ``positions`` (half wavelengths), ``(n, n)`` complex.

    ``C = I + K`` with ``K[i, j] = kappa / d_ij^2 * exp(-j pi d_ij)`` for ``0 < d_ij <= coupling_reach``
    (``kappa = 10^(coupling_db / 20)``, ``d_ij`` the distance in half wavelengths, the phase that of
    the path between the two elements), else 0. Element ``i`` radiates/receives ``sum_j C[i, j]``
    times what element ``j`` alone would: RADIal's Rx line (one half wavelength apart) couples at
    -22 dB to its neighbours and -34 dB to the next; its Tx (>= 4 half wavelengths apart) at
    <= -46 dB.
    """
    p = np.asarray(positions, dtype=np.float64)
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    kappa = 10 ** (cfg.coupling_db / 20)
    near = (d > 0) & (d <= cfg.coupling_reach)
    k = np.where(near, kappa / np.where(near, d, 1.0) ** 2 * np.exp(-1j * np.pi * d), 0.0)
    return np.eye(len(p), dtype=np.complex128) + k


def _tx_rx_errors(cfg: DDMARadarConfig) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(cfg.hardware_seed)
    def draw(n):
        g = 10 ** (rng.normal(0.0, cfg.gain_error_db, n) / 20)
        ph = np.deg2rad(rng.normal(0.0, cfg.phase_error_deg, n))
        return g * np.exp(1j * ph)
    tx, rx = draw(cfg.n_tx), draw(cfg.n_rx)
    tx[0] = 1.0  # reference channel
    rx[0] = 1.0
    return tx, rx


def channel_errors(cfg: DDMARadarConfig) -> np.ndarray:
    """Per-virtual-channel complex gain of the RF chains, ``(n_virtual,)`` complex128.

    Product of a per-Tx and a per-Rx error (log-normal gain, Gaussian phase) drawn from
    ``cfg.hardware_seed``: a fixed property of the radar unit that the calibration measures.
    """
    tx, rx = _tx_rx_errors(cfg)
    return (tx[:, None] * rx[None, :]).reshape(-1)


def array_factors(cfg: DDMARadarConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(T, R)``: the Tx and Rx hardware matrices of the true response, ``(n_tx, n_tx)``, ``(n_rx, n_rx)``.

    ``T = diag(g_tx) C_tx`` and ``R = diag(g_rx) C_rx``: mutual coupling at the antennas
    (:func:`coupling_matrix`), then the gain/phase error of each RF chain (:func:`channel_errors`).
    """
    tx, rx = _tx_rx_errors(cfg)
    return tx[:, None] * coupling_matrix(cfg, cfg.tx_pos), rx[:, None] * coupling_matrix(cfg, cfg.rx_pos)


def steering_vectors(cfg: DDMARadarConfig, az_deg, el_deg, *, hardware: bool = True) -> np.ndarray:
    """Array response of the virtual array towards ``(az_deg, el_deg)``.

    Parameters
    ----------
    cfg : DDMARadarConfig
    az_deg, el_deg : array_like
        Broadcastable azimuth and elevation in degrees.
    hardware : bool
        ``True`` (default): the TRUE response of the unit, what the antennas really deliver,

        .. math::

            A_{m n_{rx} + r}(u) = \\frac{G(u)}{G_0}\\, \\big(T\\, e_{tx}(u)\\big)_m \\big(R\\, e_{rx}(u)\\big)_r,
            \\qquad e_{tx}(u)_{m'} = e^{-j \\pi\\, p_{tx,m'} \\cdot u},\\ e_{rx}(u)_{r'} = e^{-j \\pi\\, p_{rx,r'} \\cdot u}

        with the element pattern :func:`element_gain` and the hardware matrices
        :func:`array_factors` (coupling, then per-channel gain/phase errors). ``False``: the ideal
        geometric response ``exp(-j pi (p_h u_y + p_v u_z))`` (unit modulus).

    Returns
    -------
    numpy.ndarray
        Complex128 of shape ``broadcast(az, el).shape + (n_virtual,)``. IF = tx * conj(rx); an
        element nearer the target has the shorter delay, so a target on the left, +y, is
        beamformed at positive azimuth.
    """
    a = np.deg2rad(np.asarray(az_deg, dtype=np.float64))
    e = np.deg2rad(np.asarray(el_deg, dtype=np.float64))
    a, e = np.broadcast_arrays(a, e)
    u = np.stack([np.cos(e) * np.sin(a), np.sin(e)], axis=-1)               # (..., 2) = (u_y, u_z)
    pt = np.asarray(cfg.tx_pos, dtype=np.float64)
    pr = np.asarray(cfg.rx_pos, dtype=np.float64)
    et = np.exp(-1j * np.pi * (u @ pt.T))                                    # (..., n_tx)
    er = np.exp(-1j * np.pi * (u @ pr.T))                                    # (..., n_rx)
    if hardware:
        t, r = array_factors(cfg)
        et = et @ t.T
        er = er @ r.T * element_gain(cfg, np.rad2deg(a), np.rad2deg(e))[..., None]
    return (et[..., :, None] * er[..., None, :]).reshape(*a.shape, cfg.n_virtual)


@dataclass(frozen=True)
class Calibration:
    """Calibrated beamforming dictionary, with RADIal's ``CalibrationTable`` content.

    Attributes
    ----------
    signal : ndarray, complex64, ``(n_az, n_virtual, n_el)``
        Beamforming weights (conjugate measured array response), RADIal's ``Signal``.
    window : ndarray, float32, ``(n_virtual,)``
        Channel taper, RADIal's ``H[0]``.
    azimuth_deg : ndarray, ``(n_az,)``
    elevation_deg : ndarray, ``(n_el,)``
    """

    signal: np.ndarray
    window: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray

    def __post_init__(self) -> None:
        s = self.signal
        if s.ndim != 3 or s.shape[0] != len(self.azimuth_deg) or s.shape[2] != len(self.elevation_deg):
            raise ValueError(
                f"calibration Signal must be (n_az={len(self.azimuth_deg)}, n_virtual, "
                f"n_el={len(self.elevation_deg)}), got {s.shape}")
        if self.window.shape != (s.shape[1],):
            raise ValueError(f"calibration window H must have {s.shape[1]} taps, got {self.window.shape}")

    @property
    def n_virtual(self) -> int:
        return self.signal.shape[1]

    @property
    def grid_shape(self) -> tuple[int, int]:
        """``(n_az, n_el)``: the angle spectrum of a snapshot reshapes to this."""
        return self.signal.shape[0], self.signal.shape[2]

    def dictionary(self, device: torch.device | str | None = None,
                   dtype: torch.dtype = torch.complex64) -> torch.Tensor:
        """The dictionary ``B`` with the taper folded in: ``(n_az * n_el, n_virtual)``.

        Row ``k = az * n_el + el`` (RADIal's ordering), so ``|B @ v|`` is the angle spectrum of
        the raw snapshot ``v`` and ``k // n_el, k % n_el`` index the tables.
        """
        b = np.moveaxis(self.signal, 2, 1).reshape(-1, self.n_virtual) * self.window[None, :]
        return torch.as_tensor(b, device=device).to(dtype)

    def check_sensor(self, cfg: DDMARadarConfig, source: str | os.PathLike = "calibration") -> None:
        """Raise if this table does not fit ``cfg``'s virtual array."""
        if self.n_virtual != cfg.n_virtual:
            raise ValueError(
                f"{source}: calibration has {self.n_virtual} virtual channels, sensor {cfg.name!r} "
                f"has {cfg.n_virtual} (n_tx * n_rx)")
