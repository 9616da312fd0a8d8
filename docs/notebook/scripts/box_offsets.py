"""Where a trained run's boxes sit against the labels: which axis fails RADIal's IoU 0.5.

RADIal's boxes are all ``W x L = 1.8 m x 4 m`` and axis-aligned (``x`` across, ``y`` along the
boresight), so two boxes whose near-edge centres differ by ``(dx, dy)`` overlap
``(W - |dx|)(L - |dy|)`` and match (IoU >= 0.5) exactly when that overlap is at least
``2 W L / 3 = 4.8 m^2``. Alone, ``|dx| <= W / 3 = 0.6 m`` or ``|dy| <= L / 3 = 1.33 m``. A label
missed with a detection within 3 m (``fn_near`` of the metrics) failed on one of the two axes;
this script says which. For every label of a split inside the range gate it takes the nearest
detection scored above the threshold (the metrics' rule, scores ``> t``) and prints one JSON
object:

* ``labels``, ``matched`` (some detection matches the label), ``near_miss`` (not matched, a
  detection within 3 m), ``far_miss``;
* for the near misses, the nearest detection's offset: how many fail by ``x`` alone (``|dy|``
  would pass), by ``y`` alone, or only by the two together, the medians of ``|dx|``, ``|dy|``,
  the range and azimuth differences, and the azimuth difference in cells (0.8 deg);
* the same counts by label range (0-30, 30-60, >= 60 m).

``--figure`` draws the offsets of matched and near-missed labels over the IoU 0.5 region.
Usage::

    python benchmarks/box_offsets.py runs/sp --split test --threshold 0.2 --figure offsets.png
"""
from __future__ import annotations

import argparse
import functools
import json

import numpy as np
import torch
from torch.utils.data import DataLoader

from radarpc.eval.detection import FIXED_THRESHOLD, IOU_THRESHOLD, NEAR_MISS_M, lateral_tolerance_m, match_frame
from radarpc.experiments.detection import load_trained
from radarpc.models.targets import BOX_LENGTH_M, BOX_WIDTH_M, decode_detections
from radarpc.training.radial import DECODE_THRESHOLD, collate_detection, detection_dataset
from radarpc.viz import save_figure

RANGE_BINS_M = (30.0, 60.0)


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


def label_offsets(run: str, split: str, threshold: float) -> dict:
    """Per gated label of ``run``'s ``split``: range, nearest detection above ``threshold``
    (offsets ``dx``, ``dy``, range and azimuth differences; NaN without one), whether some
    detection matches it, and whether it is a near miss."""
    cfg, model, key = load_trained(run, "cpu")
    ds = detection_dataset(cfg, key["data"], key.get("points"), split)
    # batch 4 without a candidate cap, as radarpc evaluate scores
    loader = DataLoader(ds, batch_size=4, shuffle=False, collate_fn=functools.partial(collate_detection, cfg=cfg))
    rows = []
    with torch.inference_mode():
        for batch in loader:
            det = decode_detections(model(batch.inputs).detection.float(), cfg.targets, threshold=DECODE_THRESHOLD)
            l_end = batch.label_offset.tolist()
            for f in range(len(det)):
                d = det.frame(f)
                labels = batch.labels[(l_end[f - 1] if f else 0):l_end[f]]
                m = match_frame(d.score, d.range_m, d.azimuth_deg, labels)
                keep = m.score > threshold
                n_lab = len(m.label_xy)
                row = torch.full((n_lab, 6), float("nan"), dtype=torch.float64)
                row[:, 0] = m.label_range_m
                row[:, 1] = m.hit[keep].any(0).double()                          # (M,)
                if keep.any():
                    dist = torch.cdist(m.xy[keep], m.label_xy, compute_mode="donot_use_mm_for_euclid_dist")
                    i = dist.argmin(0)                                           # nearest detection per label
                    row[:, 2:4] = m.xy[keep][i] - m.label_xy
                    row[:, 4] = m.range_m[keep][i] - m.label_range_m
                    row[:, 5] = m.azimuth_deg[keep][i] - m.label_azimuth_deg
                rows.append(row)
    a = torch.cat(rows).numpy() if rows else np.zeros((0, 6))
    matched = a[:, 1] > 0
    return {"range_m": a[:, 0], "matched": matched, "dx": a[:, 2], "dy": a[:, 3],
            "d_range_m": a[:, 4], "d_azimuth_deg": a[:, 5],
            # missed with a detection within NEAR_MISS_M (NaN, no detection, compares False)
            "near": ~matched & (np.hypot(a[:, 2], a[:, 3]) <= NEAR_MISS_M),
            "model": cfg.name, "azimuth_cell_deg": cfg.targets.azimuth_cell_deg}


