"""Multipath of road scenes: ground bounce, mirror ghosts off walls, as point scatterers.

Every path is found by the image method. A flat reflecting surface (the ground, a guard rail,
a facade) seen from the radar is replaced by the mirror image of the scatterer through it: the
path radar -> surface -> scatterer has the length of the straight line radar -> image, and the
image moves with the mirrored velocity. For a scatterer at ``p`` (radar frame) with image ``p'``
a round trip has three kinds of paths:

* direct out, direct back: the monostatic scatterer at ``p`` (the ordinary return);
* out along one, back along the other (twice, with equal lengths): a *bistatic* path of length
  ``|p| + |p'|`` and amplitude ``2 Gamma`` relative to the direct one;
* out and back via the surface: the monostatic scatterer at ``p'`` with amplitude ``Gamma^2``.

A point-scatterer model (:class:`radarpc.sim.rd.Scatterers`) has one range, one direction and
one radial velocity per path, as if the path were monostatic. The bistatic path is placed at
the mean range ``(|p| + |p'|) / 2`` (its delay is exact), with the mean of the two legs' radial
velocities (the rate of change of that half path length, exact), in the direction of the mean of
the two legs' unit vectors. The direction is the approximation: the virtual array sees the
transmit leg's phase gradient on its Tx positions and the receive leg's on its Rx positions,
which a single direction reproduces only to first order in the angle between the legs (for a
ground bounce the legs share the azimuth and differ in elevation by ``~2 h / d``, a fraction
of a degree beyond 10 m; for a wall ghost they differ in azimuth). The radar equation of the
synthesis then takes ``R^-4`` at the mean range instead of ``|p|^-2 |p'|^-2``: equal to first
order in ``(|p'| - |p|) / |p|``.

Powers: ``Gamma`` is the amplitude reflection coefficient of the surface, given as the power
loss per reflection in dB (``|Gamma|^2``), so the bistatic path carries ``4 |Gamma|^2`` times
the scatterer's RCS and the double reflection ``|Gamma|^4`` times.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "path_fields",
    "ground_image",
    "mirror_through_line",
    "bistatic_fields",
    "reflection_amplitude",
]


def reflection_amplitude(loss_db: float) -> float:
    """Amplitude ``|Gamma|`` of a reflection whose power loss is ``loss_db`` (dB, <= 0)."""
    if not loss_db <= 0.0:
        raise ValueError(f"a reflection loss must be <= 0 dB, got {loss_db}")
    return 10.0 ** (loss_db / 20.0)


def path_fields(xyz: np.ndarray, vel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Range, azimuth (deg), elevation (deg) and radial velocity of monostatic paths to ``xyz``.

    ``xyz`` and ``vel`` ``(N, 3)`` are radar-frame positions and velocities relative to the radar;
    the radial velocity is ``<p, v> / |p|`` (receding positive), as in
    :meth:`radarpc.sim.rd.Scatterers.from_xyz`.
    """
    r = np.linalg.norm(xyz, axis=1)
    rs = np.maximum(r, 1e-12)
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    el = np.degrees(np.arcsin(np.clip(xyz[:, 2] / rs, -1.0, 1.0)))
    return r, az, el, (xyz * vel).sum(1) / rs


def ground_image(xyz: np.ndarray, vel: np.ndarray, radar_height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Mirror images through the ground plane ``z = -radar_height_m`` (radar frame).

    A point at height ``z_w = z + h`` above the ground has its image at ``z_w' = -z_w``, i.e.
    ``z' = -z - 2 h``; the vertical velocity changes sign.
    """
    img, v = xyz.copy(), vel.copy()
    img[:, 2] = -xyz[:, 2] - 2.0 * float(radar_height_m)
    v[:, 2] = -vel[:, 2]
    return img, v


def mirror_through_line(xyz: np.ndarray, vel: np.ndarray, point: np.ndarray, direction: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Mirror images through vertical walls, each given by a point and a direction in the xy plane.

    Parameters
    ----------
    xyz, vel : ndarray ``(N, 3)``
        Positions and velocities; heights and vertical velocities are kept.
    point, direction : ndarray ``(N, 2)`` or ``(2,)``
        A point of the wall line and its direction (any length), per row or shared.

    Returns
    -------
    (xyz', vel') : ndarray ``(N, 3)``
        ``p' = p - 2 <p - q, n> n`` with ``n`` the unit normal of the line, velocities
        ``v' = v - 2 <v, n> n``.
    """
    d = np.broadcast_to(np.asarray(direction, float), (xyz.shape[0], 2))
    q = np.broadcast_to(np.asarray(point, float), (xyz.shape[0], 2))
    n = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
    img, v = xyz.copy(), vel.copy()
    off = ((xyz[:, :2] - q) * n).sum(1, keepdims=True)
    img[:, :2] = xyz[:, :2] - 2.0 * off * n
    v[:, :2] = vel[:, :2] - 2.0 * (vel[:, :2] * n).sum(1, keepdims=True) * n
    return img, v


def bistatic_fields(xyz_a: np.ndarray, vel_a: np.ndarray, xyz_b: np.ndarray, vel_b: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Point-scatterer fields of the paths out along leg ``a`` and back along leg ``b``.

    Range ``(|a| + |b|) / 2`` (exact delay), radial velocity ``(<a, v_a>/|a| + <b, v_b>/|b|) / 2``
    (exact Doppler), direction of ``a/|a| + b/|b|`` (see the module notes).
    """
    ra, _, _, va = path_fields(xyz_a, vel_a)
    rb, _, _, vb = path_fields(xyz_b, vel_b)
    u = xyz_a / np.maximum(ra, 1e-12)[:, None] + xyz_b / np.maximum(rb, 1e-12)[:, None]
    un = np.maximum(np.linalg.norm(u, axis=1), 1e-12)
    az = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    el = np.degrees(np.arcsin(np.clip(u[:, 2] / un, -1.0, 1.0)))
    return 0.5 * (ra + rb), az, el, 0.5 * (va + vb)
