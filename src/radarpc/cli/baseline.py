"""``radarpc baseline os-cfar``: point clouds from the radar cube by 3-D OS-CFAR, tuned on a split.

::

    radarpc baseline os-cfar ROOT --split test --out preds/oscfar [--tune-split val] [--config FILE]

Writes into ``--out``:

* ``config.yaml`` -- the OS-CFAR parameters used (tuned, given, or reused when resuming);
* ``tuning.json`` -- mean Chamfer distance of every candidate of the grid search (when tuned);
* ``{run}/{frame:06d}.npy`` -- float32 ``(N, 3)`` points in the single-chip radar frame, one per
  paired radar frame of the split (``frame`` = index of the ADC frame in its run);
* ``index.json`` -- one entry per frame: run, scene, frame, paired LiDAR scan index and file,
  timestamps, prediction file and point count.

Every file is written atomically. A rerun into the same folder keeps the existing
``config.yaml`` (unless ``--config`` or ``--retune`` is given) and skips frames already written
with it, so an interrupted job resumes.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from radarpc.io import atomic_write, load_array, save_npy_atomic

__all__ = ["add_parser", "run_oscfar", "prediction_path"]


def prediction_path(out: str | Path, run: str, frame: int) -> Path:
    """``out/{run}/{frame:06d}.npy``: where a method's cloud for a radar frame lives."""
    return Path(out) / run / f"{int(frame):06d}.npy"


def _tuning_frames(ds, max_frames: int):
    n = len(ds)
    picks = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int)) if n else []
    for i in picks:
        yield ds.cube(int(i)).intensity_db, ds.lidar_points(int(i))


def _axes(ds):
    from radarpc.rald.oscfar_baseline import CubeAxes

    cube = ds.cube(0)
    return CubeAxes.from_radians(cube.range_m, cube.azimuth_rad, cube.elevation_rad)


def run_oscfar(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from radarpc.data.coloradar import ColoRadar
    from radarpc.rald.oscfar_baseline import (
        OSCFARConfig,
        TuningGrid,
        detect_points,
        load_config,
        save_config,
        tune_oscfar,
    )

    out = Path(args.out)
    cfg_path = out / "config.yaml"
    if args.max_tune_frames < 1:
        raise ValueError(f"--max-tune-frames must be >= 1, got {args.max_tune_frames}")
    ds = ColoRadar(args.root, args.split, cube_size=None)
    if len(ds) == 0:
        raise ValueError(f"split {args.split!r} of {args.root} has no paired radar/LiDAR frame")
    axes = _axes(ds)

    if args.config is not None:
        cfg, how = load_config(args.config), f"given ({args.config})"
    elif cfg_path.is_file() and not args.retune:
        cfg, how = load_config(cfg_path), f"reused ({cfg_path})"
    else:
        val = ColoRadar(args.root, args.tune_split, cube_size=None)
        if len(val) == 0:
            raise ValueError(f"tuning split {args.tune_split!r} of {args.root} has no paired frame; "
                             "pass --tune-split with another split or --config FILE")
        grid = TuningGrid() if not args.quick_tune else TuningGrid(
            windows=((9, 3, 3),), guards=((3, 1, 1),), ranks=(0.75,), taus_db=(4.0, 8.0, 12.0), angle_bins=(None,))
        res = tune_oscfar(_tuning_frames(val, args.max_tune_frames), axes, grid, progress=True)
        cfg, how = res.best, f"tuned on {res.n_frames} {args.tune_split} frames (mean CD {res.best_chamfer:.3f} m)"
        table = [{"config": c.to_dict(), "chamfer_m": cd, "points_per_frame": npts} for c, cd, npts in res.table]
        with atomic_write(out / "tuning.json", "w") as f:
            json.dump({"split": args.tune_split, "frames": res.n_frames, "best": cfg.to_dict(),
                       "best_chamfer_m": res.best_chamfer, "candidates": table}, f, indent=1)
    same = cfg_path.is_file() and load_config(cfg_path) == cfg
    if not same:
        save_config(cfg_path, cfg, method="os-cfar", root=str(args.root), split=args.split,
                    tune_split=args.tune_split, how=how)
    print(f"OS-CFAR config {how}: {cfg}")

    index = []
    n_done = 0
    for i in tqdm(range(len(ds)), desc=f"OS-CFAR {args.split}", unit="frame"):
        k, ri, li = ds.index[i]
        run = ds.runs[k]
        path = prediction_path(out, run.name, ri)
        if same and path.is_file():
            pts = load_array(path, shape=(None, 3))   # resume: keep a valid earlier result
        else:
            pts = detect_points(ds.cube(i).intensity_db, axes, cfg).cpu().numpy().astype(np.float32)
            save_npy_atomic(path, pts)
            n_done += 1
        index.append({"run": run.name, "scene": run.scene, "frame": int(ri), "lidar_index": int(li),
                      "lidar_file": str(run.lidar_path(li)), "radar_time": float(run.radar_timestamps[ri]),
                      "lidar_time": float(run.lidar_timestamps[li]),
                      "file": str(path.relative_to(out)), "n_points": int(pts.shape[0])})
    with atomic_write(out / "index.json", "w") as f:
        json.dump({"method": "os-cfar", "root": str(Path(args.root).resolve()), "split": args.split,
                   "frames": index}, f, indent=1)
    print(f"wrote {n_done} new point clouds ({len(index)} frames) to {out}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("baseline", help="classical baselines that turn radar frames into point clouds",
                       description=__doc__.splitlines()[0])
    kinds = p.add_subparsers(dest="kind", required=True, metavar="METHOD")
    q = kinds.add_parser("os-cfar", help="3-D OS-CFAR on the radar cube, tuned for Chamfer distance",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("root", help="ColoRadar root (real or simulated)")
    q.add_argument("--split", default="test", choices=("train", "val", "test", "all"), help="frames to predict")
    q.add_argument("--out", required=True, help="prediction folder")
    q.add_argument("--tune-split", default="val", choices=("train", "val", "test", "all"),
                   help="split whose frames tune the parameters (default val)")
    q.add_argument("--max-tune-frames", type=int, default=32,
                   help="evenly spaced frames of the tuning split used by the grid search (default 32)")
    q.add_argument("--config", default=None, help="use this config.yaml instead of tuning")
    q.add_argument("--retune", action="store_true", help="tune again even if OUT/config.yaml exists")
    q.add_argument("--quick-tune", action="store_true", help="a 3-candidate grid (for smoke tests)")
    q.set_defaults(func=run_oscfar)
