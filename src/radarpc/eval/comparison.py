"""Methods side by side: the per-scene table of several prediction folders' scores, and what the
comparison figure of one frame draws (computed here, drawn by :func:`radarpc.viz.plot_cloud_comparison`).

Table (:func:`comparison_markdown`, :func:`comparison_dict`): one row per scene and ``all``, one
column group per method (CD mean and median, EMD mean and median, metres), from the methods'
:class:`~radarpc.eval.pointsets.PointSetReport` of the same frames.

Figure (:func:`comparison_view`): one radar frame, in two rows that share their axes across the
columns:

* bird's-eye view (x forward, y left; metres): the radar cube's intensity, maximum over
  elevation, on its range-azimuth cells mapped to the plane (each cell the quadrilateral of its
  range and azimuth edges), then the LiDAR truth and each method's cloud as points ``(y, x)``;
* range-elevation (range ``|p|`` in metres, elevation ``asin(z / |p|)`` in degrees): the
  intensity's maximum over azimuth on its range-elevation cells, then the clouds as points.

Angle bins of an FFT are evenly spaced in the sine of the angle, so a bin's edges are the
midpoints in sine between neighbouring bins (the outer edges half a step beyond, clipped to
+-90 deg): :func:`angle_edges_deg`. A cloud with more than ``max_points`` points is drawn from a
random subset of that many (a fixed seed; the view says how many of how many are drawn).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from radarpc.eval.pointsets import PointSetReport
from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV

__all__ = [
    "comparison_markdown",
    "comparison_dict",
    "angle_edges_deg",
    "range_edges",
    "CloudView",
    "ComparisonView",
    "cloud_view",
    "comparison_view",
]


# ---- the table ----------------------------------------------------------------------------------

def _scenes(reports: Mapping[str, PointSetReport]) -> list[str]:
    names = [s.scene for r in reports.values() for s in r.scenes]
    return sorted(dict.fromkeys(names))


def _summary(report: PointSetReport, scene: str):
    if scene == "all":
        return report.overall
    return next((s for s in report.scenes if s.scene == scene), None)


def comparison_markdown(reports: Mapping[str, PointSetReport]) -> str:
    """A Markdown table of several methods' scores per scene: rows the scenes and ``all``, a group
    of four columns per method (CD mean, CD median, EMD mean, EMD median; metres), then the number
    of frames (``a/b/...`` where the methods' counts differ; a scene a method lacks shows ``-``)."""
    if not reports:
        raise ValueError("comparison_markdown needs at least one method's report")
    names = list(reports)
    head = "| scene | frames | " + " | ".join(f"{n}: CD mean | {n}: CD median | {n}: EMD mean | {n}: EMD median"
                                             for n in names) + " |"
    lines = [head, "|---|---:|" + "---:|" * (4 * len(names))]
    for scene in [*_scenes(reports), "all"]:
        sums = [_summary(reports[n], scene) for n in names]
        counts = {s.n_frames if s is not None else 0 for s in sums}
        frames = str(counts.pop()) if len(counts) == 1 else "/".join(str(s.n_frames if s else 0) for s in sums)
        cells = []
        for s in sums:
            cells += (["-"] * 4 if s is None else
                      [f"{s.chamfer_mean:.3f}", f"{s.chamfer_median:.3f}", f"{s.emd_mean:.3f}", f"{s.emd_median:.3f}"])
        label = "**all**" if scene == "all" else scene
        lines.append(f"| {label} | {frames} | " + " | ".join(cells) + " |")
    first = next(iter(reports.values()))
    lines += ["", f"CD: RaLD's non-squared Chamfer distance (m). EMD: exact Wasserstein-1 between random subsets of "
                  f"min({first.emd_points}, |cloud|) points, seed {first.emd_seed} (m). Same frames for every method."]
    return "\n".join(lines) + "\n"


def comparison_dict(reports: Mapping[str, PointSetReport], folders: Mapping[str, str] | None = None) -> dict:
    """The same as a JSON-able dict: per method its folder (if given) and its per-scene and overall
    summaries."""
    from dataclasses import asdict

    return {"methods": [{"name": n, **({"folder": str(folders[n])} if folders and n in folders else {}),
                         "emd_points": r.emd_points, "emd_seed": r.emd_seed,
                         "overall": asdict(r.overall), "scenes": [asdict(s) for s in r.scenes]}
                        for n, r in reports.items()]}


# ---- the figure ---------------------------------------------------------------------------------

def angle_edges_deg(centres_deg) -> np.ndarray:
    """Edges ``(A + 1,)`` of angle bins evenly spaced in sine (FFT bins): midpoints in sine, the outer
    edges half a step beyond the end bins, clipped to +-90 deg; a single bin spans +-0.5 in sine."""
    s = np.sin(np.radians(np.asarray(centres_deg, dtype=np.float64)))
    if s.size < 2:
        return np.degrees(np.arcsin(np.clip(np.r_[s - 0.5, s + 0.5], -1, 1)))
    mid = 0.5 * (s[1:] + s[:-1])
    e = np.r_[s[0] - (mid[0] - s[0]), mid, s[-1] + (s[-1] - mid[-1])]
    return np.degrees(np.arcsin(np.clip(e, -1.0, 1.0)))


def range_edges(centres_m) -> np.ndarray:
    """Edges ``(R + 1,)`` of evenly spaced range bins, half a step either side of each centre."""
    r = np.asarray(centres_m, dtype=np.float64)
    step = float(r[1] - r[0]) if r.size > 1 else 1.0
    return np.r_[r - 0.5 * step, r[-1] + 0.5 * step]


@dataclass(frozen=True)
class CloudView:
    """One cloud as the comparison figure draws it."""

    name: str                     # the method ("LiDAR truth" for the truth)
    n_points: int                 # points of the cloud
    xy: np.ndarray                # (K, 2) x forward, y left (m) of the drawn points, K = min(n_points, max_points)
    range_elevation: np.ndarray   # (K, 2) range |p| (m), elevation (deg) of the same points
    note: str = ""                # e.g. "CD 0.412 m" (shown in the panel's title)

    @property
    def n_drawn(self) -> int:
        return int(self.xy.shape[0])


@dataclass(frozen=True)
class ComparisonView:
    """One frame of the comparison figure: the radar cube's projections, the truth, each method."""

    run: str
    scene: str
    frame: int                    # radar frame index in its run
    lidar_index: int              # the paired LiDAR scan
    fov: RadarFOV                 # the frustum the truth is cropped to
    bev_x: np.ndarray             # (R + 1, A + 1) x (m) of the range-azimuth cell corners
    bev_y: np.ndarray             # (R + 1, A + 1) y (m)
    bev_db: np.ndarray            # (R, A) intensity, max over elevation (dB)
    re_range: np.ndarray          # (R + 1,) range edges (m)
    re_elevation: np.ndarray      # (E + 1,) elevation edges (deg)
    re_db: np.ndarray             # (R, E) intensity, max over azimuth (dB)
    truth: CloudView
    methods: tuple[CloudView, ...]
    split: str = ""


def cloud_view(name: str, points, *, max_points: int = 50_000, seed: int = 0, note: str = "") -> CloudView:
    """The projections of a Cartesian cloud ``(N, 3)`` (N may be 0), from at most ``max_points`` points
    drawn without replacement by a generator of ``seed``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = p.shape[0]
    if n > max_points:
        p = p[np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))]
    r = np.linalg.norm(p, axis=1)
    el = np.degrees(np.arcsin(np.divide(p[:, 2], r, out=np.zeros_like(r), where=r > 0)))
    return CloudView(name, n, np.stack((p[:, 0], p[:, 1]), axis=1), np.stack((r, el), axis=1), note)


def comparison_view(intensity_db, range_m, azimuth_deg, elevation_deg, truth, clouds: Mapping[str, object], *,
                    run: str, scene: str, frame: int, lidar_index: int, fov: RadarFOV = AWR1843_FOV, split: str = "",
                    notes: Mapping[str, str] | None = None, max_points: int = 50_000) -> ComparisonView:
    """What the comparison figure draws for one frame (module docstring).

    Parameters
    ----------
    intensity_db : array-like, ``(R, A, E)``
        The radar cube's intensity (dB).
    range_m, azimuth_deg, elevation_deg : array-like
        Its bin centres (azimuth left positive, elevation up positive).
    truth : array-like, ``(M, 3)``
        The LiDAR truth (radar frame, cropped to the frustum).
    clouds : mapping of str to array-like ``(N, 3)``
        Each method's cloud by name, in the order to draw (a cloud may be empty).
    run, scene, frame, lidar_index, fov, split
        What the frame is (titles).
    notes : mapping of str to str, optional
        A note per method name (e.g. its Chamfer distance on this frame).
    max_points : int
        Points drawn per cloud at most.
    """
    x = np.asarray(intensity_db, dtype=np.float64)
    r, a, e = (np.asarray(v, dtype=np.float64).reshape(-1) for v in (range_m, azimuth_deg, elevation_deg))
    if x.ndim != 3 or x.shape != (r.size, a.size, e.size):
        raise ValueError(f"intensity {x.shape} must be (R, A, E) with its axes ({r.size}, {a.size}, {e.size})")
    if not clouds:
        raise ValueError("comparison_view needs at least one method's cloud")
    order = np.argsort(a)                                          # draw azimuth ascending
    bev_db = x.max(axis=2)[:, order]                               # (R, A)
    re_order = np.argsort(e)
    re_db = x.max(axis=1)[:, re_order]                             # (R, E)
    rr = np.clip(range_edges(r), 0.0, None)                        # (R + 1,)
    aa = np.radians(angle_edges_deg(a[order]))                     # (A + 1,)
    notes = dict(notes or {})
    return ComparisonView(
        run=run, scene=scene, frame=int(frame), lidar_index=int(lidar_index), fov=fov,
        bev_x=rr[:, None] * np.cos(aa)[None, :], bev_y=rr[:, None] * np.sin(aa)[None, :], bev_db=bev_db,
        re_range=rr, re_elevation=angle_edges_deg(e[re_order]), re_db=re_db,
        truth=cloud_view("LiDAR truth", truth, max_points=max_points),
        methods=tuple(cloud_view(name, pts, max_points=max_points, seed=k + 1, note=notes.get(name, ""))
                      for k, (name, pts) in enumerate(clouds.items())),
        split=split)

