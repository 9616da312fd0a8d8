"""RADIal labels and freespace masks from the geometry of a simulated road frame.

Labels (one row per vehicle in the field of view, columns exactly :data:`LABEL_COLUMNS`):

* Reference point: RADIal's "middle of either the back or front visible face of the vehicle":
  the centre of the rear face if the radar is behind the vehicle's centre along its heading,
  else of the front face; at half the vehicle's height.
* ``radar_X_m, radar_Y_m``: that point in the radar frame (x forward, y left), metres.
* ``radar_R_m = hypot(X, Y)`` (ground-plane range), ``radar_A_deg = atan2(Y, X)`` in degrees,
  left positive.
* ``radar_D``: radial velocity of the vehicle relative to the radar at the reference point, in
  m/s, receding positive: ``<(X, Y), v_rel> / R`` with ``v_rel`` the vehicle's ground velocity
  minus the ego's.
* ``radar_P_db``: received power of the vehicle as ``10 log10`` of the sum over its scatterers in
  the frame (after aspect and occlusion) of their on-bin peak SNR per RD cell per virtual channel
  (:func:`radarpc.sim.rd.peak_snr_rd`), i.e. dB above the thermal-noise floor of one RD cell.
* ``laser_X/Y/Z_m``: the same point (with its height) in a LiDAR frame whose axes are the radar's
  and whose origin is :data:`LIDAR_OFFSET_M` in the radar frame (a roof LiDAR 1.5 m behind and
  1.0 m above the radar): ``laser = point - LIDAR_OFFSET_M``.
* ``x1_pix .. y2_pix``: the vehicle's box in the camera image, in the 1920 x 1080 pixels of
  RADIal's frames (:func:`radarpc.sim.radial_camera.vehicle_image_boxes`: bounding rectangle of
  its projected 3-D box, clipped to the image); -1 where it is not in the image.
* ``dataset``: :func:`simulated_sequence_name` ``(seed, sequence)``; ``dataset_index``: frame
  index in the sequence; ``numSample``: ``sequence * frames_per_sequence + index``.
* ``Difficult``: 1 if less than half of the vehicle's radar-facing scatterers are unoccluded or
  its range exceeds :data:`DIFFICULT_RANGE_FRACTION` of the instrumented range, else 0.

Field of view: reference point ahead (``X > 0``), ``R < max_range_m - 1`` and ``|A|`` within
the sensor's calibrated azimuth span, with at least one of the vehicle's own scatterers in the
frame (direct, ground-bounce or under-body returns; mirror ghosts belong to no vehicle)
(:func:`labelled_vehicles`).

A frame without any vehicle gets one row of -1 in every column except ``numSample``,
``dataset`` and ``dataset_index`` (which the reader needs for the frame id and the split);
``Difficult`` is -1 there too.

Freespace (``FREESPACE_SHAPE`` uint8, 255 = free): pixel ``(i, j)`` is the point at range
``i * max_range_m / 512`` and azimuth :func:`freespace_azimuth_deg` ``(j)``; it is free if it lies
on the drivable road surface and is nearer than the first vehicle footprint along its ray (cells
inside or behind a vehicle are not free).
"""
from __future__ import annotations

import math

import numpy as np

from radarpc.data.radial_format import (
    FREESPACE_SHAPE,
    LABEL_COLUMNS,
    freespace_azimuth_deg,
    simulated_sequence_name,
)
from radarpc.sensors.radial import DDMARadarConfig
from radarpc.sim.radial_camera import vehicle_image_boxes
from radarpc.sim.rd import peak_snr_rd
from radarpc.sim.road import RoadFrame, VehicleTruth, footprint_crossings

__all__ = [
    "LIDAR_OFFSET_M",
    "DIFFICULT_RANGE_FRACTION",
    "reference_points",
    "frame_label_rows",
    "labelled_vehicles",
    "empty_label_row",
    "freespace_mask",
]

