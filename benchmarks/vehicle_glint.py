"""Where one frame puts a vehicle across, from its rear face alone: angle glint against RADIal's tolerance.

A RADIal box is 1.8 m wide; a detection matches a label (IoU >= 0.5, ``dy = 0``) only if it sits
within ``W (1 - t) / (1 + t) = W / 3 = 0.6 m`` of it across. The scatterers of a vehicle's rear
face (bumper, lights, the strong corners of :func:`radarpc.sim.road._vehicle_template`) lie at one
range and share one Doppler, so they fill one RD cell, and the DSP gives that cell one azimuth:
the maximum of its calibrated angle spectrum (the seed's eq. 6). Their returns add with phases
set by millimetre path differences, effectively random from frame to frame, so that maximum
wanders across the face (angle glint). Once the face is narrower than the beam (-3 dB width
``theta``; from ``W / theta`` metres on), the corners are no longer resolved and the point lands
at their glint centroid; nearer in, the maximum picks one of the two resolved corners.

For a car straight ahead (or at ``--azimuth``) at each range this draws the template's rear face
``--draws`` times (its RCS draws, its aspect factor ``sqrt(cos)``, uniform phases; no noise, no
ground bounce, no under-body returns: the glint alone), beamforms the snapshot with the sensor's
own calibration (:func:`radarpc.sim.radial_calibration.make_calibration`, hardware errors
included), and prints one JSON object: the beam's -3 dB width and, per range, the share of draws
whose maximum lies within the tolerance across and the median lateral offset. ``--figure`` plots
the share against range. Usage::

    python benchmarks/vehicle_glint.py --sensor radial --draws 400 --figure glint.png
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from radarpc.dsp.beamform import angle_spectrum
from radarpc.eval.detection import IOU_THRESHOLD
from radarpc.io import atomic_write
from radarpc.models.targets import BOX_WIDTH_M
from radarpc.sensors.radial import DDMARadarConfig, radial_sensor, steering_vectors
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.road import _vehicle_template

CAR_LWH_M = (4.0, BOX_WIDTH_M, 1.5)          # RADIal's box: the label's face is as wide as its box


def lateral_tolerance_m(iou_threshold: float = IOU_THRESHOLD, width_m: float = BOX_WIDTH_M) -> float:
    """Largest offset across at which two equal axis-aligned boxes still reach ``iou_threshold``.

    Overlap ``(W - dx) L`` over union ``(W + dx) L``: ``IoU >= t  <=>  dx <= W (1 - t) / (1 + t)``.
    """
    if not 0.0 < iou_threshold < 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1), got {iou_threshold}")
    return width_m * (1 - iou_threshold) / (1 + iou_threshold)


def rear_face(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One draw of a car's rear-facing scatterers as the simulator lays them out.

    Returns
    -------
    lateral_m : ndarray ``(K,)``
        Offsets across from the face centre (body ``y``), left positive.
    amplitude : ndarray ``(K,)``
        ``sqrt(rcs * aspect)`` seen from straight behind, aspect ``sqrt(cos)`` of the incidence
        angle on each scatterer's normal (the simulator's rule); under-body returns left out.
    """
    body = _vehicle_template(rng, *CAR_LWH_M, truck=False, speed=10.0, under_rcs=(0.1, 0.5))
    cos_inc = -body.normal[:, 0]                       # the radar lies behind: direction (-1, 0)
    seen = (cos_inc > 0.05) & ~body.under
    return body.local[seen, 1], np.sqrt(body.rcs[seen] * np.sqrt(cos_inc[seen]))


