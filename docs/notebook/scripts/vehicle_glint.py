"""Where one frame puts a car across from its rear face: angle glint against RADIal's tolerance.

A RADIal box is 1.8 m wide; a detection level with a label matches it (IoU >= 0.5) only within
``W (1 - t) / (1 + t) = 0.6 m`` across (:func:`radarpc.eval.detection.lateral_tolerance_m`).
:mod:`radarpc.sim.glint` models why a car's rear face lands off that: its scatterers fill one RD
cell, whose azimuth (the maximum of the calibrated angle spectrum) wanders across the face from
frame to frame with the carrier phases.

For a car at each range (straight ahead, or at ``--azimuth``) this draws ``--draws`` rear faces
(:func:`radarpc.sim.glint.glint_azimuths`): the template's scatterers with their RCS draws,
heights and the simulator's aspect factor ``sqrt(cos)``; the face turned by up to ``--yaw``
degrees and moved by up to 0.5 m in range, so that the carrier phases vary as between frames; and
each scatterer's three paths as the simulator makes them (direct, ground bistatic ``4 |Gamma|^2``,
ground double ``|Gamma|^4``, radar 0.8 m above the road). It beamforms each cell with the
sensor's own calibration (:func:`radarpc.sim.radial_calibration.make_calibration`, hardware errors
included), with no noise and no other cell, and scores the maximum's azimuth with RADIal's box
rule at the face's range. Under-body returns lie in other range cells and are left out. Prints one
JSON object: the beam's -3 dB width and, per range, the share of faces matched and the median
offset across. ``--figure`` plots the share against range. Usage::

    python docs/notebook/scripts/vehicle_glint.py --sensor radial --draws 400 --figure glint.png
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from radarpc.eval.detection import IOU_THRESHOLD, lateral_tolerance_m
from radarpc.boxes import box_iou, ra_to_box_xy
from radarpc.sensors.radial import radial_sensor
from radarpc.sim.glint import CAR_LWH_M, beamwidth_deg, glint_azimuths
from radarpc.sim.radial_calibration import make_calibration
from radarpc.sim.road import RoadSceneConfig
from radarpc.viz import save_figure


def score(range_m: np.ndarray, peak_azimuth_deg: np.ndarray, azimuth_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """RADIal's box rule on each face: whether a detection at the face's range and the peak's
    azimuth matches the label at the face centre, and its offset across ``R (sin A_peak - sin A_0)``
    as the metric's boxes see it."""
    r = torch.as_tensor(range_m)
    det = ra_to_box_xy(r, torch.as_tensor(peak_azimuth_deg, dtype=torch.float64))
    lab = ra_to_box_xy(r, torch.full_like(r, azimuth_deg))
    matched = box_iou(det, lab).diagonal() >= IOU_THRESHOLD
    return matched.numpy(), (det[:, 0] - lab[:, 0]).numpy()


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
        r_face, peak = glint_azimuths(cfg, r, a.draws, rng, azimuth_deg=a.azimuth, yaw_deg=a.yaw,
                                      ground_reflection_db=a.ground_reflection_db, dictionary=dictionary)
        matched, dx = score(r_face, peak, a.azimuth)
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