LIDAR_OFFSET_M: tuple[float, float, float] = (-1.5, 0.0, 1.0)
"""Origin of the LiDAR frame in the radar frame (metres); the axes are parallel."""
DIFFICULT_RANGE_FRACTION: float = 0.85
"""Vehicles beyond this fraction of ``cfg.max_range_m`` are ``Difficult``."""
_FOV_MARGIN_M = 1.0


def reference_points(vehicles: VehicleTruth) -> np.ndarray:
    """Middle of the visible back or front face of each vehicle, radar frame, ``(V, 3)``.

    The rear face is taken when the radar (the origin) lies behind the vehicle's centre along its
    heading, the front face otherwise; the point is at half the vehicle's height above the ground.
    """
    c = vehicles.center_xyz
    h = np.stack([np.cos(vehicles.yaw_rad), np.sin(vehicles.yaw_rad)], 1)       # heading (V, 2)
    ahead = (h * (-c[:, :2])).sum(1) > 0                                        # radar in front of centre
    sign = np.where(ahead, 1.0, -1.0)
    xy = c[:, :2] + sign[:, None] * h * (vehicles.size_lwh[:, :1] / 2)
    z = c[:, 2] + vehicles.size_lwh[:, 2] / 2
    return np.concatenate([xy, z[:, None]], 1)


def empty_label_row(num_sample: int, dataset: str, dataset_index: int) -> tuple:
    """The row of a frame without vehicles: -1 everywhere but numSample, dataset, dataset_index."""
    row = {c: -1 for c in LABEL_COLUMNS}
    row.update(numSample=int(num_sample), dataset=str(dataset), dataset_index=int(dataset_index))
    return tuple(row[c] for c in LABEL_COLUMNS)


def labelled_vehicles(cfg: DDMARadarConfig, frame: RoadFrame) -> np.ndarray:
    """Indices into ``frame.vehicles`` of the labelled vehicles, in the order of their label rows.

    A vehicle is labelled when it is in the field of view (see the module notes): reference
    point ahead, nearer than ``cfg.max_range_m - 1``, within the calibrated azimuth span, and at
    least one scatterer of its own (direct, ground-bounce or under-body; mirror ghosts belong to
    no vehicle) in the frame. Sorted by ground range (stable).
    """
    veh = frame.vehicles
    if len(veh) == 0:
        return np.zeros(0, np.int64)
    ref = reference_points(veh)
    x, y = ref[:, 0], ref[:, 1]
    r = np.hypot(x, y)
    a = np.degrees(np.arctan2(y, x))
    owner = frame.owner.numpy()
    count = np.bincount(owner[owner >= 0], minlength=len(veh))
    az_lim = max(abs(cfg.az_grid_deg[0]), abs(cfg.az_grid_deg[1]))
    in_view = (x > 0) & (r < cfg.max_range_m - _FOV_MARGIN_M) & (np.abs(a) <= az_lim) & (count > 0)
    return np.flatnonzero(in_view)[np.argsort(r[in_view], kind="stable")]