def beamformed_azimuth(cfg: DDMARadarConfig, azimuth_deg: np.ndarray, amplitude: np.ndarray,
                       dictionary: torch.Tensor) -> np.ndarray:
    """Azimuth (deg) of the calibrated angle spectrum's maximum, one snapshot per row.

    Parameters
    ----------
    cfg : DDMARadarConfig
    azimuth_deg : ndarray ``(D, K)``
        Azimuths of ``K`` point scatterers (elevation 0) in each of ``D`` snapshots.
    amplitude : ndarray ``(D, K)``, complex
        Their complex amplitudes.
    dictionary : Tensor
        ``B`` of :meth:`Calibration.dictionary`, rows ``k = az n_el + el`` on ``cfg``'s tables.

    Returns
    -------
    ndarray ``(D,)``
        ``cfg.azimuth_table_deg`` at the maximum over all directions (the seed's eq. 6).
    """
    azimuth_deg, amplitude = np.asarray(azimuth_deg, float), np.asarray(amplitude, complex)
    if azimuth_deg.ndim != 2 or azimuth_deg.shape != amplitude.shape:
        raise ValueError(f"azimuth_deg and amplitude must both be (D, K), got {azimuth_deg.shape} and {amplitude.shape}")
    v = (amplitude[..., None] * steering_vectors(cfg, azimuth_deg, 0.0)).sum(1)             # (D, n_virtual)
    s = angle_spectrum(torch.as_tensor(v, dtype=torch.complex64), dictionary)               # (D, n_az n_el)
    return cfg.azimuth_table_deg[(s.argmax(1) // len(cfg.elevation_table_deg)).numpy()]


def peak_lateral_offsets(cfg: DDMARadarConfig, range_m: float, draws: int, rng: np.random.Generator, *,
                         azimuth_deg: float = 0.0, dictionary: torch.Tensor | None = None) -> np.ndarray:
    """Lateral offsets (m) of the beamformed maximum of a car's rear face from its centre.

    Parameters
    ----------
    cfg : DDMARadarConfig
    range_m : float
        Range of the face centre, > 0.
    draws : int
        Independent rear faces (:func:`rear_face`, uniform phases), >= 1.
    rng : numpy.random.Generator
    azimuth_deg : float
        Azimuth of the face centre; the face stays perpendicular to the line of sight.
    dictionary : Tensor, optional
        ``B`` of :meth:`Calibration.dictionary`; made from ``cfg`` when not given.

    Returns
    -------
    ndarray ``(draws,)``
        ``R sin(A_peak - A_0)``: across the line of sight, where the metric measures it.
    """
    if range_m <= 0 or draws < 1:
        raise ValueError(f"range_m must be > 0 and draws >= 1, got {range_m} and {draws}")
    if dictionary is None:
        dictionary = make_calibration(cfg).dictionary()
    faces = [rear_face(rng) for _ in range(draws)]
    k = max(len(a) for _, a in faces)
    az = np.full((draws, k), azimuth_deg)
    amp = np.zeros((draws, k), complex)                   # faces with fewer scatterers pad with zeros
    for i, (lateral, a) in enumerate(faces):
        az[i, :len(a)] += np.degrees(np.arctan2(lateral, range_m))
        amp[i, :len(a)] = a * np.exp(2j * np.pi * rng.random(len(a)))
    peak = beamformed_azimuth(cfg, az, amp, dictionary)
    return range_m * np.sin(np.radians(peak - azimuth_deg))


def beamwidth_deg(cfg: DDMARadarConfig, azimuth_deg: float = 0.0, dictionary: torch.Tensor | None = None) -> float:
    """-3 dB width (deg) of the calibrated azimuth spectrum of one point target at elevation 0,
    measured on the calibration grid (so within one grid step, 0.2 deg for ``radial``)."""
    if dictionary is None:
        dictionary = make_calibration(cfg).dictionary()
    az_table, el_table = cfg.azimuth_table_deg, cfg.elevation_table_deg
    v = torch.as_tensor(steering_vectors(cfg, azimuth_deg, 0.0)[None], dtype=torch.complex64)
    s = angle_spectrum(v, dictionary)[0].reshape(len(az_table), len(el_table)).numpy()
    cut = s[:, int(np.argmin(np.abs(el_table)))]
    above = np.flatnonzero(cut >= cut.max() / np.sqrt(2))
    k = int(cut.argmax())
    lo, hi = k, k                                   # the main lobe: the run of the maximum above -3 dB
    while lo - 1 in above:
        lo -= 1
    while hi + 1 in above:
        hi += 1
    return float(az_table[hi] - az_table[lo] + (az_table[1] - az_table[0]))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sensor", default="radial", help="a RADIal sensor name (radial, radial-s, tiny)")
    p.add_argument("--ranges", type=float, nargs="+", default=[10, 20, 30, 40, 50, 60, 70, 80, 90, 100])
    p.add_argument("--draws", type=int, default=400, help="rear faces per range")
    p.add_argument("--azimuth", type=float, default=0.0, help="azimuth of the car (deg)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--figure", help="write the share within the tolerance against range here (PNG)")
    a = p.parse_args(argv)
    cfg = radial_sensor(a.sensor)
    dictionary = make_calibration(cfg).dictionary()
    rng = np.random.default_rng(a.seed)
    tol = lateral_tolerance_m()
    theta = beamwidth_deg(cfg, a.azimuth, dictionary)
    rows = []
    for r in a.ranges:
        off = np.abs(peak_lateral_offsets(cfg, r, a.draws, rng, azimuth_deg=a.azimuth, dictionary=dictionary))
        rows.append({"range_m": r, "share_within_tolerance": float((off <= tol).mean()),
                     "median_abs_lateral_m": float(np.median(off)),
                     "face_width_deg": float(2 * np.degrees(np.arctan(CAR_LWH_M[1] / 2 / r)))})
    print(json.dumps({"sensor": a.sensor, "azimuth_deg": a.azimuth, "draws": a.draws, "seed": a.seed,
                      "lateral_tolerance_m": tol, "beamwidth_3db_deg": theta,
                      "unresolved_beyond_m": CAR_LWH_M[1] / np.radians(theta), "by_range": rows}))
    if a.figure:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6.5, 4))
        ax.plot(a.ranges, [r["share_within_tolerance"] for r in rows], "o-",
                label=f"beamformed maximum within {tol:.1f} m across ({a.draws} rear faces a range)")
        ax.axvline(CAR_LWH_M[1] / np.radians(theta), color="0.5", ls=":",
                   label=f"face as wide as the beam ({theta:.1f} deg at -3 dB)")
        ax.set(xlabel="range of the car (m)", ylabel="share of frames", ylim=(0, 1),
               title=f"{a.sensor}: one car's rear face, glint only (no noise)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        with atomic_write(a.figure, "wb") as f:
            fig.savefig(f, format="png", dpi=120)
        plt.close(fig)


if __name__ == "__main__":
    main()
