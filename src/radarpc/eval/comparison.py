"""Methods side by side: the per-scene table of several prediction folders' scores, the
empirical CDFs of their per-frame scores, and what the comparison figure of one frame draws
(computed here, drawn by :func:`radarpc.viz.plot_cloud_comparison` and :func:`radarpc.viz.plot_cdfs`).

Table (:func:`comparison_markdown`, :func:`comparison_dict`): one row per scene (and ``all``) and
method: frames, empty predictions, CD, EMD and EMD_equal mean and median (metres), from the
methods' :class:`~radarpc.eval.pointsets.PointSetReport` of the same frames. An empty prediction
is counted, not scored; when the methods differ in which frames they scored, a second table gives
the same over the frames *every* method scored (:func:`common_scored_frames`), so that no method
gains by failing on the hard frames.

CDFs (:func:`empirical_cdf`, :func:`cdf_panels`), as the seed's Figs. 6-7: per panel (each scene,
and all frames when there are several scenes) one curve per method, the fraction of the frames
whose score is at most ``x``. A frame whose prediction is empty counts in the denominator and
never below any ``x``: such a method's curve ends below 1, at its scored fraction.

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

from dataclasses import asdict, dataclass
from typing import Mapping

import numpy as np

from radarpc.eval.pointsets import PointSetReport, metric_note
from radarpc.sensors.coloradar import AWR1843_FOV, RadarFOV

__all__ = [
    "CDF_METRICS",
    "comparison_markdown",
    "comparison_dict",
    "common_scored_frames",
    "empirical_cdf",
    "CDFCurve",
    "CDFPanel",
    "cdf_panels",
    "angle_edges_deg",
    "range_edges",
    "CloudView",
    "ComparisonView",
    "cloud_view",
    "comparison_view",
]

CDF_METRICS = {"chamfer": "Chamfer distance", "emd": "EMD", "emd_equal": "EMD_equal"}
"""The per-frame scores :func:`cdf_panels` takes (FrameMetrics field -> name in titles)."""


# ---- the table ----------------------------------------------------------------------------------

def _scenes(reports: Mapping[str, PointSetReport]) -> list[str]:
    names = [s.scene for r in reports.values() for s in r.scenes]
    return sorted(dict.fromkeys(names))


def _summary(report: PointSetReport, scene: str):
    if scene == "all":
        return report.overall
    return next((s for s in report.scenes if s.scene == scene), None)


def _m(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _count(n: int) -> str:
    return f"{n} frame" if n == 1 else f"{n} frames"


def common_scored_frames(reports: Mapping[str, PointSetReport]) -> set[tuple[str, int]] | None:
    """``(run, frame)`` of the frames every method scored, or None when every method scored the
    same frames (then the main table already compares like with like)."""
    scored = [r.scored_keys for r in reports.values()]
    if all(k == scored[0] for k in scored):
        return None
    return set.intersection(*scored) if scored else set()


def _table(reports: Mapping[str, PointSetReport], *, with_empty: bool) -> list[str]:
    head = "| scene | method | frames | " + ("empty | " if with_empty else "") + \
        "CD mean | CD median | EMD mean | EMD median | EMD_equal mean | EMD_equal median |"
    lines = [head, "|---|---|---:|" + ("---:|" if with_empty else "") + "---:|" * 6]
    for scene in [*_scenes(reports), "all"]:
        label = "**all**" if scene == "all" else scene
        for name, r in reports.items():
            s = _summary(r, scene)
            if s is None:
                cells = ["0", *(["-"] if with_empty else []), *["-"] * 6]
            else:
                cells = [str(s.n_frames), *([str(s.empty)] if with_empty else []),
                         _m(s.chamfer_mean), _m(s.chamfer_median), _m(s.emd_mean), _m(s.emd_median),
                         _m(s.emd_equal_mean), _m(s.emd_equal_median)]
            lines.append(f"| {label} | {name} | " + " | ".join(cells) + " |")
    return lines


def comparison_markdown(reports: Mapping[str, PointSetReport]) -> str:
    """Markdown tables of several methods' scores per scene (metres).

    The first table: a row per scene (scenes sorted, then ``all``) and method (in the order
    given): frames, empty predictions, CD, EMD and EMD_equal mean and median over the frames the
    method scored (``-`` where it scored none, a scene a method lacks shows 0 frames). When the
    methods scored different frames (:func:`common_scored_frames`), a second table gives the same
    over the frames every method scored.
    """
    if not reports:
        raise ValueError("comparison_markdown needs at least one method's report")
    first = next(iter(reports.values()))
    lines = _table(reports, with_empty=True)
    common = common_scored_frames(reports)
    if common is not None:
        lines += ["", f"The methods differ in which frames they scored (an empty prediction is counted, not scored). "
                      f"Over the {_count(len(common))} every method scored:", ""]
        if common:
            lines += _table({n: r.subset(common) for n, r in reports.items()}, with_empty=False)
        else:
            lines.append("(no frame was scored by every method)")
    lines += ["", metric_note(first.emd_points, first.emd_seed)]
    return "\n".join(lines) + "\n"


def comparison_dict(reports: Mapping[str, PointSetReport], folders: Mapping[str, str] | None = None) -> dict:
    """The same as a JSON-able dict: per method its folder (if given) and its per-scene and overall
    summaries; when the methods scored different frames, ``common_scored``: the number of frames
    every method scored and each method's summaries over them (else ``common_scored`` is None)."""
    common = common_scored_frames(reports)
    out = {"methods": [{"name": n, **({"folder": str(folders[n])} if folders and n in folders else {}),
                        "emd_points": r.emd_points, "emd_seed": r.emd_seed,
                        "overall": asdict(r.overall), "scenes": [asdict(s) for s in r.scenes]}
                       for n, r in reports.items()],
           "common_scored": None}
    if common is not None:
        subs = {n: r.subset(common) for n, r in reports.items()}
        out["common_scored"] = {
            "n_frames": len(common),
            "frames": [{"run": run, "frame": frame} for run, frame in sorted(common)],
            "methods": [{"name": n, "overall": asdict(r.overall), "scenes": [asdict(s) for s in r.scenes]}
                        for n, r in subs.items()]}
    return out


