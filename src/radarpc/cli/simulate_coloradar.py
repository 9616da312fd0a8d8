"""``radarpc simulate coloradar``: write a simulated dataset in ColoRadar's on-disk layout."""
from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def add_parser(kinds) -> argparse.ArgumentParser:
    """Register ``coloradar`` on the ``simulate`` sub-command's parsers; sets ``func``."""
    from radarpc.cli.options import SCENE_KINDS

    p = kinds.add_parser(
        "coloradar", help="ColoRadar layout: single-chip ADC, cascade heatmaps, LiDAR, poses, calib/ (resumable)",
        description="Simulate indoor/outdoor runs of a handheld or wheeled rig carrying the AWR1843 "
                    "single chip, the 12x16 cascade and a 64-beam LiDAR, and write them in ColoRadar's "
                    "layout (one folder {scene}_run{k} per run, calib/ at the root). Rerunning with the "
                    "same settings resumes a partial output.")
    p.add_argument("--out", required=True, help="dataset root to write")
    p.add_argument("--scenes", default="hallway,lab,classroom,outdoor",
                   help=f"comma-separated scene kinds from {','.join(SCENE_KINDS)} (default hallway,lab,classroom,outdoor)")
    p.add_argument("--runs-per-scene", type=int, default=3, help="runs per scene (default 3: train/val/test)")
    p.add_argument("--frames", type=int, default=200, help="radar frames per run (default 200, ~20 s)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    p.add_argument("--lidar-beams", type=int, default=64, help="LiDAR beams (default 64, OS1-64-like)")
    p.add_argument("--lidar-azimuth-steps", type=int, default=1024, help="LiDAR azimuth steps (default 1024)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a non-empty folder that is not a matching partial run (its "
                        "simulation.json, calib/ and this simulation's run folders are deleted first)")
    p.add_argument("--device", default="cpu", help="synthesis device, e.g. cpu or cuda (default cpu)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Write the dataset described by ``args``; returns the exit code."""
    from radarpc.cli.text import plural
    from radarpc.machine import check_device

    from radarpc.sim.coloradar_writer import write_coloradar

    scenes = [s.strip() for s in str(args.scenes).split(",") if s.strip()]
    check_device(args.device, "--device")
    counts = {}
    root = write_coloradar(args.out, scenes, args.runs_per_scene, args.frames, args.seed,
                           overwrite=args.overwrite, lidar_beams=args.lidar_beams,
                           lidar_azimuth_steps=args.lidar_azimuth_steps, device=args.device,
                           progress=not args.no_progress, on_finish=lambda w, k: counts.update(written=w, kept=k))
    print(f"{root}: {plural(len(scenes), 'scene')} x {plural(args.runs_per_scene, 'run')} x "
          f"{plural(args.frames, 'radar frame')} ({', '.join(scenes)}); "
          f"{plural(counts['written'], 'radar frame or LiDAR scan', 'radar frames and LiDAR scans')} simulated "
          f"now, {counts['kept']} kept from an earlier run")
    return 0
