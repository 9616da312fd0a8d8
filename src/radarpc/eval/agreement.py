"""Agreement of two sets of detections of one frame, e.g. the same weights in fp32 and in bf16.

:func:`pair_detections` pairs the detections of two inference paths one to one, nearest first,
within half a cell in range and in azimuth, and reports the detections left without a partner: a
path that keeps the decoded detections leaves none (up to detections whose score lies within the
paths' rounding of a threshold).
"""
from __future__ import annotations

import torch

from radarpc.boxes import Detections

__all__ = ["HALF_CELL", "pair_detections"]

HALF_CELL = (0.4, 0.4)
"""Pairing window (m, deg): below half a RADIal range cell (0.805 m) and azimuth cell (0.8 deg)."""


def pair_detections(a: Detections, b: Detections, half_cell: tuple[float, float] = HALF_CELL
                    ) -> tuple[list[tuple[int, int]], list[int], list[int]]:
    """Greedy one-to-one pairs of the detections of one frame, nearest first.

    Parameters
    ----------
    a, b : Detections
        One frame each (:meth:`Detections.frame`).
    half_cell : (float, float)
        A pair differs by at most this much in range (m) and in azimuth (deg); both > 0.

    Returns
    -------
    pairs : list of (int, int)
        Rows ``(i, j)`` of ``a`` and ``b``, in the order they were taken: the smallest
        ``|dR| / half_cell[0] + |dA| / half_cell[1]`` first among the rows not yet paired.
    lone_a, lone_b : list of int
        The rows of ``a`` and of ``b`` left without a pair, ascending.
    """
    if not (half_cell[0] > 0 and half_cell[1] > 0):
        raise ValueError(f"half_cell must be two positive widths (m, deg), got {half_cell}")
    dr = (a.range_m[:, None] - b.range_m[None, :]).abs()
    da = (a.azimuth_deg[:, None] - b.azimuth_deg[None, :]).abs()
    ok = (dr <= half_cell[0]) & (da <= half_cell[1])
    # Taking the cheapest pair left, again and again, is taking the candidate pairs in ascending
    # cost and keeping each whose rows are both still free; a stable sort of the row-major
    # candidates breaks ties as an argmin over the whole matrix would.
    ij = torch.nonzero(ok).tolist()
    cost = (dr / half_cell[0] + da / half_cell[1])[ok]
    pairs, used_a, used_b = [], set(), set()
    for k in torch.argsort(cost, stable=True).tolist():
        i, j = ij[k]
        if i not in used_a and j not in used_b:
            pairs.append((i, j))
            used_a.add(i)
            used_b.add(j)
    return (pairs, sorted(set(range(a.num_detections)) - {i for i, _ in pairs}),
            sorted(set(range(b.num_detections)) - {j for _, j in pairs}))
