"""Where one frame puts a car across from its rear face: angle glint against RADIal's tolerance.

A RADIal box is 1.8 m wide; a detection level with a label matches it (IoU >= 0.5) only within
``W (1 - t) / (1 + t) = 0.6 m`` across (:func:`radarpc.eval.detection.lateral_tolerance_m`). The
scatterers of a car's rear face (bumper, lights and the strong corners of the simulator's vehicle
template) lie at one range and share one Doppler, so they and their ground bounces fill one RD
cell, and the DSP gives that cell one azimuth: the maximum of its calibrated angle spectrum over
all directions (the seed's eq. 6). Their carrier phases differ by millimetre path differences, so
that maximum wanders across the face from frame to frame (angle glint). Nearer in, the corners
are resolved and the maximum tends to pick one of them; once the face is about as wide as the
beam, it lands between them.

For a car at each range (straight ahead, or at ``--azimuth``) this draws ``--draws`` rear faces:
the template's scatterers with their RCS draws, heights and the simulator's aspect factor
``sqrt(cos)``; the face turned by up to ``--yaw`` degrees and moved by up to 0.5 m in range, so
that the carrier phases vary as between frames; and each scatterer's three paths as the simulator
makes them (direct, ground bistatic ``4 |Gamma|^2``, ground double ``|Gamma|^4``, radar 0.8 m above
the road). It beamforms each cell with the sensor's own calibration
(:func:`radarpc.sim.radial_calibration.make_calibration`, hardware errors included), with no noise
and no other cell, and scores the maximum's azimuth with RADIal's box rule at the face's range.
Under-body returns lie in other range cells and are left out. Prints one JSON object: the beam's
-3 dB width and, per range, the share of faces matched and the median offset across.
``--figure`` plots the share against range. Usage::

    python benchmarks/vehicle_glint.py --sensor radial --draws 400 --figure glint.png
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from radarpc.dsp.beamform import angle_spectrum
from radarpc.eval.detection import IOU_THRESHOLD, lateral_tolerance_m
from radarpc.models.targets import BOX_WIDTH_M, box_iou, ra_to_box_xy
from radarpc.sensors.radial import DDMARadarConfig, radial_sensor, steering_vectors
from radarpc.sim.multipath import bistatic_fields, ground_image, path_fields
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.road import RoadSceneConfig, _vehicle_template
from radarpc.viz import save_figure

CAR_LWH_M = (4.0, BOX_WIDTH_M, 1.5)          # as wide as RADIal's box


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

    The face is perpendicular to the line of sight turned by ``yaw_deg``. Returns ``(range_m,
    azimuth_deg, elevation_deg, rcs)``, each ``(3 K,)``: the direct paths, the ground-bistatic ones
    (``4 |Gamma|^2``) and the ground-double ones (``|Gamma|^4``), as ``RoadScene.frame`` makes them.
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


def glint_draws(cfg: DDMARadarConfig, range_m: float, draws: int, rng: np.random.Generator, *,
                azimuth_deg: float = 0.0, yaw_deg: float = 5.0, ground_reflection_db: float | None = None,
                dictionary: torch.Tensor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``draws`` rear faces near ``range_m`` and score their cells' azimuths as RADIal would.

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
    matched : ndarray of bool ``(draws,)``
        Whether a detection at the face's range and the maximum's azimuth matches the label at the
        face centre (IoU >= 0.5 of their boxes).
    dx_m : ndarray ``(draws,)``
        The detection's offset across, ``R (sin A_peak - sin A_0)``, as the metric's boxes see it.
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
    peak = beamformed_azimuth(cfg, *paths, dictionary)
    r = torch.as_tensor(r_face)
    det = ra_to_box_xy(r, torch.as_tensor(peak, dtype=torch.float64))
    lab = ra_to_box_xy(r, torch.full_like(r, azimuth_deg))
    matched = box_iou(det, lab).diagonal() >= IOU_THRESHOLD
    return matched.numpy(), (det[:, 0] - lab[:, 0]).numpy()


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


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sensor", default="radial", help="a RADIal sensor name (radial, radial-s, tiny)")
    p.add_argument("--ranges", type=float, nargs="+", default=[10, 20, 30, 40, 50, 60, 70, 80, 90, 100])
    p.add_argument("--draws", type=int, default=400, help="rear faces per range")
    p.add_argument("--azimuth", type=float, default=0.0, help="azimuth of the car (deg)")
    p.add_argument("--yaw", type=float, default=5.0, help="faces turned by up to this many degrees")
    p.add_argument("--ground-reflection-db", type=float, default=RoadSceneConfig.ground_reflection_db,
                   help="power loss of one bounce off the road (the simulator's by default; -200: no bounce)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--figure", help="write the share matched against range here (PNG)")
    a = p.parse_args(argv)
    cfg = radial_sensor(a.sensor)
    dictionary = make_calibration(cfg).dictionary()
    rng = np.random.default_rng(a.seed)
    theta = beamwidth_deg(cfg, a.azimuth, dictionary)
    rows = []
    for r in a.ranges:
        matched, dx = glint_draws(cfg, r, a.draws, rng, azimuth_deg=a.azimuth, yaw_deg=a.yaw,
                                  ground_reflection_db=a.ground_reflection_db, dictionary=dictionary)
        share = float(matched.mean())
        rows.append({"range_m": r, "share_matched": share,
                     "standard_error": float(np.sqrt(share * (1 - share) / a.draws)),
                     "median_abs_dx_m": float(np.median(np.abs(dx))),
                     "face_width_deg": float(2 * np.degrees(np.arctan(CAR_LWH_M[1] / 2 / r)))})
    print(json.dumps({"sensor": a.sensor, "azimuth_deg": a.azimuth, "yaw_deg": a.yaw, "draws": a.draws,
                      "ground_reflection_db": a.ground_reflection_db,
                      "seed": a.seed, "lateral_tolerance_m": lateral_tolerance_m(), "beamwidth_3db_deg": theta,
                      "face_as_wide_as_beam_at_m": CAR_LWH_M[1] / np.radians(theta), "by_range": rows}))
    if a.figure:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6.5, 4))
        share = np.array([r["share_matched"] for r in rows])
        err = np.array([r["standard_error"] for r in rows])
        ax.errorbar(a.ranges, share, yerr=2 * err, fmt="o-", capsize=3,
                    label=f"the cell's azimuth matches the label ({a.draws} faces a range, 2 s.e.)")
        ax.axvline(CAR_LWH_M[1] / np.radians(theta), color="0.5", ls=":",
                   label=f"face as wide as the beam ({theta:.2f} deg at -3 dB)")
        ax.set(xlabel="range of the car (m)", ylabel="share of faces", ylim=(0, 1),
               title=f"{a.sensor}: one car's rear-face cell, no noise")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        save_figure(fig, a.figure, dpi=120)
        plt.close(fig)


if __name__ == "__main__":
    main()
