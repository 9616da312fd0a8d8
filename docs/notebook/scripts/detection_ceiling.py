"""How many labels a point store lets a detector reach at all: the data-side ceiling of recall.

For every label of a split (RADIal's 5..100 m gate) this measures, on the store's points
(:func:`radarpc.eval.localisation.point_reach`):

* the distance (m, bird's-eye view) from the label's reference point to the nearest point of its
  frame;
* whether some point, taken as a detection, matches the label by RADIal's rule (its 1.8 m x 4 m box
  has IoU >= 0.5 with the label's box), i.e. whether a detector that only picks points could find it;
* how many points lie within 3 m (the support a learned model has to place a box);

and, over all points, the share within 3 m of some label: the vehicle returns among the clutter.

Where the points put a box across (``placement_by_range_m``, by label range 0-30, 30-60, >= 60 m):
:func:`radarpc.eval.localisation.lateral_placement` and ``placement_summary``, the share of labels
whose points (inside the label's box grown by the 0.6 m tolerance across) place the box within
that tolerance by three rules: the centre of their extent across, the strongest point, and the
power-weighted centroid (``docs/notebook/scripts/vehicle_glint.py`` gives the physics of one rear
face).

A label without a point within a few metres can only be found by guessing, so the share of labels
with a point nearby bounds the recall of any point-cloud detector on that store, and the share
with a matching point is what a detector that does not learn offsets can reach. Several stores
(e.g. densities) are compared side by side::

    python docs/notebook/scripts/detection_ceiling.py --data data/sim_rs --points pc057.parquet pc200.parquet \\
        --split test --figure docs/results/figures/detection_ceiling.png

and so are stores of different roots (e.g. the same scenes seen by the ``radial`` and ``radial-s``
sensors), one ``--data`` root per store::

    python docs/notebook/scripts/detection_ceiling.py --data sim_r1 sim_rs1 --points pc_r1.parquet pc_rs1.parquet \\
        --split test --figure reach.png

Prints one JSON object per store.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from radarpc.data.point_dataset import PointCloudDataset
from radarpc.eval.detection import RANGE_GATE_M
from radarpc.eval.localisation import (
    LATERAL_TOLERANCE_M,
    PLACEMENT_RULES,
    lateral_placement,
    placement_summary,
    point_reach,
)
from radarpc.boxes import ra_to_box_xy
from radarpc.viz import save_figure

RADII_M = (1.0, 2.0, 3.0, 5.0)
SUPPORT_RADIUS_M = 3.0


def label_reach(points: str, data: str, split: str) -> dict:
    """Per-label reach statistics of one store (see the module docstring)."""
    ds = PointCloudDataset(points, data, split=split, difficult=True)
    nearest, matched, support, n_points, on_vehicle = [], [], [], [], 0
    label_range, placement = [], []
    for i in range(len(ds)):
        item = ds[i]
        p, lab = item.points, item.labels
        n_points.append(p.num_points)
        lab = lab[(lab[:, 0] >= RANGE_GATE_M[0]) & (lab[:, 0] <= RANGE_GATE_M[1])]
        if len(lab) == 0:
            continue
        xy_lab = ra_to_box_xy(lab[:, 0].double(), lab[:, 1].double())              # (L, 2)
        xy_pt = ra_to_box_xy(p.range_m.double(), p.azimuth_deg.double())          # (N, 2)
        label_range.append(lab[:, 0].double())
        placement.append(lateral_placement(xy_lab, xy_pt, p.amplitude))
        reach = point_reach(xy_lab, xy_pt, SUPPORT_RADIUS_M)
        nearest += reach.nearest_m.tolist()
        matched += reach.matched.tolist()
        support += reach.support.tolist()
        on_vehicle += int(reach.near_a_label.sum())
    nearest = np.asarray(nearest)
    label_range = torch.cat(label_range).numpy() if label_range else np.zeros(0)
    placement = torch.cat(placement).numpy() if placement else np.zeros((0, 4))
    return {
        "points": str(points), "split": split, "frames": len(ds), "labels": int(nearest.size),
        "points_per_frame": float(np.mean(n_points)) if n_points else 0.0,
        "share_with_matching_point": float(np.mean(matched)) if matched else float("nan"),
        **{f"share_with_point_within_{r:g}m": float(np.mean(nearest <= r)) for r in RADII_M},
        "median_nearest_m": float(np.median(nearest)) if nearest.size else float("nan"),
        "median_points_within_3m": float(np.median(support)) if support else float("nan"),
        "share_of_points_within_3m_of_a_label": on_vehicle / max(sum(n_points), 1),
        "lateral_tolerance_m": LATERAL_TOLERANCE_M,
        "placement_by_range_m": placement_summary(label_range, placement),
        "_label_range": label_range,
        "_placement": placement,
        "_nearest": nearest,
        "_support": np.asarray(support),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", required=True,
                    help="RADIal root (labels) of every store, or one root per store")
    ap.add_argument("--points", nargs="+", required=True, help="point stores")
    ap.add_argument("--split", default="test")
    ap.add_argument("--figure", default=None,
                    help="PNG: cumulative shares of labels against the distance to the nearest point "
                         "and against the number of points within 3 m, and the placement shares by range")
    args = ap.parse_args(argv)
    if len(args.data) not in (1, len(args.points)):
        ap.error(f"--data takes one root or one per store ({len(args.points)}), got {len(args.data)}")
    roots = args.data * len(args.points) if len(args.data) == 1 else args.data
    results = [label_reach(p, root, args.split) for p, root in zip(args.points, roots)]
    for r in results:
        print(json.dumps({k: v for k, v in r.items() if not k.startswith("_")}))
    if args.figure:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (ax, ax_n, ax_p) = plt.subplots(1, 3, figsize=(16, 4))
        grid = np.linspace(0, 10, 201)
        counts = np.arange(0, 31)
        edges = np.arange(0.0, 101.0, 10.0)
        for r in results:
            share = [(r["_nearest"] <= g).mean() for g in grid]
            label = f"{Path(r['points']).name} ({r['points_per_frame']:.0f} points/frame)"
            line, = ax.plot(grid, share, label=label)
            ax_n.step(counts, [(r["_support"] >= n).mean() for n in counts], where="post", label=label)
            placed = np.abs(r["_placement"][:, 1:]) <= LATERAL_TOLERANCE_M                  # (L, 3)
            b = np.clip(np.digitize(r["_label_range"], edges) - 1, 0, len(edges) - 2)  # 100 m in the last bin
            has = [k for k in range(len(edges) - 1) if (b == k).any()]
            centres = [(edges[k] + edges[k + 1]) / 2 for k in has]
            for j, style in ((0, "-"), (1, "--")):
                ax_p.plot(centres, [placed[b == k, j].mean() for k in has], style, color=line.get_color(),
                          marker="o", ms=3, label=f"{PLACEMENT_RULES[j].replace('_', ' ')}, {Path(r['points']).name}")
        ax.axvline(0.6, color="0.6", ls=":", lw=1)
        ax.set(xlabel="distance from a label to the nearest point of its frame [m]",
               ylabel="share of labels", ylim=(0, 1), xlim=(0, 10),
               title=f"{args.split} split: labels within reach of the points")
        ax_n.set(xlabel="n", ylabel="share of labels with >= n points within 3 m", ylim=(0, 1),
                 xlim=(0, counts[-1]), title="support a detector has to place each box")
        ax_p.set(xlabel="label range [m] (10 m bins)", ylim=(0, 1), xlim=(0, 100),
                 ylabel=f"share of labels placed within {LATERAL_TOLERANCE_M:.1f} m across",
                 title="what the points say of the position across")
        for a in (ax, ax_n, ax_p):
            a.grid(alpha=0.3)
            a.legend(fontsize=7, loc={ax: "lower right", ax_n: "upper right", ax_p: "lower left"}[a])
        fig.tight_layout()
        save_figure(fig, args.figure, dpi=100)
        plt.close(fig)


if __name__ == "__main__":
    main()
