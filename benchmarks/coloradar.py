"""ColoRadar-side throughput: simulated frames/s, Chamfer and EMD time on 30k-point clouds. Prints JSON.

Usage::

    python benchmarks/coloradar.py [--threads 2] [--points 30000] [--emd-points 2048] [--frames 4]

* ``chamfer_s``: :func:`radarpc.eval.pointsets.chamfer_distance` on two clouds of ``--points``
  points (best of ``--repeat``), KD-tree queries on all threads.
* ``emd_s``: :func:`radarpc.eval.pointsets.earth_movers_distance` (exact W1 by POT's network
  simplex) with subsets of ``--emd-points`` of both clouds; ``emd_sparse_pred_s`` with a 300-point
  prediction against the ``--emd-points`` ground-truth subset (the OS-CFAR case).
* ``chamfer_batch_s`` / ``emd_batch_s``: the batched API (:func:`chamfer_distance_batch`,
  :func:`earth_movers_distance_batch`) on ``--batch`` pairs in a pool of ``--threads`` threads.
* ``frustum_*``: voxelizing one cloud into RaLD's 318 x 720 x 80 grid (``RALD_GRID``) and drawing 10,000 queries.
* ``sim_frames_per_s``: frames written per second by
  :func:`radarpc.sim.coloradar_writer.write_coloradar` (one scene, one run, ``--frames`` frames,
  including LiDAR ray casting and file writing), measured after one warm-up call.
"""
from __future__ import annotations

import argparse
import datetime
import inspect
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from radarpc.eval.pointsets import (
    chamfer_distance,
    chamfer_distance_batch,
    earth_movers_distance,
    earth_movers_distance_batch,
)
from radarpc.rald.frustum import RALD_GRID, polar_to_cartesian, sample_queries, voxelize
from radarpc.machine import cpu_model


def _best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def _room_cloud(n: int, seed: int) -> np.ndarray:
    # Points on the walls, floor and ceiling of a 12 m x 8 m x 3 m room seen from the radar: a
    # LiDAR-like spatial distribution (2-D surfaces), not a uniform blob.
    rng = np.random.default_rng(seed)
    rae = np.stack([rng.uniform(0.5, 15.0, n), rng.uniform(-85, 85, n), rng.uniform(-18, 18, n)], 1)
    d = polar_to_cartesian(torch.from_numpy(rae)).numpy()
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    box_hi, box_lo = np.array([12.0, 4.0, 2.0]), np.array([-1.0, -4.0, -1.0])
    with np.errstate(divide="ignore"):
        t = np.where(u > 0, box_hi / u, box_lo / u)
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf).min(1)
    return (u * t[:, None]).astype(np.float32)


def _sim_rate(frames: int) -> dict:
    try:
        from radarpc.sim.coloradar_writer import write_coloradar
    except ImportError as e:   # the simulator is another stage; report instead of failing
        return {"sim_frames_per_s": None, "sim_note": f"simulator not importable: {e}"}
    sig = inspect.signature(write_coloradar)
    scenes = ["hallway"]
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        def run(sub: str, n: int) -> None:
            kwargs = dict(scenes=scenes, runs_per_scene=1, frames=n, seed=0)
            if "progress" in sig.parameters:
                kwargs["progress"] = False
            write_coloradar(Path(tmp) / sub, **kwargs)
        run("warm", 1)
        dt = _best(lambda: run("timed", frames), 1)
    out["sim_frames_per_s"] = frames / dt
    out["sim_frames"] = frames
    out["sim_scene"] = scenes[0]
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--points", type=int, default=30_000, help="points per cloud for CD/EMD")
    ap.add_argument("--emd-points", type=int, default=2048, help="EMD subset size")
    ap.add_argument("--frames", type=int, default=4, help="simulated frames to time (0: skip)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--batch", type=int, default=8, help="pairs of the batched CD/EMD timings")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    pred, gt = _room_cloud(args.points, 0), _room_cloud(args.points, 1)
    res: dict = {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "device": "cpu",
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "points": args.points,
        "chamfer_s": _best(lambda: chamfer_distance(pred, gt), args.repeat),
        "emd_points": args.emd_points,
        "emd_s": _best(lambda: earth_movers_distance(pred, gt, n=args.emd_points), args.repeat),
        "chamfer_m": chamfer_distance(pred, gt),
        "emd_m": earth_movers_distance(pred, gt, n=args.emd_points),
        "emd_sparse_pred_s": _best(lambda: earth_movers_distance(pred[:300], gt, n=args.emd_points), args.repeat),
    }
    preds = [_room_cloud(args.points, 10 + b) for b in range(args.batch)]
    gts = [_room_cloud(args.points, 100 + b) for b in range(args.batch)]
    res["batch"] = args.batch
    res["chamfer_batch_s"] = _best(lambda: chamfer_distance_batch(preds, gts, workers=args.threads), 1)
    res["emd_batch_s"] = _best(lambda: earth_movers_distance_batch(preds, gts, n=args.emd_points,
                                                                   workers=args.threads), 1)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for dev in devices:
        p = torch.from_numpy(gt).to(dev)
        res[f"frustum_voxelize_s_{dev}"] = _best(lambda: voxelize(RALD_GRID, p), args.repeat)
        occ = voxelize(RALD_GRID, p)
        res[f"frustum_queries_10k_s_{dev}"] = _best(lambda: sample_queries(occ, 10_000), args.repeat)
    res["frustum_occupied_cells"] = voxelize(RALD_GRID, gt).n_occupied
    if args.frames > 0:
        res.update(_sim_rate(args.frames))
    json.dump(res, sys.stdout, indent=1)
    print()
    return res


if __name__ == "__main__":
    main()
