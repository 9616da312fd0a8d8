"""What lies under a detector's false alarms, on simulated data whose scene truth is known.

A false alarm is a detection that RADIal's metric counts as a false positive: inside the range
gate (near-edge ``y`` in 5..100 m), scoring above the threshold, and with box IoU below 0.5 with
every label of its frame (:class:`radarpc.eval.detection.DetectionMetrics`' rule). Its cause is
the owner of the strongest scatterer of the simulated scene (power ``rcs / R^4``) inside its box
grown by ``margin_m`` on every side; the causes are :data:`FALSE_ALARM_CAUSES`:

* a labelled vehicle: the detector found a vehicle but put the box off by more than IoU 0.5
  allows (it is then usually also a near miss of that label);
* a vehicle without a label: a vehicle the labels leave out (out of the labelled field of view);
* a mirror ghost: a vehicle seen via a wall or rail, at the mirrored position;
* a moving person or cyclist: no vehicle's, with a radial velocity more than ``moving_mps`` away
  from a static point's at that direction (``-v_ego cos(A) cos(E)``);
* static clutter: no vehicle's otherwise (posts, rails, walls, buildings, standing people);
* nothing: no scatterer in the box (noise, sidelobes, or a score without support).

The scene truth comes from the simulator that wrote the root
(:meth:`radarpc.sim.radial_writer.RadialSimulator.from_root`); the caller turns it into the
per-scatterer arrays taken here (owner, labelled, moving, ghost), so that the metric does not
depend on the simulator. ``docs/notebook/scripts/false_alarms.py`` runs it for trained runs.
"""
from __future__ import annotations

import torch

from radarpc.boxes import BOX_LENGTH_M, BOX_WIDTH_M
from radarpc.eval.detection import FIXED_THRESHOLD, IOU_THRESHOLD, RANGE_GATE_M, match_frame

__all__ = ["FALSE_ALARM_CAUSES", "false_alarm_mask", "false_alarm_causes"]

FALSE_ALARM_CAUSES: tuple[str, ...] = (
    "labelled vehicle, box off",
    "vehicle without a label",
    "mirror ghost",
    "moving person or cyclist",
    "static clutter",
    "nothing",
)
"""Cause names, indexed by :func:`false_alarm_causes`' output."""


def false_alarm_mask(score: torch.Tensor, range_m: torch.Tensor, azimuth_deg: torch.Tensor,
                     labels: torch.Tensor, *, threshold: float = FIXED_THRESHOLD,
                     iou_threshold: float = IOU_THRESHOLD,
                     range_gate_m: tuple[float, float] = RANGE_GATE_M) -> torch.Tensor:
    """Which detections of one frame are false positives at ``threshold`` by RADIal's rule.

    Parameters
    ----------
    score, range_m, azimuth_deg : Tensor ``(K,)``
        The frame's detections.
    labels : Tensor ``(M, >= 2)``
        The frame's labels, range (m) and azimuth (deg) in columns 0 and 1.

    Returns
    -------
    BoolTensor ``(K,)``
        True for a detection inside the gate, scoring above ``threshold``, whose box has IoU below
        ``iou_threshold`` with every label inside the gate.
    """
    if not (score.shape == range_m.shape == azimuth_deg.shape) or score.ndim != 1:
        raise ValueError(f"score, range_m and azimuth_deg must be (K,) alike, got {tuple(score.shape)}, "
                         f"{tuple(range_m.shape)}, {tuple(azimuth_deg.shape)}")
    if labels.ndim != 2 or labels.shape[1] < 2:
        raise ValueError(f"labels must be (M, >= 2) with range_m, azimuth_deg in columns 0 and 1, got "
                         f"shape {tuple(labels.shape)}")
    m = match_frame(score, range_m, azimuth_deg, labels, iou_threshold=iou_threshold, range_gate_m=range_gate_m)
    fa = torch.zeros(score.shape, dtype=torch.bool)
    fa[m.kept] = (m.score > threshold) & ~m.hit.any(1)
    return fa


