"""``radarpc evaluate-points``: Chamfer distance and EMD of predicted point clouds, per scene.

::

    radarpc evaluate-points PRED_DIR --data ROOT --split test [--emd-points 2048] [--emd-seed 0] [--force]

For every paired radar frame of the split, reads ``PRED_DIR/{run}/{frame:06d}.npy`` (float32
``(N, 3)``, radar frame; the layout ``radarpc baseline os-cfar`` writes) and scores it against
the reader's LiDAR cropped to the radar frustum (:mod:`radarpc.eval.pointsets`, batched):

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

__all__ = ["add_parser", "check_index", "run_evaluate_points"]


def _pairs(ds, pred_dir: Path):
    from radarpc.cli.baseline import prediction_path
    from radarpc.eval.pointsets import CloudPair
    from radarpc.io import DataFileError, load_array

    for i in range(len(ds)):
        k, ri, _ = ds.index[i]
        run = ds.runs[k]
        path = prediction_path(pred_dir, run.name, ri)
        if not path.is_file():
            raise DataFileError(path, f"prediction for run {run.name!r} frame {ri} is missing "
                                      f"(expected float32 (N, 3) points, one file per frame of the split)")
        pred = load_array(path, shape=(None, 3), complex_=False)
        if pred.shape[0] == 0:
            raise DataFileError(path, "prediction is empty: Chamfer distance and EMD need at least one point")
        yield CloudPair(run.name, int(ri), pred, ds.lidar_points(i))


def check_index(pred_dir: Path, data: str | Path, split: str) -> None:
    """Raise ``ValueError`` unless ``pred_dir/index.json`` names the dataset root ``data`` and ``split``.

    Roots are compared after ``Path.resolve()``; a missing or unreadable index is an error too.
    """
    import json

    from radarpc.io import DataFileError

    path = pred_dir / "index.json"
    if not path.is_file():
        raise DataFileError(path, "prediction index is missing: cannot check which dataset root and split the "
                                  "predictions were made on (pass --force to score them anyway)")
    try:
        idx = json.loads(path.read_text())
        root, sp = idx["root"], idx["split"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise DataFileError(path, f"expected a JSON object with 'root' and 'split' ({e})") from e
    if Path(root).resolve() != Path(data).resolve():
        raise ValueError(f"{path} says the predictions were made on root {root!r}, but --data is {str(data)!r} "
                         "(pass --force to score them anyway)")
    if sp != split:
        raise ValueError(f"{path} says the predictions were made on split {sp!r}, but --split is {split!r} "
                         "(pass --force to score them anyway)")


def run_evaluate_points(args: argparse.Namespace) -> int:
    from radarpc.data.coloradar import ColoRadar, scene_of_run
    from radarpc.eval.pointsets import evaluate_clouds
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
    report = evaluate_clouds(_pairs(ds, pred_dir), scene_of_run, emd_points=args.emd_points,
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
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    p.add_argument("--emd-points", type=int, default=2048,
                   help="EMD subset size n: min(n, |gt|) LiDAR and min(n, |pred|) predicted points (default 2048)")
    p.add_argument("--emd-seed", type=int, default=0, help="seed of the EMD subsets (default 0)")
    p.add_argument("--force", action="store_true",
                   help="score even if PRED_DIR/index.json is missing or names another root/split")
    p.set_defaults(func=run_evaluate_points)
