"""``radarpc evaluate-points``: Chamfer distance and EMD of predicted point clouds, per scene.

::

    radarpc evaluate-points PRED_DIR --data ROOT --split test [--emd-points 2048] [--emd-seed 0] [--force]

For every paired radar frame of the split, reads ``PRED_DIR/{run}/{frame:06d}.npy`` (float32
``(N, 3)``, radar frame; the layout ``radarpc baseline os-cfar`` writes) and scores it against
the reader's LiDAR cropped to the radar frustum (:mod:`radarpc.eval.pointsets`, batched; the folder
layout is :mod:`radarpc.eval.predictions`):

* CD: RaLD's non-squared Chamfer distance on the full clouds (KD-trees, exact);
* EMD: the exact Wasserstein-1 distance (POT's network simplex) between a fixed random subset of
  min(n, |gt|) LiDAR points -- the same draw for every method, keyed only by seed and frame -- and
  min(n, |pred|) predicted points, each subset carrying uniform mass (unequal sizes allowed, so a
  sparse prediction is not scored against a shrunken ground truth).

``PRED_DIR/index.json`` (written by ``radarpc baseline``) must name the same ``--data`` root and
``--split``, so that predictions are never scored against another dataset's LiDAR; ``--force``
skips that check (e.g. for hand-made prediction folders without an index). Prints a per-scene
Markdown table and writes ``PRED_DIR/metrics.json`` (per frame, per scene, overall) and
``metrics.md``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_parser", "run_evaluate_points"]


def run_evaluate_points(args: argparse.Namespace) -> int:
    from radarpc.data.coloradar import ColoRadar, scene_of_run
    from radarpc.eval.pointsets import evaluate_clouds
    from radarpc.eval.predictions import check_index, prediction_pairs
    from radarpc.io import DataFileError

    pred_dir = Path(args.pred_dir)
    if not pred_dir.is_dir():
        raise DataFileError(pred_dir, "prediction folder is missing")
    if args.emd_points < 1:
        raise ValueError(f"--emd-points must be >= 1, got {args.emd_points}")
    if not args.force:
        check_index(pred_dir, args.data, args.split)
    ds = ColoRadar(args.data, args.split, cube_size=None)
    if len(ds) == 0:
        raise ValueError(f"split {args.split!r} of {args.data} has no paired radar/LiDAR frame")
    report = evaluate_clouds(prediction_pairs(ds, pred_dir), scene_of_run, emd_points=args.emd_points,
                             emd_seed=args.emd_seed, progress=True)
    report.extra = {"pred_dir": str(pred_dir), "data": str(Path(args.data).resolve()), "split": args.split,
                    "index_checked": not args.force}
    report.write(pred_dir / "metrics.json", pred_dir / "metrics.md")
    print(report.to_markdown(), end="")
    print(f"wrote {pred_dir / 'metrics.json'} and {pred_dir / 'metrics.md'}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("evaluate-points", help="Chamfer distance and EMD of predicted clouds per scene",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pred_dir", help="prediction folder ({run}/{frame:06d}.npy)")
    p.add_argument("--data", required=True, help="ColoRadar root the predictions were made on")
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"),
                   help="split the predictions were made on (default test; must match PRED_DIR/index.json)")
    p.add_argument("--emd-points", type=int, default=2048,
                   help="EMD subset size n: min(n, |gt|) LiDAR and min(n, |pred|) predicted points (default 2048)")
    p.add_argument("--emd-seed", type=int, default=0, help="seed of the EMD subsets (default 0)")
    p.add_argument("--force", action="store_true",
                   help="score even if PRED_DIR/index.json is missing or names another root/split")
    p.set_defaults(func=run_evaluate_points)