def frame_label_rows(cfg: DDMARadarConfig, frame: RoadFrame, *, seed: int, sequence: int,
                     index: int, frames_per_sequence: int) -> list[tuple]:
    """``labels.csv`` rows (tuples in :data:`LABEL_COLUMNS` order) of one simulated frame.

    Floats are rounded (4 decimals; ``radar_P_db`` 2), so that writing them with ``repr`` and
    parsing them back gives the same float64 values.

    Parameters
    ----------
    cfg : DDMARadarConfig
    frame : RoadFrame
    seed, sequence, index : int
        Simulator seed, sequence index, frame index in the sequence.
    frames_per_sequence : int

    Returns
    -------
    list of tuple
        One row per vehicle in the field of view, sorted by range; one -1 row if there is none.
    """
    if not 0 <= int(index) < int(frames_per_sequence):
        raise ValueError(f"frame index {index} outside [0, frames_per_sequence={frames_per_sequence})")
    num_sample = int(sequence) * int(frames_per_sequence) + int(index)
    name = simulated_sequence_name(seed, sequence)
    veh = frame.vehicles
    if len(veh) == 0:
        return [empty_label_row(num_sample, name, index)]
    ref = reference_points(veh)                                                 # (V, 3)
    x, y = ref[:, 0], ref[:, 1]
    r = np.hypot(x, y)
    a = np.degrees(np.arctan2(y, x))
    d = (x * veh.rel_velocity_xy[:, 0] + y * veh.rel_velocity_xy[:, 1]) / np.maximum(r, 1e-9)

    owner = frame.owner.numpy()
    sc = frame.scatterers
    snr = peak_snr_rd(cfg, sc.range_m.double().numpy(), sc.rcs_m2.double().numpy())
    mine = owner >= 0
    power = np.bincount(owner[mine], weights=snr[mine], minlength=len(veh))

    difficult = (veh.visible_fraction < 0.5) | (r > DIFFICULT_RANGE_FRACTION * cfg.max_range_m)
    lx, ly, lz = (ref[:, k] - LIDAR_OFFSET_M[k] for k in range(3))
    pix = vehicle_image_boxes(veh, frame.radar_height_m)                     # (V, 4), -1 = not seen
    rows = []
    for v in labelled_vehicles(cfg, frame):
        p_db = 10.0 * math.log10(max(float(power[v]), 1e-30))
        vals = dict(numSample=num_sample, x1_pix=int(pix[v, 0]), y1_pix=int(pix[v, 1]),
                    x2_pix=int(pix[v, 2]), y2_pix=int(pix[v, 3]),
                    laser_X_m=round(float(lx[v]), 4), laser_Y_m=round(float(ly[v]), 4),
                    laser_Z_m=round(float(lz[v]), 4),
                    radar_X_m=round(float(x[v]), 4), radar_Y_m=round(float(y[v]), 4),
                    radar_R_m=round(float(r[v]), 4), radar_A_deg=round(float(a[v]), 4),
                    radar_D=round(float(d[v]), 4), radar_P_db=round(p_db, 2),
                    dataset=name, dataset_index=int(index), Difficult=int(difficult[v]))
        rows.append(tuple(vals[c] for c in LABEL_COLUMNS))
    return rows or [empty_label_row(num_sample, name, index)]


def _first_hit_range(az_rad: np.ndarray, vehicles: VehicleTruth) -> np.ndarray:
    """Distance along each ray from the radar to the first vehicle footprint, ``inf`` if none."""
    if len(vehicles) == 0:
        return np.full(az_rad.shape[0], np.inf)
    dirs = np.stack([np.cos(az_rad), np.sin(az_rad)], 1)                       # unit rays (A, 2)
    t_in, t_out = footprint_crossings(dirs, vehicles.center_xyz[:, :2], vehicles.yaw_rad, vehicles.size_lwh)
    hit = (t_in < t_out) & (t_out > 0)
    return np.where(hit, np.maximum(t_in, 0.0), np.inf).min(axis=1)


def freespace_mask(cfg: DDMARadarConfig, frame: RoadFrame) -> np.ndarray:
    """Freespace PNG content of a frame: uint8 ``FREESPACE_SHAPE``, 255 = free road surface.

    Polar rasterisation: row ``i`` at range ``i * cfg.max_range_m / 512``, column ``j`` at
    :func:`freespace_azimuth_deg` ``(j)``. A pixel is free when it is on the road surface
    (:meth:`RoadGeometry.on_road`: its lateral offset from the curved centre line lies between
    the road edges) and nearer than the first vehicle footprint on its ray.
    """
    n_r, n_a = FREESPACE_SHAPE
    rng = np.arange(n_r) * (cfg.max_range_m / n_r)                             # (512,)
    az = np.deg2rad(freespace_azimuth_deg(np.arange(n_a)))                     # (900,)
    xy = rng[:, None, None] * np.stack([np.cos(az), np.sin(az)], -1)[None]    # (512, 900, 2)
    on_road = frame.road.on_road(xy)
    hit = _first_hit_range(az, frame.vehicles)                                 # (900,)
    free = on_road & (rng[:, None] < hit[None, :])
    return np.where(free, 255, 0).astype(np.uint8)
