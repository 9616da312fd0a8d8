"""Angle glint of a car's rear face: the azimuth one RD cell gives it, under the simulator's model.

The scatterers of a car's rear face (bumper, lights and the strong corners of the simulator's
vehicle template, :mod:`radarpc.sim.road`) lie at one range and share one Doppler, so they and
their ground bounces (:mod:`radarpc.sim.multipath`) fill one RD cell, and the DSP gives that cell
one azimuth: the maximum of its calibrated angle spectrum over all directions (the seed's eq. 6).
Their carrier phases differ by millimetre path differences, so that maximum wanders across the
face from frame to frame (angle glint). Nearer in, the corners are resolved and the maximum tends
to pick one of them; once the face is about as wide as the beam (:func:`beamwidth_deg`), it lands
between them.

:func:`rear_face` draws the template's rear-facing scatterers, :func:`face_paths` their three
paths each as the simulator makes them, :func:`beamformed_azimuth` the azimuth of a cell of
point paths, and :func:`glint_azimuths` all three for many faces turned and moved as between
frames, with no noise and no other cell. Scoring the azimuths with RADIal's box rule (a detection
level with its label matches only within 0.6 m across) is the metric's business
(:func:`radarpc.models.targets.box_iou`); ``docs/notebook/scripts/vehicle_glint.py`` does it.
"""
from __future__ import annotations

import numpy as np
import torch

from radarpc.dsp.beamform import angle_spectrum
from radarpc.sensors.radial import DDMARadarConfig, steering_vectors
from radarpc.sim.multipath import bistatic_fields, ground_image, path_fields
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.road import RoadSceneConfig, _vehicle_template

__all__ = ["CAR_LWH_M", "rear_face", "face_paths", "beamformed_azimuth", "glint_azimuths", "beamwidth_deg"]

CAR_LWH_M = (4.0, 1.8, 1.5)
"""Length, width and height (m) of the car: as wide as RADIal's 1.8 m box."""


