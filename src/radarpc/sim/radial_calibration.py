"""The calibration table of a simulated RADIal-like radar unit, as a chamber measurement gives it.

The unit's TRUE array response ``A(theta)`` (:func:`radarpc.sensors.radial.steering_vectors`:
element pattern, geometry, mutual coupling, per-channel gain/phase errors) is what the simulator
synthesises cubes with. The table is a MEASUREMENT of it, with the residual errors a real one has:

.. math::

    M_v(\\theta_i) = D_v\\, A_v(\\theta_i + \\delta_i) + n_{i,v}

* positioner error ``delta_i``: per grid point, uniform in ``+-cfg.cal_positioner_deg`` (az, el);
* drift ``D_v = d_{tx,m} d_{rx,r}`` of the RF chains between the measurement and the drive
  (temperature), each ``10^(gamma/20) exp(j psi)`` with ``gamma`` uniform in ``+-cal_drift[0]`` dB
  and ``psi`` uniform in ``+-cal_drift[1]`` degrees;
* chamber noise ``n``: circular complex Gaussian, ``E|n|^2 = sigma^2 = 10^(-cal_snr_db / 10)``
  (SNR per channel at boresight, where ``|A_v|`` is about 1).

All drawn from ``numpy.random.default_rng([cfg.hardware_seed, 7])``: deterministic, a property of
the unit. The stored weights are ``Signal[az, :, el] = conj(M) / rms_v|M|``: each direction is
normalised to unit RMS over the channels, which removes the element pattern (a common factor of a
direction) and keeps the matched-filter spectrum ``|Signal @ (H * v)|`` unbiased in angle, with
RADIal's Hamming channel taper ``H``. Stored with :func:`radarpc.data.radial_format.save_calibration`.

Residual-error bound (:func:`calibration_error_bound`): for every grid point and channel ``v = m
n_rx + r``,

.. math::

    |M_v - A_v(\\theta)| \\le \\beta_D\\, t_m r_r + \\delta_{az} B_{az,v} + \\delta_{el} B_{el,v} + 5 \\sigma

from ``|D A(theta + delta) - A(theta)| <= |D - 1| |A(theta + delta)| + |A(theta + delta) - A(theta)|``
and the mean-value theorem, with ``t_m = sum_m' |T[m, m']|``, ``r_r = sum_r' |R[r, r']|`` (rows of
the hardware matrices of :func:`radarpc.sensors.radial.array_factors`, ``|A_v| <= t_m r_r`` since
the pattern is <= 1), ``beta_D = (10^(2 gamma_max / 20) - 1) + 10^(2 gamma_max / 20) 2 psi_max``
(``|g e^{j psi} - 1| <= |g - 1| + g |psi|`` for the product of two chains),

.. math::

    B_{az,v} = f'_{az} t_m r_r + \\pi (\\tilde t_{h,m} r_r + t_m \\tilde r_{h,r}),\\quad
    B_{el,v} = f'_{el} t_m r_r + \\pi (\\tilde t_{hv,m} r_r + t_m \\tilde r_{hv,r})

(``tilde t_{h,m} = sum_m' |T[m, m']| |p_{h,m'}|``, ``hv`` with ``|p_h| + |p_v|``, since
``|du_y/daz|, |du_y/del|, |du_z/del| <= 1``; ``f'`` the largest slope of the pattern
``cos(x)^q``: ``sqrt(q) ((q - 1) / q)^((q - 1) / 2)`` for ``q >= 1``), angles in radians. The
noise term holds per entry with probability ``1 - exp(-25)``.
"""
from __future__ import annotations

import math

import numpy as np

from radarpc.sensors.radial import Calibration, DDMARadarConfig, array_factors, steering_vectors

__all__ = ["measure_array_response", "calibration_error_bound", "make_calibration"]


def _channel_taper(cfg: DDMARadarConfig) -> np.ndarray:
    # Hamming taper on the horizontal virtual position: sidelobe control for azimuth.
    h = cfg.virtual_positions[:, 0]
    span = h.max() - h.min()
    t = (h - h.min()) / span if span > 0 else np.zeros_like(h)
    return (0.54 - 0.46 * np.cos(2 * np.pi * t)).astype(np.float32)