def summarise(o: dict) -> dict:
    """Counts and medians of :func:`label_offsets` (see the module docstring)."""
    near = o["near"]
    axis = failing_axis(np.nan_to_num(o["dx"], nan=99.0), np.nan_to_num(o["dy"], nan=99.0))

    def counts(sel: np.ndarray) -> dict:
        n = near & sel
        return {"labels": int(sel.sum()), "matched": int((o["matched"] & sel).sum()), "near_miss": int(n.sum()),
                "far_miss": int((~o["matched"] & ~near & sel).sum()),
                "near_miss_by_axis": {k: int((axis[n] == k).sum()) for k in ("x", "y", "x+y", "x,y")}}

    out = counts(np.ones_like(near))
    if near.any():
        out["near_miss_median"] = {
            "abs_dx_m": float(np.median(np.abs(o["dx"][near]))), "abs_dy_m": float(np.median(np.abs(o["dy"][near]))),
            "abs_d_range_m": float(np.median(np.abs(o["d_range_m"][near]))),
            "abs_d_azimuth_deg": float(np.median(np.abs(o["d_azimuth_deg"][near]))),
            "abs_d_azimuth_cells": float(np.median(np.abs(o["d_azimuth_deg"][near]))) / o["azimuth_cell_deg"]}
    edges = (0.0,) + RANGE_BINS_M + (np.inf,)
    out["by_range_m"] = {(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">={lo:g}"):
                         counts((o["range_m"] >= lo) & (o["range_m"] < hi)) for lo, hi in zip(edges[:-1], edges[1:])}
    return out


def _figure(o: dict, title: str, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    near = o["near"]
    fig, ax = plt.subplots(figsize=(6.5, 6))
    gx, gy = np.meshgrid(np.linspace(-3, 3, 601), np.linspace(-3, 3, 601))
    inside = (failing_axis(gx, gy) == "match").astype(float)
    ax.contourf(gx, gy, inside, levels=[0.5, 1.5], colors=["tab:green"], alpha=0.15)
    ax.contour(gx, gy, inside, levels=[0.5], colors=["tab:green"])
    ax.scatter(o["dx"][o["matched"]], o["dy"][o["matched"]], s=5, color="tab:green", alpha=0.5,
               label=f"matched ({int(o['matched'].sum())}; nearest detection)")
    ax.scatter(o["dx"][near], o["dy"][near], s=9, color="tab:orange", label=f"missed, a detection within 3 m ({int(near.sum())})")
    ax.set_xlim(-3, 3)
    ax.set_ylim(-3, 3)
    ax.set_aspect("equal")
    ax.set_xlabel("dx: detection - label, across (m)")
    ax.set_ylabel("dy: detection - label, along the boresight (m)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a training run folder (radarpc train --out)")
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    p.add_argument("--threshold", type=float, default=FIXED_THRESHOLD, help="confidence threshold (default 0.2)")
    p.add_argument("--figure", help="write the offsets over the IoU 0.5 region here")
    a = p.parse_args(argv)
    o = label_offsets(a.run, a.split, a.threshold)
    res = {"run": a.run, "split": a.split, "threshold": a.threshold, "model": o["model"], **summarise(o)}
    print(json.dumps(res))
    if a.figure:
        _figure(o, f"{o['model']}, {a.split} split, confidence {a.threshold:g}: the nearest detection to each label", a.figure)


if __name__ == "__main__":
    main()