def rear_face(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One draw of a car's rear-facing scatterers as the simulator's vehicle template lays them out.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the template's RCS values.

    Returns
    -------
    local_yz : ndarray ``(K, 2)``
        Offsets across from the face centre (body ``y``, left positive) and heights above the road.
    rcs : ndarray ``(K,)``
        RCS times the simulator's aspect factor ``sqrt(cos)`` seen from straight behind; the
        under-body points, seen only via the road and in other range cells, are left out.
    """
    body = _vehicle_template(rng, *CAR_LWH_M, truck=False, speed=10.0,
                             under_rcs=RoadSceneConfig.underbody_rcs_m2)
    cos_inc = -body.normal[:, 0]                       # the radar lies behind: direction (-1, 0)
    seen = (cos_inc > 0.05) & ~body.under              # the simulator's visibility rule
    return body.local[seen, 1:], body.rcs[seen] * np.sqrt(cos_inc[seen])


def face_paths(local_yz: np.ndarray, rcs: np.ndarray, range_m: float, azimuth_deg: float, yaw_deg: float,
               radar_height_m: float, ground_reflection_db: float) -> tuple[np.ndarray, ...]:
    """The simulator's paths of one rear face whose centre is at ``(range_m, azimuth_deg)``.

    Parameters
    ----------
    local_yz, rcs : ndarray ``(K, 2)``, ``(K,)``
        The face's scatterers (:func:`rear_face`).
    range_m, azimuth_deg : float
        Position of the face centre on the road (radar frame, ground plane).
    yaw_deg : float
        The face is perpendicular to the line of sight turned by this angle.
    radar_height_m : float
        Height of the radar above the road.
    ground_reflection_db : float
        Power loss ``|Gamma|^2`` of one bounce off the road (dB).

    Returns
    -------
    range_m, azimuth_deg, elevation_deg, rcs : ndarray ``(3 K,)``
        The direct paths, the ground-bistatic ones (``4 |Gamma|^2``) and the ground-double ones
        (``|Gamma|^4``), as ``RoadScene.frame`` makes them.
    """
    a, t = np.radians(azimuth_deg), np.radians(azimuth_deg + yaw_deg)
    across = np.array([-np.sin(t), np.cos(t)])                        # body y in the radar frame
    xy = range_m * np.array([np.cos(a), np.sin(a)]) + local_yz[:, :1] * across
    xyz = np.concatenate([xy, local_yz[:, 1:] - radar_height_m], 1)   # radar frame, z from the radar
    still = np.zeros_like(xyz)
    img, v_img = ground_image(xyz, still, radar_height_m)
    gamma2 = 10.0 ** (ground_reflection_db / 10.0)
    fields = [path_fields(xyz, still), bistatic_fields(xyz, still, img, v_img), path_fields(img, v_img)]
    r, az, el = (np.concatenate([f[i] for f in fields]) for i in range(3))
    return r, az, el, np.concatenate([rcs, rcs * 4.0 * gamma2, rcs * gamma2 ** 2])


def beamformed_azimuth(cfg: DDMARadarConfig, range_m: np.ndarray, azimuth_deg: np.ndarray,
                       elevation_deg: np.ndarray, rcs: np.ndarray, dictionary: torch.Tensor) -> np.ndarray:
    """Azimuth (deg) of the calibrated angle spectrum's maximum of one cell per row.

    Parameters
    ----------
    cfg : DDMARadarConfig
    range_m, azimuth_deg, elevation_deg, rcs : ndarray ``(D, K)``
        ``K`` point paths in each of ``D`` cells; each adds ``sqrt(rcs) / R^2`` with the carrier
        phase ``4 pi R / lambda`` of its range, as the simulator's synthesis does.
    dictionary : Tensor ``(n_az n_el, n_virtual)``
        ``B`` of :meth:`Calibration.dictionary` on ``cfg``'s tables (rows ``k = az n_el + el``).

    Returns
    -------
    ndarray ``(D,)``
        ``cfg.azimuth_table_deg`` at the maximum over all directions. The maximum is taken in
        complex64 without the pipeline's certified tie-break, which only matters at exact ties.
    """
    shapes = {np.shape(x) for x in (range_m, azimuth_deg, elevation_deg, rcs)}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"range_m, azimuth_deg, elevation_deg and rcs must share one (D, K) shape, got {shapes}")
    n_az, n_el = len(cfg.azimuth_table_deg), len(cfg.elevation_table_deg)
    if tuple(dictionary.shape) != (n_az * n_el, cfg.n_virtual):
        raise ValueError(f"dictionary must be ({n_az * n_el}, {cfg.n_virtual}) for sensor {cfg.name!r}, "
                         f"got {tuple(dictionary.shape)}")
    r = np.asarray(range_m, np.float64)
    alpha = np.sqrt(np.asarray(rcs, np.float64)) / r ** 2 * np.exp(2j * np.pi * np.remainder(2.0 * r / cfg.wavelength_m, 1.0))
    v = (alpha[..., None] * steering_vectors(cfg, azimuth_deg, elevation_deg)).sum(1)      # (D, n_virtual)
    s = angle_spectrum(torch.as_tensor(v, dtype=torch.complex64), dictionary)            # (D, n_az n_el)
    return cfg.azimuth_table_deg[(s.argmax(1) // n_el).numpy()]


def glint_azimuths(cfg: DDMARadarConfig, range_m: float, draws: int, rng: np.random.Generator, *,
                azimuth_deg: float = 0.0, yaw_deg: float = 5.0, ground_reflection_db: float | None = None,
                dictionary: torch.Tensor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``draws`` rear faces near ``range_m`` and the azimuth the DSP gives each one's cell.

    Parameters
    ----------
    cfg : DDMARadarConfig
    range_m : float
        Range of the face centre, > 0.5 (each draw moves it by up to 0.5 m).
    draws : int
        Independent faces, >= 1.
    rng : numpy.random.Generator
    azimuth_deg : float
        Azimuth of the face centre.
    yaw_deg : float
        Each face is turned by a uniform angle in ``[-yaw_deg, yaw_deg]``, >= 0.
    ground_reflection_db : float, optional
        Power loss of one bounce off the road; the simulator's (``RoadSceneConfig``) when not given.
    dictionary : Tensor, optional
        ``B`` of :meth:`Calibration.dictionary`; made from ``cfg`` when not given.

    Returns
    -------
    range_m : ndarray ``(draws,)``
        Range of each face centre (within 0.5 m of ``range_m``).
    peak_azimuth_deg : ndarray ``(draws,)``
        Azimuth of the maximum of each face's cell (:func:`beamformed_azimuth`). A detection there
        and a label at the face centre (``azimuth_deg``), both at the face's range, are what
        RADIal's box rule scores.
    """
    if range_m <= 0.5 or draws < 1 or yaw_deg < 0:
        raise ValueError(f"range_m must be > 0.5, draws >= 1 and yaw_deg >= 0, got {range_m}, {draws}, {yaw_deg}")
    if dictionary is None:
        dictionary = make_calibration(cfg).dictionary()
    scene = RoadSceneConfig()
    if ground_reflection_db is None:
        ground_reflection_db = scene.ground_reflection_db
    faces = [rear_face(rng) for _ in range(draws)]
    k = 3 * max(len(c) for _, c in faces)
    paths = np.zeros((4, draws, k))
    paths[:3] = 1.0                                      # padding paths: rcs 0, adds nothing
    r_face = range_m + rng.uniform(-0.5, 0.5, draws)
    for i, (local_yz, rcs) in enumerate(faces):
        p = face_paths(local_yz, rcs, r_face[i], azimuth_deg, rng.uniform(-yaw_deg, yaw_deg),
                       scene.radar_height_m, ground_reflection_db)
        paths[:, i, :len(p[0])] = p
    return r_face, beamformed_azimuth(cfg, *paths, dictionary)


def beamwidth_deg(cfg: DDMARadarConfig, azimuth_deg: float = 0.0, dictionary: torch.Tensor | None = None, *,
                  hardware: bool = True) -> float:
    """-3 dB width (deg) of the calibrated azimuth spectrum of one point target at elevation 0.

    Parameters
    ----------
    cfg : DDMARadarConfig
    azimuth_deg : float
        The target's azimuth.
    dictionary : Tensor, optional
        ``B`` of :meth:`Calibration.dictionary`; made from ``cfg`` when not given.
    hardware : bool
        Whether the target's snapshot carries the unit's hardware errors
        (:func:`radarpc.sensors.radial.steering_vectors`).

    Returns
    -------
    float
        The distance between the two -3 dB crossings of the main lobe on the elevation-0 cut,
        each interpolated linearly between its two grid samples.
    """
    if dictionary is None:
        dictionary = make_calibration(cfg).dictionary()
    az_table, el_table = cfg.azimuth_table_deg, cfg.elevation_table_deg
    v = torch.as_tensor(steering_vectors(cfg, azimuth_deg, 0.0, hardware=hardware)[None], dtype=torch.complex64)
    s = angle_spectrum(v, dictionary)[0].reshape(len(az_table), len(el_table)).double().numpy()
    cut = s[:, int(np.argmin(np.abs(el_table)))]
    half = cut.max() / np.sqrt(2)
    lo = hi = int(cut.argmax())
    while lo > 0 and cut[lo - 1] >= half:               # the main lobe: the run of the maximum above -3 dB
        lo -= 1
    while hi < len(cut) - 1 and cut[hi + 1] >= half:
        hi += 1
    if lo == 0 or hi == len(cut) - 1:
        raise ValueError(f"the main lobe at {azimuth_deg} deg reaches the end of the calibration grid")

    def crossing(inside: int, outside: int) -> float:
        f = (cut[inside] - half) / (cut[inside] - cut[outside])
        return az_table[inside] + f * (az_table[outside] - az_table[inside])

    return float(crossing(hi, hi + 1) - crossing(lo, lo - 1))