def measure_array_response(cfg: DDMARadarConfig) -> np.ndarray:
    """The chamber measurement ``M`` of the unit's array response on the calibration grid.

    Returns
    -------
    numpy.ndarray
        complex128 ``(n_az, n_el, n_virtual)`` on ``cfg.azimuth_table_deg x cfg.elevation_table_deg``
        (model and parameters in the module docstring).
    """
    az = cfg.azimuth_table_deg
    el = cfg.elevation_table_deg
    rng = np.random.default_rng([cfg.hardware_seed, 7])
    shape = (len(az), len(el))
    d_az = rng.uniform(-1.0, 1.0, shape) * cfg.cal_positioner_deg[0]
    d_el = rng.uniform(-1.0, 1.0, shape) * cfg.cal_positioner_deg[1]
    truth = steering_vectors(cfg, az[:, None] + d_az, el[None, :] + d_el)     # (n_az, n_el, V)

    def chain(n):
        gain = 10 ** (rng.uniform(-1.0, 1.0, n) * cfg.cal_drift[0] / 20)
        return gain * np.exp(1j * np.deg2rad(rng.uniform(-1.0, 1.0, n) * cfg.cal_drift[1]))
    drift = (chain(cfg.n_tx)[:, None] * chain(cfg.n_rx)[None, :]).reshape(-1)  # (V,)
    sigma = 10 ** (-cfg.cal_snr_db / 20)
    noise = rng.standard_normal((*shape, cfg.n_virtual, 2)) @ np.array([1.0, 1j]) * (sigma / math.sqrt(2))
    return truth * drift + noise


def _slope(q: float, max_deg: float) -> float:
    # largest |d/dx cos(x)^q| for |x| <= max_deg
    if q == 0:
        return 0.0
    if q >= 1:
        return math.sqrt(q) * ((q - 1) / q) ** ((q - 1) / 2)
    return q * math.tan(math.radians(min(max_deg, 89.9)))


def calibration_error_bound(cfg: DDMARadarConfig) -> np.ndarray:
    """Per-channel bound on ``|M_v(theta) - A_v(theta)|`` over the whole grid, ``(n_virtual,)``.

    Derived in the module docstring from ``cal_positioner_deg``, ``cal_drift``, ``cal_snr_db``, the
    element pattern, the element positions and the hardware matrices; the noise term is 5 sigma.
    """
    t, r = array_factors(cfg)
    pt = np.abs(np.asarray(cfg.tx_pos, dtype=np.float64))
    pr = np.abs(np.asarray(cfg.rx_pos, dtype=np.float64))
    tm, rr = np.abs(t).sum(1), np.abs(r).sum(1)                              # (n_tx,), (n_rx,)
    th, rh = np.abs(t) @ pt[:, 0], np.abs(r) @ pr[:, 0]
    thv, rhv = np.abs(t) @ pt.sum(1), np.abs(r) @ pr.sum(1)
    amp = np.outer(tm, rr)                                                   # bound on |A_v|
    g = 10 ** (2 * cfg.cal_drift[0] / 20)
    beta = (g - 1) + g * 2 * math.radians(cfg.cal_drift[1])
    max_az = max(abs(cfg.az_grid_deg[0]), abs(cfg.az_grid_deg[1])) + cfg.cal_positioner_deg[0]
    max_el = max(abs(cfg.el_grid_deg[0]), abs(cfg.el_grid_deg[1])) + cfg.cal_positioner_deg[1]
    b_az = _slope(cfg.element_q_az, max_az) * amp + math.pi * (np.outer(th, rr) + np.outer(tm, rh))
    b_el = _slope(cfg.element_q_el, max_el) * amp + math.pi * (np.outer(thv, rr) + np.outer(tm, rhv))
    sigma = 10 ** (-cfg.cal_snr_db / 20)
    bound = (beta * amp + math.radians(cfg.cal_positioner_deg[0]) * b_az
             + math.radians(cfg.cal_positioner_deg[1]) * b_el + 5 * sigma)
    return bound.reshape(-1)


def make_calibration(cfg: DDMARadarConfig) -> Calibration:
    """The calibration table of ``cfg``'s radar unit: the normalised conjugate of the measurement.

    ``Signal[az, :, el] = conj(M) / rms_v|M|`` with ``M`` from :func:`measure_array_response`, on
    the grid ``cfg.az_grid_deg x cfg.el_grid_deg``; ``H`` a Hamming taper over the horizontal
    virtual positions.
    """
    m = measure_array_response(cfg)                                          # (n_az, n_el, V)
    rms = np.sqrt((np.abs(m) ** 2).mean(-1, keepdims=True))
    signal = np.conj(m / rms).transpose(0, 2, 1).astype(np.complex64)        # (n_az, V, n_el)
    return Calibration(signal=signal, window=_channel_taper(cfg),
                       azimuth_deg=cfg.azimuth_table_deg.astype(np.float32),
                       elevation_deg=cfg.elevation_table_deg.astype(np.float32))