# ---- the CDFs -----------------------------------------------------------------------------------

def empirical_cdf(values) -> tuple[np.ndarray, np.ndarray]:
    """The empirical CDF of per-frame scores: ``(x, F)`` with ``x`` the distinct finite values in
    increasing order and ``F[i]`` the fraction of *all* the values that are ``<= x[i]``.

    A NaN or infinite value (a frame not scored: an empty prediction) counts in the denominator
    and is never ``<= x``, so ``F`` ends at the scored fraction.

    Examples
    --------
    >>> x, F = empirical_cdf([0.3, 0.1, float("nan"), 0.3])
    >>> x.tolist(), F.tolist()
    ([0.1, 0.3], [0.25, 0.75])
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("empirical_cdf needs at least one value")
    finite = np.sort(v[np.isfinite(v)])
    x, counts = np.unique(finite, return_counts=True)
    return x, np.cumsum(counts) / float(v.size)


@dataclass(frozen=True)
class CDFCurve:
    """One method's curve in one panel of the CDF figure."""

    label: str            # the method
    x: np.ndarray         # (K,) distinct scores, increasing (m)
    p: np.ndarray         # (K,) fraction of the panel's frames with score <= x
    n_frames: int         # frames of the panel (the denominator)
    n_empty: int          # of which the prediction was empty (never reached)


@dataclass(frozen=True)
class CDFPanel:
    """One panel of the CDF figure: a scene (or ``all``) and a curve per method."""

    title: str
    curves: tuple[CDFCurve, ...]


def cdf_panels(reports: Mapping[str, PointSetReport], metric: str) -> list[CDFPanel]:
    """The CDF figure's panels for one per-frame score (``metric``: a key of :data:`CDF_METRICS`):
    a panel per scene (sorted), then ``all`` when there are several scenes; in each, a curve per
    method (in the order given) over that method's frames of the scene (:func:`empirical_cdf`;
    empty predictions count as never reached)."""
    if metric not in CDF_METRICS:
        raise ValueError(f"metric must be one of {sorted(CDF_METRICS)}, got {metric!r}")
    if not reports:
        raise ValueError("cdf_panels needs at least one method's report")
    scenes = _scenes(reports)
    panels = []
    for scene in scenes + (["all"] if len(scenes) > 1 else []):
        curves = []
        for name, r in reports.items():
            frames = [f for f in r.frames if scene == "all" or f.scene == scene]
            if not frames:
                continue
            vals = [np.nan if getattr(f, metric) is None else getattr(f, metric) for f in frames]
            x, p = empirical_cdf(vals)
            curves.append(CDFCurve(name, x, p, len(frames), sum(f.empty for f in frames)))
        panels.append(CDFPanel("all scenes" if scene == "all" else f"scene {scene}", tuple(curves)))
    return panels


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

