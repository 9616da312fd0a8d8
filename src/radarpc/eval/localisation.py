"""Where RADIal's boxes sit against the labels: why a near miss fails IoU 0.5, and how far a
frame's points carry each label.

RADIal's boxes are all ``W x L = 1.8 m x 4 m`` and axis-aligned (``x`` across, ``y`` along the
boresight; :mod:`radarpc.eval.detection`), so two boxes whose near-edge centres differ by
``(dx, dy)`` overlap ``(W - |dx|)(L - |dy|)`` and match (IoU >= 0.5) exactly when that overlap is
at least ``2 W L / 3 = 4.8 m^2``. Alone, ``|dx| <= W / 3 = 0.6 m`` or ``|dy| <= L / 3 = 1.33 m``.

Near misses (a detector's side): a label missed with a detection within 3 m (``fn_near`` of the
metrics) failed on one of the two axes. :func:`nearest_detection_offsets` gives, per label of one
frame, the offset of the nearest detection scored above a threshold (the metrics' rule, scores
``> t``), :func:`failing_axis` which axis fails, and :func:`near_miss_summary` the counts over a
split, overall and by label range (:func:`range_bins`: 0-30, 30-60, >= 60 m).

The ceiling (the data's side): a label without a point within a few metres can only be found by
guessing, so the share of labels with a point nearby bounds the recall of any point-cloud detector
on a point store, and the share with a point that matches the label as a detection is what a
detector that does not learn offsets can reach (:func:`point_reach`). A box matches (IoU >= 0.5,
no error along) only within :data:`LATERAL_TOLERANCE_M` of the label across, so
:func:`lateral_placement` tells, for the points inside each label's box grown by that much on every
side, where three simple rules put the box across (the centre of the points' extent, the strongest
point, the power-weighted centroid), and :func:`placement_summary` the shares of labels placed
within the tolerance. The grown box is centred on the truth, so the rules know where the vehicle
is (a detector must find it first), but its points come mixed with any clutter inside; they are
simple rules, not bounds, and say how well the points carry the vehicle's position across.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from radarpc.eval.detection import IOU_THRESHOLD, NEAR_MISS_M, FrameMatch, lateral_tolerance_m
from radarpc.boxes import BOX_LENGTH_M, BOX_WIDTH_M, box_iou

__all__ = [
    "RANGE_BINS_M",
    "LATERAL_TOLERANCE_M",
    "PLACEMENT_RULES",
    "OFFSET_COLUMNS",
    "FAILING_AXES",
    "range_bins",
    "failing_axis",
    "nearest_detection_offsets",
    "near_misses",
    "near_miss_summary",
    "PointReach",
    "point_reach",
    "lateral_placement",
    "placement_summary",
]

RANGE_BINS_M = (30.0, 60.0)
"""Edges (m) of the label-range bins of the summaries: 0-30, 30-60, >= 60."""
LATERAL_TOLERANCE_M = lateral_tolerance_m(IOU_THRESHOLD)
"""0.6 m: the largest offset across at which a box level with its label matches it."""
PLACEMENT_RULES = ("extent_centre", "strongest_point", "power_centroid")
"""The rules of :func:`lateral_placement`, in the order of its columns 1..3."""
OFFSET_COLUMNS = ("range_m", "matched", "dx_m", "dy_m", "d_range_m", "d_azimuth_deg")
"""The columns of :func:`nearest_detection_offsets`."""
FAILING_AXES = ("x", "y", "x+y", "x,y")
"""The ways a near miss fails (:func:`failing_axis`, all but ``"match"``)."""


def range_bins(range_m: np.ndarray, edges_m: tuple[float, ...] = RANGE_BINS_M) -> dict[str, np.ndarray]:
    """Masks of the label-range bins ``lo <= R < hi`` between 0, ``edges_m`` and infinity.

    Parameters
    ----------
    range_m : ndarray ``(L,)``
        The labels' ranges (m).
    edges_m : tuple of float
        Inner edges, ascending.

    Returns
    -------
    dict
        ``{"0-30": mask, "30-60": mask, ">=60": mask}`` for the default edges (``f"{lo:g}-{hi:g}"``,
        the last ``f">={lo:g}"``), each a bool ``(L,)``.
    """
    if any(b <= a for a, b in zip(edges_m[:-1], edges_m[1:])) or (edges_m and edges_m[0] <= 0):
        raise ValueError(f"edges_m must be positive and ascending, got {edges_m}")
    r = np.asarray(range_m, dtype=np.float64)
    edges = (0.0,) + tuple(edges_m) + (np.inf,)
    return {(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">={lo:g}"): (r >= lo) & (r < hi)
            for lo, hi in zip(edges[:-1], edges[1:])}


def failing_axis(dx: np.ndarray, dy: np.ndarray, iou_threshold: float = IOU_THRESHOLD) -> np.ndarray:
    """Why boxes offset by ``(dx, dy)`` (m, any shapes) miss IoU ``iou_threshold``.

    Parameters
    ----------
    dx, dy : ndarray
        Offsets of two RADIal boxes' near-edge centres across and along the boresight.
    iou_threshold : float
        In (0, 1).

    Returns
    -------
    ndarray of str
        ``"match"``; ``"x"`` where ``dy`` alone would pass but the pair does not; ``"y"`` the
        other way round; ``"x+y"`` where each alone would pass but not both together; ``"x,y"``
        where neither alone would.
    """
    if not 0.0 < iou_threshold < 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1), got {iou_threshold}")
    dx, dy = np.abs(np.asarray(dx, dtype=np.float64)), np.abs(np.asarray(dy, dtype=np.float64))
    # IoU = I / (2 W L - I) >= t  <=>  I >= 2 W L t / (1 + t)
    need = 2 * BOX_WIDTH_M * BOX_LENGTH_M * iou_threshold / (1 + iou_threshold)
    inter = np.clip(BOX_WIDTH_M - dx, 0, None) * np.clip(BOX_LENGTH_M - dy, 0, None)
    x_ok = dx <= lateral_tolerance_m(iou_threshold)                         # passes with dy = 0
    y_ok = dy <= BOX_LENGTH_M * (1 - iou_threshold) / (1 + iou_threshold)   # passes with dx = 0, likewise
    return np.select([inter >= need, y_ok & ~x_ok, x_ok & ~y_ok, x_ok & y_ok],
                     ["match", "x", "y", "x+y"], default="x,y")


def nearest_detection_offsets(match: FrameMatch, threshold: float) -> torch.Tensor:
    """Per gated label of one frame: whether a detection matches it, and the nearest detection.

    Parameters
    ----------
    match : FrameMatch
        The frame's :func:`radarpc.eval.detection.match_frame`.
    threshold : float
        Detections scored ``> threshold`` count, as in the metrics.

    Returns
    -------
    Tensor ``(L, 6)``, float64
        Columns :data:`OFFSET_COLUMNS`: the label's range; 1 where some counted detection matches
        it (IoU >= the match's threshold), else 0; the nearest counted detection's offset (detection
        minus label) across and along (``dx``, ``dy``, between near-edge centres), in range and in
        azimuth. The offsets are NaN where no detection counts.
    """
    keep = match.score > threshold
    row = torch.full((len(match.label_xy), 6), float("nan"), dtype=torch.float64)
    row[:, 0] = match.label_range_m
    row[:, 1] = match.hit[keep].any(0).double()
    if keep.any():
        dist = torch.cdist(match.xy[keep], match.label_xy, compute_mode="donot_use_mm_for_euclid_dist")
        i = dist.argmin(0)                                                     # nearest detection per label
        row[:, 2:4] = match.xy[keep][i] - match.label_xy
        row[:, 4] = match.range_m[keep][i] - match.label_range_m
        row[:, 5] = match.azimuth_deg[keep][i] - match.label_azimuth_deg
    return row


def near_misses(offsets: np.ndarray) -> np.ndarray:
    """Labels missed with a counted detection within ``NEAR_MISS_M`` (3 m): the metrics' ``fn_near``.

    Parameters
    ----------
    offsets : ndarray ``(L, 6)``
        Rows of :func:`nearest_detection_offsets`.

    Returns
    -------
    ndarray of bool ``(L,)``
    """
    o = np.asarray(offsets, dtype=np.float64)
    # without a detection the offsets are NaN, which compares False
    return ~(o[:, 1] > 0) & (np.hypot(o[:, 2], o[:, 3]) <= NEAR_MISS_M)


def near_miss_summary(offsets: np.ndarray, azimuth_cell_deg: float) -> dict:
    """Counts and medians of :func:`nearest_detection_offsets` rows over a split.

    Parameters
    ----------
    offsets : ndarray ``(L, 6)``
        Rows of :func:`nearest_detection_offsets` of every frame.
    azimuth_cell_deg : float
        The model's azimuth cell, to give the azimuth error in cells.

    Returns
    -------
    dict
        ``labels``, ``matched``, ``near_miss`` (:func:`near_misses`), ``far_miss`` and
        ``near_miss_by_axis`` (:func:`failing_axis` of the near misses, keys
        :data:`FAILING_AXES`); where there are near misses, ``near_miss_median``: the medians of
        ``|dx|``, ``|dy|``, the range and azimuth differences and the azimuth difference in cells;
        and ``by_range_m``: the counts by label range (:func:`range_bins`).
    """
    o = np.asarray(offsets, dtype=np.float64).reshape(-1, 6)
    matched, near = o[:, 1] > 0, near_misses(o)
    axis = failing_axis(np.nan_to_num(o[:, 2], nan=99.0), np.nan_to_num(o[:, 3], nan=99.0))

    def counts(sel: np.ndarray) -> dict:
        n = near & sel
        return {"labels": int(sel.sum()), "matched": int((matched & sel).sum()), "near_miss": int(n.sum()),
                "far_miss": int((~matched & ~near & sel).sum()),
                "near_miss_by_axis": {k: int((axis[n] == k).sum()) for k in FAILING_AXES}}

    out = counts(np.ones(len(o), dtype=bool))
    if near.any():
        out["near_miss_median"] = {
            "abs_dx_m": float(np.median(np.abs(o[near, 2]))), "abs_dy_m": float(np.median(np.abs(o[near, 3]))),
            "abs_d_range_m": float(np.median(np.abs(o[near, 4]))),
            "abs_d_azimuth_deg": float(np.median(np.abs(o[near, 5]))),
            "abs_d_azimuth_cells": float(np.median(np.abs(o[near, 5]))) / azimuth_cell_deg}
    out["by_range_m"] = {k: counts(sel) for k, sel in range_bins(o[:, 0]).items()}
    return out


@dataclass(frozen=True)
class PointReach:
    """What one frame's points offer its labels (:func:`point_reach`).

    Attributes
    ----------
    nearest_m : float64 ``(L,)``
        Distance from each label's reference point to the nearest point (inf without points).
    matched : bool ``(L,)``
        Whether some point, taken as a detection, matches the label (box IoU >= 0.5).
    support : int64 ``(L,)``
        Points closer than the radius to the label.
    near_a_label : bool ``(N,)``
        Points closer than the radius to some label.
    """

    nearest_m: torch.Tensor
    matched: torch.Tensor
    support: torch.Tensor
    near_a_label: torch.Tensor


def point_reach(label_xy: torch.Tensor, point_xy: torch.Tensor, radius_m: float = NEAR_MISS_M) -> PointReach:
    """How far one frame's points reach its labels, on RADIal's box frame.

    Parameters
    ----------
    label_xy, point_xy : Tensor ``(L, 2)``, ``(N, 2)``
        Near-edge centres (:func:`radarpc.models.targets.ra_to_box_xy`) of the labels and points.
    radius_m : float
        Support radius (> 0): points closer than it to a label support that label.

    Returns
    -------
    PointReach
    """
    if label_xy.ndim != 2 or label_xy.shape[1] != 2 or point_xy.ndim != 2 or point_xy.shape[1] != 2:
        raise ValueError(f"label_xy and point_xy must be (L, 2) and (N, 2), got {tuple(label_xy.shape)} "
                         f"and {tuple(point_xy.shape)}")
    if radius_m <= 0:
        raise ValueError(f"radius_m must be > 0, got {radius_m}")
    n_lab, n_pt = len(label_xy), len(point_xy)
    if n_pt == 0 or n_lab == 0:
        return PointReach(torch.full((n_lab,), float("inf"), dtype=torch.float64),
                          torch.zeros(n_lab, dtype=torch.bool), torch.zeros(n_lab, dtype=torch.int64),
                          torch.zeros(n_pt, dtype=torch.bool))
    d = torch.cdist(label_xy.double(), point_xy.double())                     # (L, N)
    close = d < radius_m
    return PointReach(d.min(1).values, (box_iou(label_xy.double(), point_xy.double()) >= IOU_THRESHOLD).any(1),
                      close.sum(1), close.any(0))


def lateral_placement(label_xy: torch.Tensor, point_xy: torch.Tensor, amplitude: torch.Tensor,
                      grow_m: float = LATERAL_TOLERANCE_M) -> torch.Tensor:
    """How one frame's points place each label's box across.

    Parameters
    ----------
    label_xy : Tensor ``(L, 2)``
        Labels' near-edge centres in RADIal's box frame (``x`` across, ``y`` along the boresight).
    point_xy : Tensor ``(N, 2)``
        The frame's points in the same frame.
    amplitude : Tensor ``(N,)``
        The points' amplitudes (``Ae``), non-negative.
    grow_m : float
        Margin by which each label's ``W x L`` box is grown on every side, >= 0.

    Returns
    -------
    Tensor ``(L, 4)``, float64
        Per label: the number of points inside its grown box, then the offset across (point minus
        label, m) of the centre of their extent, of the strongest of them, and of their centroid
        weighted by ``amplitude**2`` (:data:`PLACEMENT_RULES`); NaN offsets where no point is
        inside.
    """
    if label_xy.ndim != 2 or label_xy.shape[1] != 2 or point_xy.ndim != 2 or point_xy.shape[1] != 2:
        raise ValueError(f"label_xy and point_xy must be (L, 2) and (N, 2), got {tuple(label_xy.shape)} "
                         f"and {tuple(point_xy.shape)}")
    if amplitude.shape != point_xy.shape[:1]:
        raise ValueError(f"amplitude must be ({point_xy.shape[0]},), got {tuple(amplitude.shape)}")
    if grow_m < 0:
        raise ValueError(f"grow_m must be >= 0, got {grow_m}")
    if len(point_xy) == 0:
        out = torch.full((len(label_xy), 4), float("nan"), dtype=torch.float64)
        out[:, 0] = 0
        return out
    d = point_xy.double()[None] - label_xy.double()[:, None]                     # (L, N, 2)
    dx = d[..., 0]
    inside = (dx.abs() <= BOX_WIDTH_M / 2 + grow_m) & (d[..., 1] >= -grow_m) & (d[..., 1] <= BOX_LENGTH_M + grow_m)
    n = inside.sum(1)
    inf = torch.tensor(float("inf"), dtype=torch.float64)
    extent = (torch.where(inside, dx, inf).amin(1) + torch.where(inside, dx, -inf).amax(1)) / 2
    power = torch.where(inside, amplitude.double()[None] ** 2, torch.zeros((), dtype=torch.float64))  # (L, N)
    # -1 outside: the strongest is an inside point even where all inside amplitudes are 0
    strongest = dx.gather(1, torch.where(inside, power, -1.0).argmax(1, keepdim=True))[:, 0]
    centroid = (power * dx).sum(1) / power.sum(1)
    out = torch.stack([n.double(), extent, strongest, centroid], 1)
    out[n == 0, 1:] = float("nan")
    return out


def placement_summary(range_m: np.ndarray, placement: np.ndarray, tolerance_m: float = LATERAL_TOLERANCE_M) -> dict:
    """Counts and shares of :func:`lateral_placement` rows, overall and by label range.

    Parameters
    ----------
    range_m : ndarray ``(L,)``
        The labels' ranges.
    placement : ndarray ``(L, 4)``
        Their :func:`lateral_placement` rows.
    tolerance_m : float
        An offset across counts as placed when ``|dx| <= tolerance_m``.

    Returns
    -------
    dict
        Under ``"all"`` and one key per range bin (:func:`range_bins`: ``"0-30"``, ``"30-60"``,
        ``">=60"``, ``lo <= R < hi``): ``labels``, ``median_points_in_grown_box``,
        ``share_without_a_point`` and, per rule of :data:`PLACEMENT_RULES`,
        ``share_placed_within_tolerance`` (a label without a point is not placed). Values of an
        empty bin are None.
    """
    def one(sel: np.ndarray) -> dict:
        p = placement[sel]
        if len(p) == 0:
            return {"labels": 0, "median_points_in_grown_box": None, "share_without_a_point": None,
                    "share_placed_within_tolerance": dict.fromkeys(PLACEMENT_RULES)}
        return {"labels": int(sel.sum()), "median_points_in_grown_box": float(np.median(p[:, 0])),
                "share_without_a_point": float(np.mean(p[:, 0] == 0)),
                "share_placed_within_tolerance": {  # NaN (no point) compares False
                    rule: float(np.mean(np.abs(p[:, 1 + k]) <= tolerance_m)) for k, rule in enumerate(PLACEMENT_RULES)}}

    return {"all": one(np.ones(len(range_m), bool)), **{k: one(sel) for k, sel in range_bins(range_m).items()}}
