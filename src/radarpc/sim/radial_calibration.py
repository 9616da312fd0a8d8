"""The calibration table of a simulated RADIal-like radar unit, as a chamber measurement gives it.

``Signal[az, :, el] = conj(a(az, el))`` with ``a`` the unit's true array response
(:func:`radarpc.sensors.radial.steering_vectors`, hardware errors included) on the sensor's angle
tables, and RADIal's Hamming channel taper ``H``. Stored with
:func:`radarpc.data.radial_format.save_calibration`.
"""
from __future__ import annotations

import numpy as np

from radarpc.sensors.radial import Calibration, DDMARadarConfig, steering_vectors

__all__ = ["make_calibration"]


def _channel_taper(cfg: DDMARadarConfig) -> np.ndarray:
    # Hamming taper on the horizontal virtual position: sidelobe control for azimuth.
    h = cfg.virtual_positions[:, 0]
    span = h.max() - h.min()
    t = (h - h.min()) / span if span > 0 else np.zeros_like(h)
    return (0.54 - 0.46 * np.cos(2 * np.pi * t)).astype(np.float32)


def make_calibration(cfg: DDMARadarConfig) -> Calibration:
    """The calibration table of ``cfg``'s radar unit, as a chamber measurement would give it.

    ``Signal[az, :, el] = conj(a(az, el))`` with ``a`` the true array response including the
    unit's hardware errors, on the grid ``cfg.az_grid_deg x cfg.el_grid_deg``.
    """
    az = cfg.azimuth_table_deg
    el = cfg.elevation_table_deg
    resp = steering_vectors(cfg, az[:, None], el[None, :])        # (n_az, n_el, n_virtual)
    signal = np.conj(resp).transpose(0, 2, 1).astype(np.complex64)  # (n_az, n_virtual, n_el)
    return Calibration(signal=signal, window=_channel_taper(cfg),
                       azimuth_deg=az.astype(np.float32), elevation_deg=el.astype(np.float32))
