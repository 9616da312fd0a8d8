"""Where a trained run's boxes sit against the labels: which axis fails RADIal's IoU 0.5.

For every label of a split inside the range gate this takes the nearest detection scored above
the threshold (the metrics' rule, scores ``> t``) and prints
:func:`radarpc.eval.localisation.near_miss_summary` as one JSON object:

* ``labels``, ``matched`` (some detection matches the label), ``near_miss`` (not matched, a
  detection within 3 m: ``fn_near`` of the metrics), ``far_miss``;
* for the near misses, the nearest detection's offset: how many fail by ``x`` alone (``|dy|``
  would pass), by ``y`` alone, or only by the two together, the medians of ``|dx|``, ``|dy|``,
  the range and azimuth differences, and the azimuth difference in cells (0.8 deg);
* the same counts by label range (0-30, 30-60, >= 60 m).

``--figure`` draws the offsets of matched and near-missed labels over the IoU 0.5 region.
Usage::

    python docs/notebook/scripts/box_offsets.py runs/sp --split test --threshold 0.2 --figure offsets.png
"""
from __future__ import annotations

import argparse
import functools
import json

import numpy as np
import torch
from torch.utils.data import DataLoader

from radarpc.eval.detection import FIXED_THRESHOLD, match_frame
from radarpc.eval.localisation import failing_axis, near_miss_summary, near_misses, nearest_detection_offsets
from radarpc.experiments.radial_detection.evaluation import load_trained
from radarpc.models.targets import decode_detections
from radarpc.experiments.radial_detection.task import DECODE_THRESHOLD, collate_detection, detection_dataset
from radarpc.viz import save_figure


def label_offsets(run: str, split: str, threshold: float) -> tuple[np.ndarray, str, float]:
    """:func:`radarpc.eval.localisation.nearest_detection_offsets` of every frame of ``run``'s
    ``split`` (the run's best weights, detections above ``threshold``), the model's name and its
    azimuth cell (deg)."""
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
                rows.append(nearest_detection_offsets(m, threshold))
    offsets = torch.cat(rows).numpy() if rows else np.zeros((0, 6))
    return offsets, cfg.name, cfg.targets.azimuth_cell_deg


def _figure(offsets: np.ndarray, title: str, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    near, matched = near_misses(offsets), offsets[:, 1] > 0
    dx, dy = offsets[:, 2], offsets[:, 3]
    fig, ax = plt.subplots(figsize=(6.5, 6))
    gx, gy = np.meshgrid(np.linspace(-3, 3, 601), np.linspace(-3, 3, 601))
    inside = (failing_axis(gx, gy) == "match").astype(float)
    ax.contourf(gx, gy, inside, levels=[0.5, 1.5], colors=["tab:green"], alpha=0.15)
    ax.contour(gx, gy, inside, levels=[0.5], colors=["tab:green"])
    ax.scatter(dx[matched], dy[matched], s=5, color="tab:green", alpha=0.5,
               label=f"matched ({int(matched.sum())}; nearest detection)")
    ax.scatter(dx[near], dy[near], s=9, color="tab:orange", label=f"missed, a detection within 3 m ({int(near.sum())})")
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
    offsets, model, azimuth_cell_deg = label_offsets(a.run, a.split, a.threshold)
    res = {"run": a.run, "split": a.split, "threshold": a.threshold, "model": model,
           **near_miss_summary(offsets, azimuth_cell_deg)}
    print(json.dumps(res))
    if a.figure:
        _figure(offsets, f"{model}, {a.split} split, confidence {a.threshold:g}: the nearest detection to each label", a.figure)


if __name__ == "__main__":
    main()