def false_alarm_causes(box_xy: torch.Tensor, scatterer_xy: torch.Tensor, power: torch.Tensor,
                       owner: torch.Tensor, labelled: torch.Tensor, moving: torch.Tensor, ghost: torch.Tensor,
                       *, margin_m: float = 1.0) -> torch.Tensor:
    """The cause of each false alarm: the owner of the strongest scatterer inside its box.

    Parameters
    ----------
    box_xy : Tensor ``(K, 2)``
        Near-edge centres of the false alarms' boxes (:func:`radarpc.boxes.ra_to_box_xy`).
    scatterer_xy : Tensor ``(N, 2)``
        The scene's scatterers in the same ``(x, y) = (R sin A, R cos A)`` frame.
    power : Tensor ``(N,)``
        Their strength (e.g. ``rcs / R^4``); the strongest in a box decides.
    owner : LongTensor ``(N,)``
        The index (``>= 0``) of the vehicle the scatterer belongs to, negative for none (static
        clutter, people, mirror ghosts), e.g. :attr:`radarpc.sim.road.RoadFrame.owner`.
    labelled : BoolTensor ``(N,)``
        The scatterer belongs to a vehicle that has a label in this frame.
    moving : BoolTensor ``(N,)``
        The scatterer moves over the ground (used for scatterers of no vehicle only).
    ghost : BoolTensor ``(N,)``
        The scatterer is a mirror ghost (``RoadFrame.owner == radarpc.sim.road.GHOST_OWNER``).
    margin_m : float
        The box ``[x - W/2, x + W/2] x [y, y + L]`` is grown by this much on every side.

    Returns
    -------
    LongTensor ``(K,)``
        Indices into :data:`FALSE_ALARM_CAUSES`.
    """
    n = scatterer_xy.shape[0]
    if box_xy.ndim != 2 or box_xy.shape[1] != 2 or scatterer_xy.ndim != 2 or scatterer_xy.shape[1] != 2:
        raise ValueError(f"box_xy and scatterer_xy must be (K, 2) and (N, 2), got {tuple(box_xy.shape)} "
                         f"and {tuple(scatterer_xy.shape)}")
    for name, t in (("power", power), ("owner", owner), ("labelled", labelled), ("moving", moving),
                    ("ghost", ghost)):
        if t.shape != (n,):
            raise ValueError(f"{name} must be ({n},) like scatterer_xy's rows, got {tuple(t.shape)}")
    if margin_m < 0:
        raise ValueError(f"margin_m must be >= 0, got {margin_m}")
    if n == 0:
        return torch.full((box_xy.shape[0],), FALSE_ALARM_CAUSES.index("nothing"), dtype=torch.long)
    dx = scatterer_xy[None, :, 0] - box_xy[:, None, 0]                          # (K, N)
    dy = scatterer_xy[None, :, 1] - box_xy[:, None, 1]                          # (K, N)
    inside = (dx.abs() <= BOX_WIDTH_M / 2 + margin_m) & (dy >= -margin_m) & (dy <= BOX_LENGTH_M + margin_m)
    strongest = torch.where(inside, power[None, :].to(torch.float64), -torch.inf).argmax(1)   # (K,)
    o, lab, mov, gh = owner[strongest], labelled[strongest], moving[strongest], ghost[strongest]
    cause = torch.full((box_xy.shape[0],), FALSE_ALARM_CAUSES.index("static clutter"), dtype=torch.long)
    cause[(o < 0) & mov] = FALSE_ALARM_CAUSES.index("moving person or cyclist")
    cause[gh] = FALSE_ALARM_CAUSES.index("mirror ghost")
    cause[(o >= 0) & lab] = FALSE_ALARM_CAUSES.index("labelled vehicle, box off")
    cause[(o >= 0) & ~lab] = FALSE_ALARM_CAUSES.index("vehicle without a label")
    cause[~inside.any(1)] = FALSE_ALARM_CAUSES.index("nothing")
    return cause
