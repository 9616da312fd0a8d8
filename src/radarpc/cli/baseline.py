"""``radarpc baseline``: classical baselines.

::

    radarpc baseline os-cfar ROOT --split test --out preds/oscfar [--tune-split val] [--config FILE]
    radarpc baseline detect POINTS --data ROOT --split test --out runs/classical [--show K]

``detect`` is the detection models' classical reference row (:mod:`radarpc.models.classical`: ego
speed from the points, Doppler gating, BEV clustering, one detection per cluster) on a RADIal point
store, scored like ``radarpc evaluate`` scores a trained run: ``OUT/eval_{split}.md`` and ``.json``
(RADIal's AP/AR/F1, F1 at confidence 0.2, range/azimuth errors, batch-1 frames/s with the point
extraction excluded), ``OUT/classical.yaml`` (its settings) and, with ``--show K``, figures.

``os-cfar`` writes into ``--out``:

* ``config.yaml`` -- the OS-CFAR parameters used (tuned, given, or reused when resuming);
* ``tuning.json`` -- mean Chamfer distance of every candidate of the grid search (when tuned);
* ``{run}/{frame:06d}.npy`` -- float32 ``(N, 3)`` points in the single-chip radar frame, one per
  paired radar frame of the split (``frame`` = index of the ADC frame in its run);
* ``index.json`` -- one entry per frame: run, scene, frame, paired LiDAR scan index and file,
  timestamps, prediction file and point count.

Every file is written atomically. A rerun into the same folder keeps the existing
``config.yaml`` (unless ``--config`` or ``--retune`` is given) and skips frames already written
with it, so an interrupted job resumes; a second job writing the same folder at the same time is
refused. The driver is :mod:`radarpc.pipelines.oscfar`, the layout :mod:`radarpc.eval.predictions`.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from radarpc.cli.options import frame_step

__all__ = ["add_parser", "run_oscfar", "run_detect"]


def run_detect(args: argparse.Namespace) -> int:
    from radarpc.config import load_yaml
    from radarpc.experiments.radial_detection.evaluation import evaluate_classical
    from radarpc.models.classical import ClassicalConfig

    cfg = load_yaml(ClassicalConfig, args.config) if args.config else ClassicalConfig()
    evaluate_classical(args.points, args.data, args.out, args.split, cfg=cfg, difficult=args.difficult,
                       show=args.show)
    return 0


def run_oscfar(args: argparse.Namespace) -> int:
    from radarpc.cli.text import plural
    from radarpc.pipelines.oscfar import OSCFARJob, predict_oscfar

    job = OSCFARJob(root=args.root, out=args.out, split=args.split, every=args.every, tune_split=args.tune_split,
                    max_tune_frames=args.max_tune_frames, config=args.config, retune=args.retune,
                    quick_tune=args.quick_tune, overwrite=args.overwrite)
    res = predict_oscfar(job, on_config=lambda cfg, how: print(f"OS-CFAR config {how}: {cfg}"))
    print(f"wrote {plural(res.n_new, 'new point cloud')} ({plural(res.n_frames, 'frame')}) to {Path(args.out)}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("baseline", help="classical baselines that turn radar frames into point clouds",
                       description=__doc__.splitlines()[0])
    kinds = p.add_subparsers(dest="kind", required=True, metavar="METHOD")
    q = kinds.add_parser("os-cfar", help="3-D OS-CFAR on the radar cube, tuned for Chamfer distance",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("root", help="ColoRadar root (real or simulated)")
    q.add_argument("--split", default="test", choices=("train", "val", "test", "all"), help="split whose paired frames are predicted (default test)")
    q.add_argument("--every", type=frame_step, default=1, metavar="K",
                   help="predict every K-th paired frame of each run (default 1: all)")
    q.add_argument("--out", required=True, help="prediction folder")
    q.add_argument("--tune-split", default="val", choices=("train", "val", "test", "all"),
                   help="split whose frames tune the parameters (default val)")
    q.add_argument("--max-tune-frames", type=int, default=32,
                   help="evenly spaced frames of the tuning split used by the grid search (default 32)")
    q.add_argument("--config", default=None, help="use this config.yaml instead of tuning")
    q.add_argument("--retune", action="store_true", help="tune again even if OUT/config.yaml exists")
    q.add_argument("--quick-tune", action="store_true", help="a 3-candidate grid (for smoke tests)")
    q.add_argument("--overwrite", action="store_true",
                   help="replace the predictions of another root or split (or write into a non-empty folder "
                        "that is not a prediction folder); without it such a folder is refused")
    q.set_defaults(func=run_oscfar)
    d = kinds.add_parser("detect", help="vehicle detections from a RADIal point store: Doppler gating and "
                                        "BEV clustering, scored with RADIal's metrics",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d.add_argument("points", help="point store (radarpc pointcloud ROOT --out FILE.parquet)")
    d.add_argument("--data", required=True, help="the RADIal root the store was made from (labels)")
    d.add_argument("--split", default="test", choices=("train", "val", "test", "all"), help="split (default test)")
    d.add_argument("--out", required=True, help="folder for eval_{split}.md/.json, classical.yaml and figures")
    d.add_argument("--config", default=None, help="a classical.yaml with other settings")
    d.add_argument("--difficult", action=argparse.BooleanOptionalAction, default=True,
                   help="score every label (default), or --no-difficult: leave out RADIal's 'Difficult' labels, "
                        "its easy mode; writes eval_{split}_easy.*")
    d.add_argument("--show", type=int, default=0, metavar="K", help="draw K frames spread evenly over the split")
    d.set_defaults(func=run_detect)
